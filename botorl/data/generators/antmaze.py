"""AntMaze data made here, in the D4RL recipe (tasks ``antmaze-<maze>-<diverse|play>-local``).

docs/antmaze.md describes the recipe and where botorl's version differs from Minari's files.
Facts cited below are from Farama-Foundation/minari-dataset-generation-scripts,
``scripts/antmaze/`` (``create_antmaze_dataset.py``, ``controller.py``), which made Minari's
``D4RL/antmaze/*``, and Gymnasium-Robotics' AntMaze. The MuJoCo model is the one ``AntMazeEnv``
builds, stepped with ``mujoco.mj_step(nstep=5)`` as ``AntEnv.step`` does (``ctrl = action``;
AntMaze ignores the ant's own termination), without Gymnasium's per-step cost (tests replay the
actions in the env). Deterministic for a seed.
"""

from __future__ import annotations

import math
import os
from functools import partial
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from botorl.data.dataset import Dataset
from botorl.envs.ant_goal import NumpyActor
from botorl.envs.antmaze import SUCCESS_RADIUS, layout, make_maze_env  # the mazes: botorl/envs/antmaze.py
from botorl.envs.pointmaze import cell_to_xy, free_cells, next_cell_table
from botorl.errors import BotorlError
from botorl.io import atomic_save_figure, pyplot

ACTION_NOISE = 0.2  # create_antmaze_dataset.py --action-noise
WAYPOINT_THRESHOLD = 0.45  # controller.py waypoint_threshold
WAYPOINT_JITTER = 0.2  # controller.py: cell centre - U(0, 1) * 0.2
SCALE = 4.0  # AntMaze maze_size_scaling
POSITION_NOISE = 0.25  # Gymnasium-Robotics position_noise_range (cells)
EPISODE_STEPS = 1000
FRAME_SKIP = 5

ASSET = Path(__file__).parent / "assets" / "ant_goal_actor.npz"


def cell_xy(maze_map, cell) -> np.ndarray:
    """Centre of a cell in AntMaze coordinates (Maze.cell_rowcol_to_xy; exact: multiples of 0.5)."""
    return SCALE * cell_to_xy(maze_map, cell)


def xy_cell(maze_map, xy) -> tuple[int, int]:
    """Maze.cell_xy_to_rowcol."""
    rows, cols = len(maze_map), len(maze_map[0])
    return (math.floor((rows * SCALE / 2 - xy[1]) / SCALE), math.floor((xy[0] + cols * SCALE / 2) / SCALE))


class WaypointController:
    """Follows the BFS planner's path of cells (``table``) to ``goal_xy`` with the goal-reaching
    ant ``policy`` (controller.py's rule), re-planning if the ant leaves the path."""

    def __init__(self, maze_map, table, policy, rng: np.random.Generator):
        self.maze_map, self.table, self.policy, self.rng = maze_map, table, policy, rng
        self.goal_cell = None

    def set_goal(self, goal_xy, xy) -> None:
        self.goal_xy = np.asarray(goal_xy, float)
        self.goal_cell = xy_cell(self.maze_map, self.goal_xy)
        self._plan(xy_cell(self.maze_map, xy))

    def _plan(self, cell) -> None:
        nxt = self.table[self.goal_cell]
        if cell not in nxt:  # in a wall cell (numerically): aim at the goal's path from the nearest
            cell = self.goal_cell
        path = [cell]
        while path[-1] != self.goal_cell:
            path.append(nxt[path[-1]])
        self.path = path
        self.index = 0
        self._advance()

    def _advance(self) -> None:
        """Aim at path[index + 1] (or the goal once in the goal cell)."""
        self.index = min(self.index + 1, len(self.path) - 1)
        if self.path[self.index] == self.goal_cell:
            self.waypoint = self.goal_xy
        else:
            self.waypoint = cell_xy(self.maze_map, self.path[self.index]) - self.rng.uniform(size=2) * WAYPOINT_JITTER

    def act(self, observation27, xy):
        """The policy's action towards the current waypoint, re-planned or advanced first."""
        cell = xy_cell(self.maze_map, xy)
        lo = max(self.index - 1, 0)
        if cell not in self.path[lo: self.index + 1]:
            self._plan(cell)
        if self.path[self.index] != self.goal_cell and np.sum((self.waypoint - xy) ** 2) <= WAYPOINT_THRESHOLD**2:
            self._advance()
        obs = np.concatenate([observation27, self.waypoint - xy]).astype(np.float32)
        return self.policy(obs[None])[0]

    def start(self, sim, goal_cell, start_cell) -> np.ndarray:
        """Reset ``sim`` near ``start_cell``, aim near ``goal_cell`` (the env's noise); returns the goal."""
        noise = POSITION_NOISE * SCALE
        goal = cell_xy(self.maze_map, goal_cell) + self.rng.uniform(-noise, noise, 2)
        xy = cell_xy(self.maze_map, start_cell) + self.rng.uniform(-noise, noise, 2)
        sim.reset(xy)
        self.set_goal(goal, xy)
        return goal

    def drive(self, sim, action_noise: float) -> np.ndarray:
        """Step ``sim`` with the waypoint action plus ``action_noise`` (Gaussian), clipped; returns it."""
        d = sim.data
        a = self.act(np.concatenate([d.qpos[2:], d.qvel]), d.qpos[:2].copy())
        if action_noise > 0:
            a = a + action_noise * self.rng.standard_normal(8)
        a = np.clip(a, -1.0, 1.0)
        sim.step(a)
        return a


def load_actor(path=None):
    path = Path(path or os.environ.get("BOTORL_ANT_ACTOR") or ASSET)
    if not path.exists():
        raise BotorlError(f"the goal-reaching ant's weights are missing ({path}); train them with `botorl train-ant "
                          f"--out runs/ant_goal` and point BOTORL_ANT_ACTOR at runs/ant_goal/actor.npz.")
    return NumpyActor.load(path)


class _Sim:
    """The AntMaze model stepped directly (see module docstring)."""

    def __init__(self, maze: str):
        env = make_maze_env(maze)
        self.model = env.ant_env.model
        self.data = mujoco.MjData(self.model)
        self.qpos0 = env.ant_env.init_qpos.copy()
        env.close()

    def reset(self, xy) -> None:
        d = self.data
        mujoco.mj_resetData(self.model, d)
        d.qpos[:] = self.qpos0
        d.qpos[:2] = xy
        mujoco.mj_forward(self.model, d)

    def step(self, action) -> None:
        self.data.ctrl[:] = action
        mujoco.mj_step(self.model, self.data, FRAME_SKIP)


def _controller(maze: str, actor, seed: int):
    """(layout, maze map, simulator, generator, waypoint controller) of a run on ``maze``."""
    spec = layout(maze)
    maze_map = [list(r) for r in spec.maze_map]
    policy = actor if actor is not None else load_actor()
    rng = np.random.default_rng(seed)
    return spec, maze_map, _Sim(maze), rng, WaypointController(maze_map, next_cell_table(maze_map), policy, rng)


def generate(maze: str, kind: str, steps: int, seed: int, progress: bool = True, *, actor=None,
             action_noise: float = ACTION_NOISE, episode_steps: int = EPISODE_STEPS) -> Dataset:
    """``steps`` transitions of the waypoint-following ant; see the module docstring."""
    if kind not in ("diverse", "play"):
        raise ValueError(f"kind must be 'diverse' or 'play', not {kind!r}")
    if steps <= 0 or episode_steps <= 0:
        raise ValueError(f"steps and episode_steps must be positive, got {steps} and {episode_steps}")
    spec, maze_map, sim, rng, ctl = _controller(maze, actor, seed)
    cells = free_cells(maze_map) if kind == "diverse" else list(spec.locations)
    eval_goal = cell_xy(maze_map, spec.eval_goal)

    def new_episode():
        while True:
            g = cells[rng.integers(len(cells))]
            s = cells[rng.integers(len(cells))]
            if np.linalg.norm(cell_xy(maze_map, g) - cell_xy(maze_map, s)) > 0.5 * SCALE:
                return ctl.start(sim, g, s)

    obs_qpos, next_qpos = np.empty((steps, 15)), np.empty((steps, 15))
    obs_qvel, next_qvel = np.empty((steps, 14)), np.empty((steps, 14))
    goals = np.empty((steps, 2))
    actions = np.empty((steps, 8))
    ends = np.arange(1, steps + 1) % episode_steps == 0
    d = sim.data
    for t in tqdm(range(steps), desc=f"antmaze-{maze}-{kind}", unit="step", mininterval=1.0, disable=not progress):
        if t % episode_steps == 0:
            goal = new_episode()
        obs_qpos[t], obs_qvel[t] = d.qpos, d.qvel
        actions[t] = ctl.drive(sim, action_noise)
        goals[t] = goal
        next_qpos[t], next_qvel[t] = d.qpos, d.qvel

    next_xy = next_qpos[:, :2]
    rewards = (np.sum((next_xy - eval_goal) ** 2, axis=1) <= SUCCESS_RADIUS**2).astype(np.float32)
    success = (np.sum((next_xy - goals) ** 2, axis=1) <= SUCCESS_RADIUS**2).astype(np.float32)
    terminals = rewards > 0
    # The 29-dim layout of the antmaze tasks: achieved_goal (x, y) then observation (27).
    observations = np.concatenate([obs_qpos, obs_qvel], axis=1)
    next_observations = np.concatenate([next_qpos, next_qvel], axis=1)
    return Dataset(
        observations=observations, actions=actions, rewards=rewards, next_observations=next_observations,
        terminals=terminals, episode_ends=ends | terminals,
        infos={"success": success, "qpos": next_qpos.astype(np.float32), "qvel": next_qvel.astype(np.float32),
               "goal": goals.astype(np.float32)},
        metadata={
            "source": f"generated: antmaze-{maze}-{kind}-local (steps={steps}, seed={seed})",
            "task": f"antmaze-{maze}-{kind}-local", "generator": "botorl.data.generators.antmaze",
            "steps": int(steps), "seed": int(seed), "maze": maze, "kind": kind, "action_noise": float(action_noise),
            "eval_start_cell": list(spec.eval_start), "eval_goal_cell": list(spec.eval_goal),
            "observation_layout": "achieved_goal (x, y), observation (qpos[2:], qvel)",
            # write_minari stores these slices of the flat rows as Minari dict observations
            # (D4RL/antmaze/* keys); desired_goal comes from infos["goal"].
            "minari_dict_obs": {"achieved_goal": [0, 2], "observation": [2, 29], "desired_goal": "infos:goal"},
        },
    )


generate_large_diverse = partial(generate, "large", "diverse")
generate_large_play = partial(generate, "large", "play")
generate_medium_diverse = partial(generate, "medium", "diverse")
generate_medium_play = partial(generate, "medium", "play")
generate_umaze_diverse = partial(generate, "umaze", "diverse")


# ------------------------------------------------------------------ the quality check


def evaluate_controller(maze: str = "large", episodes: int = 20, seed: int = 0, *, actor=None,
                        action_noise: float = 0.0, max_steps: int = EPISODE_STEPS, progress: bool = False) -> dict:
    """Success and steps to success of the waypoint controller from the evaluation start to the
    evaluation goal (with the evaluation env's noise), no action noise by default."""
    spec, _, sim, _, ctl = _controller(maze, actor, seed)
    results = []
    for ep in range(episodes):
        gxy = ctl.start(sim, spec.eval_goal, spec.eval_start)
        steps = None
        for t in range(max_steps):
            ctl.drive(sim, action_noise)
            if np.sum((sim.data.qpos[:2] - gxy) ** 2) <= SUCCESS_RADIUS**2:
                steps = t + 1
                break
        results.append(steps)
        if progress:
            print(f"episode {ep}: {'reached in ' + str(steps) + ' steps' if steps else 'failed'}", flush=True)
    ok = [s for s in results if s is not None]
    return {"maze": maze, "episodes": episodes, "success": len(ok) / episodes,
            "mean_steps_to_goal": float(np.mean(ok)) if ok else None, "steps": results,
            "action_noise": action_noise}


# ------------------------------------------------------------------ statistics and the coverage picture


def maze_of(ds) -> str | None:
    """The maze of a generated antmaze dataset (fresh or loaded from the cache), else None."""
    meta = ds.metadata.get("botorl") or ds.metadata
    antmaze = "antmaze" in str(meta.get("generator", "")) and meta.get("maze") in ("umaze", "medium", "large")
    return meta["maze"] if antmaze else None


def maze_stats(ds, maze: str | None = None) -> dict | None:
    """Coverage of the maze (free cells with at least 100 steps; our threshold, so a cell
    crossed once does not count) and the evaluation-goal rows of an antmaze dataset."""
    maze = maze or maze_of(ds)
    if maze is None:
        return None
    free = np.array(layout(maze).maze_map) == 0
    rows, cols = free.shape
    xy = np.asarray(ds.observations[:, :2])
    r = np.floor((rows * SCALE / 2 - xy[:, 1]) / SCALE).astype(int)  # xy_cell of every row
    c = np.floor((xy[:, 0] + cols * SCALE / 2) / SCALE).astype(int)
    ok = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
    counts = np.zeros((rows, cols), np.int64)
    np.add.at(counts, (r[ok], c[ok]), 1)
    covered = int(((counts >= 100) & free).sum())
    return {"maze": maze, "cells_free": int(free.sum()), "cells_covered": covered,
            "coverage": covered / int(free.sum()), "eval_goal_rows": int((ds.rewards > 0).sum())}


def plot_coverage(ds, path, maze: str | None = None, title: str | None = None, max_points: int = 200_000) -> Path:
    """The visited (x, y) over the maze map (walls grey), written atomically as a PNG."""
    plt = pyplot()
    maze = maze or maze_of(ds)
    if maze is None:
        raise BotorlError("`data plot` draws antmaze datasets made by botorl (their metadata name the maze); "
                          "this dataset names none.")
    spec = layout(maze)
    rows, cols = len(spec.maze_map), len(spec.maze_map[0])
    fig, ax = plt.subplots(figsize=(cols * 0.55 + 1, rows * 0.55 + 0.6))
    for r in range(rows):
        for c in range(cols):
            if spec.maze_map[r][c] == 1:
                x, y = cell_xy(spec.maze_map, (r, c))
                ax.add_patch(plt.Rectangle((x - SCALE / 2, y - SCALE / 2), SCALE, SCALE, color="0.55", lw=0))
    xy = np.asarray(ds.observations[:, :2])
    if len(xy) > max_points:
        xy = xy[np.random.default_rng(0).choice(len(xy), max_points, replace=False)]
    ax.scatter(xy[:, 0], xy[:, 1], s=0.2, alpha=0.15, color="tab:blue", rasterized=True)
    for cell, mark, colour in ((spec.eval_start, "o", "tab:green"), (spec.eval_goal, "*", "tab:red")):
        x, y = cell_xy(spec.maze_map, cell)
        ax.plot(x, y, mark, color=colour, ms=12, mec="k")
    ax.set(xlim=(-cols * SCALE / 2, cols * SCALE / 2), ylim=(-rows * SCALE / 2, rows * SCALE / 2), aspect="equal",
           xticks=[], yticks=[])
    st = maze_stats(ds, maze)
    ax.set_title(title or f"{len(ds):,} steps, {st['cells_covered']}/{st['cells_free']} cells covered", fontsize=9)
    fig.tight_layout()
    atomic_save_figure(fig, path, dpi=120)
    return Path(path)

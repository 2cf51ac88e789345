"""PointMaze data in the style of D4RL maze2d (tasks ``pointmaze-umaze|medium|large``).

The recipe is docs/tasks.md's ("Generated data"). The MuJoCo model is the one the env builds,
stepped directly with the env's own step semantics (velocity clipped to +-5 before the step,
``ctrl = action``, one step of 0.01 s), without Gymnasium's per-step overhead (tests replay the
actions in the env). Deterministic for a seed.
"""

from __future__ import annotations

import math
from functools import partial

import mujoco
import numpy as np
from tqdm import tqdm

from botorl.data.dataset import Dataset
from botorl.envs.pointmaze import MAZES, SUCCESS_RADIUS, cell_to_xy, free_cells, make_inner, next_cell_table

KP, KD, ACTION_NOISE = 10.0, 1.0, 0.5
GOAL_RADIUS = 0.45  # planner goal reached
GOAL_NOISE = 0.25  # uniform noise on planner goals and the start, in cells
MAX_STEPS_PER_GOAL = 1000
VEL_CLIP = 5.0  # PointEnv._clip_velocity


def generate(maze: str, steps: int, seed: int, progress: bool = True) -> Dataset:
    if maze not in MAZES:
        raise ValueError(f"unknown maze {maze!r}; one of {sorted(MAZES)}")
    if steps <= 0:
        raise ValueError("steps must be positive")
    spec = MAZES[maze]
    maze_map = spec.maze_map
    inner = make_inner(spec)
    model = inner.point_env.model
    data = mujoco.MjData(model)
    inner.close()
    table = next_cell_table(maze_map)
    cells = free_cells(maze_map)
    centres = {c: tuple(cell_to_xy(maze_map, c)) for c in cells}
    eval_gx, eval_gy = cell_to_xy(maze_map, spec.goal_cell)
    r2_eval, r2_goal = SUCCESS_RADIUS**2, GOAL_RADIUS**2

    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, ACTION_NOISE, size=(steps, 2))

    def draw_goal(avoid):
        while True:
            c = cells[rng.integers(len(cells))]
            if c != avoid:
                cx, cy = centres[c]
                return c, cx + rng.uniform(-GOAL_NOISE, GOAL_NOISE), cy + rng.uniform(-GOAL_NOISE, GOAL_NOISE)

    # the point at rest near a random free cell's centre, then a goal in another cell
    start = cells[rng.integers(len(cells))]
    data.qpos[0] = centres[start][0] + rng.uniform(-GOAL_NOISE, GOAL_NOISE)
    data.qpos[1] = centres[start][1] + rng.uniform(-GOAL_NOISE, GOAL_NOISE)
    mujoco.mj_forward(model, data)
    goal_cell, gx, gy = draw_goal(start)
    steps_on_goal = 0

    states = np.empty((steps + 1, 4))
    actions = np.empty((steps, 2))
    rewards = np.zeros(steps, dtype=np.float32)
    ends = np.zeros(steps, dtype=bool)
    qpos, qvel, ctrl = data.qpos, data.qvel, data.ctrl
    states[0] = (qpos[0], qpos[1], qvel[0], qvel[1])
    half_r, half_c = len(maze_map) / 2, len(maze_map[0]) / 2

    nextc = table[goal_cell]
    for t in tqdm(range(steps), desc=f"pointmaze-{maze}", unit="step", mininterval=1.0, disable=not progress):
        x, y, vx, vy = qpos[0], qpos[1], qvel[0], qvel[1]
        cell = (math.floor(half_r - y), math.floor(x + half_c))
        if cell == goal_cell:
            wx, wy = gx, gy
        else:
            wx, wy = centres[nextc.get(cell, goal_cell)]
        ax = KP * (wx - x) - KD * vx + noise[t, 0]
        ay = KP * (wy - y) - KD * vy + noise[t, 1]
        ax = -1.0 if ax < -1.0 else (1.0 if ax > 1.0 else ax)
        ay = -1.0 if ay < -1.0 else (1.0 if ay > 1.0 else ay)
        # PointEnv.step: clip the velocity, then one physics step with ctrl = action.
        qvel[0] = -VEL_CLIP if vx < -VEL_CLIP else (VEL_CLIP if vx > VEL_CLIP else vx)
        qvel[1] = -VEL_CLIP if vy < -VEL_CLIP else (VEL_CLIP if vy > VEL_CLIP else vy)
        ctrl[0], ctrl[1] = ax, ay
        mujoco.mj_step(model, data)
        nx, ny = qpos[0], qpos[1]
        states[t + 1] = (nx, ny, qvel[0], qvel[1])
        actions[t] = (ax, ay)
        if (nx - eval_gx) ** 2 + (ny - eval_gy) ** 2 <= r2_eval:
            rewards[t] = 1.0
        steps_on_goal += 1
        if (nx - gx) ** 2 + (ny - gy) ** 2 <= r2_goal or steps_on_goal >= MAX_STEPS_PER_GOAL:
            ends[t] = True
            goal_cell, gx, gy = draw_goal(goal_cell)
            nextc = table[goal_cell]
            steps_on_goal = 0

    terminals = rewards > 0
    return Dataset(
        observations=states[:-1], actions=actions, rewards=rewards, next_observations=states[1:], terminals=terminals,
        episode_ends=ends | terminals, infos={"success": rewards.copy()},
        metadata={"source": f"generated: pointmaze-{maze} (steps={steps}, seed={seed})", "task": f"pointmaze-{maze}",
                  "generator": "botorl.data.generators.pointmaze", "steps": int(steps), "seed": int(seed), "maze": maze,
                  "eval_start_cell": list(spec.start_cell), "eval_goal_cell": list(spec.goal_cell),
                  "observation_layout": "x, y, vx, vy"},
    )


generate_umaze = partial(generate, "umaze")
generate_medium = partial(generate, "medium")
generate_large = partial(generate, "large")

"""AntMaze, D4RL-style evaluation on the Gymnasium-Robotics ant (antmaze-large-*-v2).

- Maze: the large D4RL map (``maps.LARGE_MAZE``), start cell (1, 1), goal cell (7, 9), the
  D4RL antmaze-large evaluation pair (row, column in the map list).
- ``continuing_task=False``: reward 1 and termination when the ant's (x, y) is within 0.45 of
  the goal. D4RL used a radius of 0.5; we keep Gymnasium-Robotics' 0.45 because the Minari
  ``D4RL/antmaze/*-v1`` datasets (the offline data of these tasks) were regenerated in this env
  and label their rewards with 0.45.
- Goal and start positions get Gymnasium-Robotics' uniform noise (+-0.25 cells), as the
  evaluation env of the Minari datasets does.
- Observation (29, float32): ``achieved_goal`` (x, y) followed by the 27-dim ``observation``
  (ant qpos without x, y, then qvel). This is D4RL's layout; the Minari datasets store the
  same three keys, so a loader concatenates ``ANTMAZE_OBS_KEYS`` in this order.
- Horizon 1000 (D4RL antmaze evaluation; set by the registry).
- The medium and umaze maps (``layout``, ``make_antmaze_task``) are the antmaze-*-local tasks'
  (their data made by botorl.data.generators.antmaze): the same wrapper, D4RL's evaluation
  start and goal of that map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from botorl.envs.wrappers import TaskEnv, import_robotics

START_CELL = (1, 1)
GOAL_CELL = (7, 9)
ANTMAZE_OBS_KEYS = ("achieved_goal", "observation")
OBS_DIM = 29
ACTION_DIM = 8
SUCCESS_RADIUS = 0.45


class AntMazeTask(TaskEnv):
    def _reset_options(self):
        return {"reset_cell": np.array(START_CELL), "goal_cell": np.array(GOAL_CELL)}

    def _observe(self, obs):
        return np.concatenate([obs["achieved_goal"], obs["observation"]])

    def _task_step(self, obs, reward, terminated, info):
        success = bool(info.get("success", False))
        return (1.0 if success else 0.0), success, float(success)


def make_antmaze(seed: int | None = None) -> AntMazeTask:
    import_robotics()
    from gymnasium_robotics.envs.maze import maps
    from gymnasium_robotics.envs.maze.ant_maze_v4 import AntMazeEnv

    inner = AntMazeEnv(
        maze_map=[list(row) for row in maps.LARGE_MAZE],
        reward_type="sparse",
        continuing_task=False,
        reset_target=False,
    )
    return AntMazeTask(inner, OBS_DIM, seed)


# ------------------------------------------------------------------ the other mazes (data made by botorl)
@dataclass(frozen=True)
class AntMazeLayout:
    name: str
    maze_map: tuple[tuple[int, ...], ...]  # 1 = wall, 0 = free
    locations: tuple[tuple[int, int], ...]  # "play": hand-picked goal/start cells
    eval_start: tuple[int, int]
    eval_goal: tuple[int, int]


def _layouts() -> dict[str, AntMazeLayout]:
    import_robotics()
    from gymnasium_robotics.envs.maze import maps

    def parse(m):
        walls = tuple(tuple(1 if c == 1 else 0 for c in row) for row in m)
        picked = tuple((r, c) for r, row in enumerate(m) for c, v in enumerate(row) if v in ("c", "g", "r"))
        return walls, picked

    out = {}
    # evaluation start/goal: D4RL's (Minari EVAL_ENV_MAPS 'r'/'g' cells)
    for name, grid, picked_grid, start, goal in (
        ("umaze", maps.U_MAZE, None, (3, 1), (1, 1)),
        ("medium", maps.MEDIUM_MAZE, maps.MEDIUM_MAZE_DIVERSE_GR, (1, 1), (6, 6)),
        ("large", maps.LARGE_MAZE, maps.LARGE_MAZE_DIVERSE_GR, (1, 1), (7, 9)),
    ):
        walls, _ = parse(grid)
        picked = parse(picked_grid)[1] if picked_grid is not None else (start, goal)
        out[name] = AntMazeLayout(name, walls, picked, start, goal)
    return out


def layout(maze: str) -> AntMazeLayout:
    layouts = _layouts()
    if maze not in layouts:
        raise ValueError(f"unknown maze {maze!r}; one of {sorted(layouts)}")
    return layouts[maze]




def make_antmaze_task(maze: str, seed: int | None = None):
    """The D4RL-style evaluation env on the medium or umaze map (the large map's is
    ``botorl.envs.antmaze.make_antmaze``): the same wrapper, this maze's start and goal."""
    import_robotics()
    from gymnasium_robotics.envs.maze.ant_maze_v4 import AntMazeEnv

    spec = layout(maze)

    class _Task(AntMazeTask):
        def _reset_options(self):
            return {"reset_cell": np.array(spec.eval_start), "goal_cell": np.array(spec.eval_goal)}

    inner = AntMazeEnv(maze_map=[list(r) for r in spec.maze_map], reward_type="sparse", continuing_task=False,
                       reset_target=False)
    return _Task(inner, OBS_DIM, seed)

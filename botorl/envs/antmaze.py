"""AntMaze, D4RL-style evaluation on the Gymnasium-Robotics ant (antmaze-large-*-v2).

- D4RL's evaluation start and goal cells per map (``layout``); reward 1 and termination within
  0.45 of the goal: D4RL used 0.5, but the Minari ``D4RL/antmaze/*-v1`` datasets were
  regenerated in this env and label their rewards with 0.45. Goal and start get
  Gymnasium-Robotics' +-0.25-cell noise, as the Minari datasets' evaluation env does.
- Observation (29): ``achieved_goal`` (x, y) then the 27-dim ``observation``: D4RL's layout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from botorl.envs.pointmaze import MAZES
from botorl.envs.wrappers import TaskEnv, import_robotics

OBS_DIM = 29
SUCCESS_RADIUS = 0.45


class AntMazeTask(TaskEnv):
    start_cell, goal_cell = (1, 1), (7, 9)  # the large map's evaluation pair

    def _reset_options(self):
        return {"reset_cell": np.array(self.start_cell), "goal_cell": np.array(self.goal_cell)}

    def _observe(self, obs):
        return np.concatenate([obs["achieved_goal"], obs["observation"]])


@dataclass(frozen=True)
class AntMazeLayout:
    maze_map: tuple[tuple[int, ...], ...]  # 1 = wall, 0 = free
    locations: tuple[tuple[int, int], ...]  # "play": hand-picked goal/start cells
    eval_start: tuple[int, int]
    eval_goal: tuple[int, int]


def layout(maze: str) -> AntMazeLayout:
    """A maze's walls, its "play" cells (Gymnasium-Robotics' 'c'/'g'/'r' marks; umaze: the
    evaluation pair) and D4RL's evaluation start and goal (pointmaze's ``MAZES``)."""
    if maze not in MAZES:
        raise ValueError(f"unknown maze {maze!r}; one of {sorted(MAZES)}")
    maps = import_robotics("gymnasium_robotics.envs.maze.maps")
    spec = MAZES[maze]
    picked_grid = {"medium": maps.MEDIUM_MAZE_DIVERSE_GR, "large": maps.LARGE_MAZE_DIVERSE_GR}.get(maze)
    picked = (spec.start_cell, spec.goal_cell) if picked_grid is None else tuple(
        (r, c) for r, row in enumerate(picked_grid) for c, v in enumerate(row) if v in ("c", "g", "r"))
    return AntMazeLayout(tuple(map(tuple, spec.maze_map)), picked, spec.start_cell, spec.goal_cell)


def make_maze_env(maze: str, *, continuing_task: bool = True):
    """Gymnasium-Robotics' AntMazeEnv on the maze's wall map (no goal/reset marks)."""
    return import_robotics("gymnasium_robotics.envs.maze.ant_maze_v4").AntMazeEnv(
        maze_map=[list(r) for r in layout(maze).maze_map], reward_type="sparse", continuing_task=continuing_task,
        reset_target=False)


def make_antmaze_task(maze: str, seed: int | None = None) -> AntMazeTask:
    """The D4RL-style evaluation env on a map: the same wrapper, this maze's start and goal."""
    spec = layout(maze)
    # The class name is recorded in a mid-episode env state (botorl.envs.state): "_Task" off the large map.
    cls = AntMazeTask if maze == "large" else type(
        "_Task", (AntMazeTask,), {"start_cell": spec.eval_start, "goal_cell": spec.eval_goal})
    return cls(make_maze_env(maze, continuing_task=False), OBS_DIM, seed)

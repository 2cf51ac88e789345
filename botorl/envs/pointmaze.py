"""PointMaze with the D4RL maze2d maps: a fixed start, a fixed goal, sparse reward; a small
stand-in for antmaze (data: ``botorl.data.generators.pointmaze``).

- The goal is the goal cell's centre exactly (Gymnasium-Robotics' +-0.25 goal noise is removed
  so the offline data, labelled against this same point, reward exactly what evaluation
  rewards); the start keeps its noise. Reward 1 and termination within 0.45 of the goal.
- Observation (4): (x, y, vx, vy); the goal is fixed, so it is not observed.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from botorl.envs.wrappers import TaskEnv, import_robotics

SUCCESS_RADIUS = 0.45
OBS_DIM = 4


@dataclass(frozen=True)
class MazeSpec:
    name: str
    start_cell: tuple[int, int]
    goal_cell: tuple[int, int]

    @property
    def maze_map(self) -> list[list[int]]:
        maps = import_robotics("gymnasium_robotics.envs.maze.maps")
        grid = {"umaze": maps.U_MAZE, "medium": maps.MEDIUM_MAZE, "large": maps.LARGE_MAZE}[self.name]
        return [[int(c) for c in row] for row in grid]


MAZES = {
    "umaze": MazeSpec("umaze", start_cell=(3, 1), goal_cell=(1, 1)),
    "medium": MazeSpec("medium", start_cell=(1, 1), goal_cell=(6, 6)),
    "large": MazeSpec("large", start_cell=(1, 1), goal_cell=(7, 9)),
}


def cell_to_xy(maze_map, cell) -> np.ndarray:
    """Cell (row, col) -> centre (x, y), Gymnasium-Robotics' convention (scale 1, centred, y up)."""
    rows, cols = len(maze_map), len(maze_map[0])
    return np.array([(cell[1] + 0.5) - cols / 2, rows / 2 - (cell[0] + 0.5)])


def free_cells(maze_map) -> list[tuple[int, int]]:
    return [(i, j) for i, row in enumerate(maze_map) for j, c in enumerate(row) if c != 1]


def next_cell_table(maze_map) -> dict[tuple[int, int], dict[tuple[int, int], tuple[int, int]]]:
    """``table[goal][cell]`` = the neighbour of ``cell`` on a shortest path to ``goal`` (BFS
    over free cells, 4-connected); ``goal`` maps to itself."""
    cells = set(free_cells(maze_map))
    table = {}
    for goal in cells:
        nxt = {goal: goal}
        queue = deque([goal])
        while queue:
            c = queue.popleft()
            for d in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                n = (c[0] + d[0], c[1] + d[1])
                if n in cells and n not in nxt:
                    nxt[n] = c  # from n, step towards c
                    queue.append(n)
        table[goal] = nxt
    return table


class PointMazeTask(TaskEnv):
    def __init__(self, env, spec: MazeSpec, seed=None):
        super().__init__(env, OBS_DIM, seed)
        self.spec_ = spec
        self.goal_xy = cell_to_xy(spec.maze_map, spec.goal_cell)

    def _reset_options(self):
        return {"reset_cell": np.array(self.spec_.start_cell), "goal_cell": np.array(self.spec_.goal_cell)}

    def _after_reset(self, obs, info):
        inner = self.env.unwrapped
        inner.goal = self.goal_xy.copy()  # drop the goal noise (see module docstring)
        inner.update_target_site_pos()
        return {**obs, "desired_goal": self.goal_xy.copy()}

    def _observe(self, obs):
        return obs["observation"]

    def _task_step(self, obs, reward, terminated, info):
        success = bool(np.linalg.norm(obs["achieved_goal"] - self.goal_xy) <= SUCCESS_RADIUS)
        return float(success), success, float(success)

    def set_state(self, qpos, qvel) -> None:
        """Put the point at (x, y) with velocity (vx, vy) (tests replay generated data)."""
        self.env.unwrapped.point_env.set_state(np.asarray(qpos, float), np.asarray(qvel, float))


def make_inner(spec: MazeSpec):
    return import_robotics("gymnasium_robotics.envs.maze.point_maze").PointMazeEnv(
        maze_map=spec.maze_map, reward_type="sparse", continuing_task=False, reset_target=False)


def make_pointmaze(name: str, seed: int | None = None) -> PointMazeTask:
    spec = MAZES[name]
    return PointMazeTask(make_inner(spec), spec, seed)

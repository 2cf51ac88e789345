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
"""

from __future__ import annotations

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

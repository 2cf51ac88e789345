"""Franka kitchen as D4RL's kitchen-partial-v0 / kitchen-mixed-v0 (d4rl/kitchen/__init__.py's
sub-tasks), on ``FrankaKitchen-v1``: the reward is the number of target sub-tasks done at this
step (0-4, as in the D4RL datasets), termination when all 4 are done at once, ``info["success"]`` =
reward / 4; the observation (59) is the env's ``observation`` entry only (the goals are constants
or copies of object qpos), with the observation noise the Minari datasets were recorded with.
"""

from __future__ import annotations

from botorl.envs import compat
from botorl.envs.wrappers import TaskEnv, import_robotics

PARTIAL_TASKS = ("microwave", "kettle", "light switch", "slide cabinet")
MIXED_TASKS = ("microwave", "kettle", "bottom burner", "light switch")
OBS_DIM = 59


class KitchenTask(TaskEnv):
    def __init__(self, env, tasks, seed=None):
        super().__init__(env, OBS_DIM, seed)
        self.tasks = tuple(tasks)

    def _observe(self, obs):
        return obs["observation"]

    def _task_step(self, obs, reward, terminated, info):
        n_done = int(round(reward))
        return float(n_done), n_done == len(self.tasks), n_done / len(self.tasks)


def make_kitchen(tasks, seed: int | None = None) -> KitchenTask:
    compat.apply()
    inner = import_robotics("gymnasium_robotics.envs.franka_kitchen").KitchenEnv(
        tasks_to_complete=list(tasks),
        terminate_on_tasks_completed=False,  # we terminate when all are done at once
        remove_task_when_completed=False,
    )
    return KitchenTask(inner, tasks, seed)

"""Franka kitchen as D4RL's kitchen-partial-v0 / kitchen-mixed-v0, on ``FrankaKitchen-v1``.

- Target sub-tasks (D4RL's registrations, checked against d4rl/kitchen/__init__.py):
  kitchen-partial-v0 = ``KitchenMicrowaveKettleLightSliderV0``, kitchen-mixed-v0 =
  ``KitchenMicrowaveKettleBottomBurnerLightV0`` (``PARTIAL_TASKS``, ``MIXED_TASKS``).
- ``remove_task_when_completed=False``: the env's reward is the number of target sub-tasks
  whose objects are within 0.3 of their goal at this step (0-4), the reward the D4RL datasets
  (and WSRL's fork) carry. Termination when all 4 are done at the same step;
  ``info["success"]`` = reward / 4, read at an episode's last step (success_mode "last").
- Observation (59, float32): the env's ``observation`` entry only (robot qpos and qvel, object
  qpos and qvel): the desired goal is a constant of the task and the achieved goal a
  (noise-free) copy of object qpos. Gymnasium-Robotics' default observation noise, with which
  the Minari kitchen datasets were recorded.
- mujoco >= 3.12 needs ``botorl.envs.compat.apply()`` (applied here at make time).
"""

from __future__ import annotations

from botorl.envs import compat
from botorl.envs.wrappers import TaskEnv, import_robotics

PARTIAL_TASKS = ("microwave", "kettle", "light switch", "slide cabinet")
MIXED_TASKS = ("microwave", "kettle", "bottom burner", "light switch")
KITCHEN_OBS_KEYS = ("observation",)
OBS_DIM, ACTION_DIM = 59, 9


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
    import_robotics()
    from gymnasium_robotics.envs.franka_kitchen import KitchenEnv

    inner = KitchenEnv(
        tasks_to_complete=list(tasks),
        terminate_on_tasks_completed=False,  # we terminate when all are done at once
        remove_task_when_completed=False,
    )
    return KitchenTask(inner, tasks, seed)

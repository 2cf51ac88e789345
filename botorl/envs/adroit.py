"""Adroit "binary" tasks as Cal-QL defines them (pen-binary-v0, door-binary-v0).

Wraps the plain ``AdroitHandPen-v1`` / ``AdroitHandDoor-v1`` (not the ``Sparse`` variants,
whose reward is +10 / -0.1 and whose pen horizon is 200):

- reward = success - 1, i.e. -1 before and 0 at the goal;
- the episode terminates at the first success;
- success: door, hinge angle ``obs[28] >= 1.35`` (the env's own ``goal_achieved``); pen, the
  env's ``goal_achieved`` (pen within 0.075 of the target and orientation similarity > 0.95);
- observations as the env gives them: door 39, pen 45 dims (Cal-QL's dims);
- horizons 100 (pen) and 200 (door), set by the registry.
"""

from __future__ import annotations

from botorl.envs.wrappers import TaskEnv, import_robotics

DOOR_OBS_DIM, PEN_OBS_DIM = 39, 45
DOOR_ACTION_DIM, PEN_ACTION_DIM = 28, 24
DOOR_SUCCESS_ANGLE = 1.35


class AdroitBinaryTask(TaskEnv):
    def _observe(self, obs):
        return obs

    def _task_step(self, obs, reward, terminated, info):
        success = bool(info.get("success", False))
        return float(success) - 1.0, success, float(success)


def make_door(seed: int | None = None) -> AdroitBinaryTask:
    import_robotics()
    from gymnasium_robotics.envs.adroit_hand.adroit_door import AdroitHandDoorEnv

    return AdroitBinaryTask(AdroitHandDoorEnv(reward_type="dense"), DOOR_OBS_DIM, seed)


def make_pen(seed: int | None = None) -> AdroitBinaryTask:
    import_robotics()
    from gymnasium_robotics.envs.adroit_hand.adroit_pen import AdroitHandPenEnv

    return AdroitBinaryTask(AdroitHandPenEnv(reward_type="dense"), PEN_OBS_DIM, seed)

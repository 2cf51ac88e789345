"""Adroit "binary" tasks as Cal-QL defines them (pen-binary-v0, door-binary-v0), on the plain
``AdroitHandPen/Door-v1`` (not the ``Sparse`` variants: +10 / -0.1 rewards, pen horizon 200):
reward = success - 1, termination at the first success (the env's ``goal_achieved``; door: hinge
``obs[28] >= 1.35``), observations as the env gives them.
"""

from __future__ import annotations

from botorl.envs.wrappers import TaskEnv, import_robotics

DOOR_OBS_DIM, PEN_OBS_DIM = 39, 45
DOOR_SUCCESS_ANGLE = 1.35


class AdroitBinaryTask(TaskEnv):
    reward_offset = -1.0


def make_door(seed: int | None = None) -> AdroitBinaryTask:
    door = import_robotics("gymnasium_robotics.envs.adroit_hand.adroit_door").AdroitHandDoorEnv
    return AdroitBinaryTask(door(reward_type="dense"), DOOR_OBS_DIM, seed)


def make_pen(seed: int | None = None) -> AdroitBinaryTask:
    pen = import_robotics("gymnasium_robotics.envs.adroit_hand.adroit_pen").AdroitHandPenEnv
    return AdroitBinaryTask(pen(reward_type="dense"), PEN_OBS_DIM, seed)

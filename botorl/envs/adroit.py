"""Adroit "binary" tasks as Cal-QL defines them (pen-binary-v0, door-binary-v0), on the plain
``AdroitHandPen/Door-v1`` (not the ``Sparse`` variants: +10 / -0.1 rewards, pen horizon 200):
reward = success - 1, termination at the first success (the env's ``goal_achieved``; door: hinge
``obs[28] >= 1.35``), observations as the env gives them.
"""

from __future__ import annotations

from botorl.envs.wrappers import TaskEnv, import_robotics

OBS_DIM = {"door": 39, "pen": 45}
DOOR_SUCCESS_ANGLE = 1.35


class AdroitBinaryTask(TaskEnv):
    reward_offset = -1.0


def make_adroit(hand: str, seed: int | None = None) -> AdroitBinaryTask:
    """The binary task on ``AdroitHand<Door|Pen>Env``: ``hand`` "door" or "pen"."""
    module = import_robotics(f"gymnasium_robotics.envs.adroit_hand.adroit_{hand}")
    return AdroitBinaryTask(getattr(module, f"AdroitHand{hand.title()}Env")(reward_type="dense"), OBS_DIM[hand], seed)

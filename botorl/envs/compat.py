"""Compatibility patch: FrankaKitchen-v1 (gymnasium-robotics 1.4.2) under mujoco >= 3.12.

gymnasium_robotics.utils.mujoco_utils' joint helpers check ``model.jnt_type[i] in
(mjJNT_HINGE, mjJNT_SLIDE)``; since mujoco 3.12 ``np.int32(3) in (mjJNT_HINGE, ...)`` is False,
so ``FrankaKitchen-v1`` crashes at construction. ``apply()`` (once, when a kitchen env is made; a
no-op where the originals work) replaces the four helpers with ones comparing integer codes.
"""

from __future__ import annotations

import functools

import mujoco
import numpy as np

from botorl.envs.wrappers import import_robotics

# Width of a joint in qpos / qvel, by integer joint type (mjtJoint: FREE=0, BALL=1, SLIDE=2, HINGE=3).
_QPOS_WIDTH = {0: 7, 1: 4, 2: 1, 3: 1}
_QVEL_WIDTH = {0: 6, 1: 3, 2: 1, 3: 1}


def _joint(model, name: str, qpos: bool) -> slice:
    """The joint's slice of qpos (``qpos``) or qvel: address by joint name, width by joint type."""
    joint_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
    if joint_id == -1:
        raise KeyError(f"joint {name!r} is not part of the model")
    start = int((model.jnt_qposadr if qpos else model.jnt_dofadr)[joint_id])
    return slice(start, start + (_QPOS_WIDTH if qpos else _QVEL_WIDTH)[int(model.jnt_type[joint_id])])


def get_joint_qpos(model, data, name):
    return data.qpos[_joint(model, name, True)].copy()


def get_joint_qvel(model, data, name):
    # A ball joint has 3 dofs (the original helper slices 4; kitchen has no ball joints).
    return data.qvel[_joint(model, name, False)].copy()


def set_joint_qpos(model, data, name, value):
    where = _joint(model, name, True)
    data.qpos[where] = np.asarray(value).reshape(where.stop - where.start)


def set_joint_qvel(model, data, name, value):
    where = _joint(model, name, False)
    data.qvel[where] = np.asarray(value).reshape(where.stop - where.start)


def needs_patch() -> bool:
    """True where the installed mujoco breaks the original tuple-membership check."""
    hinge, slide = mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE
    return np.int32(int(hinge)) not in (hinge, slide)


@functools.cache
def apply() -> bool:
    """Patch gymnasium-robotics' joint helpers if needed (once). Returns True if patched."""
    if not needs_patch():
        return False
    mujoco_utils = import_robotics("gymnasium_robotics.utils.mujoco_utils")
    # robot_get_obs and the kitchen env look these up as module globals at call time.
    for helper in (get_joint_qpos, get_joint_qvel, set_joint_qpos, set_joint_qvel):
        setattr(mujoco_utils, helper.__name__, helper)
    return True

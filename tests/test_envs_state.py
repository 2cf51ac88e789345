"""get_env_state / set_env_state: a fresh env given a captured state continues bit-identically.

Per env family: step k random actions, capture (through JSON), step m more recording
observations, rewards, terminated/truncated and success (crossing the horizon, so the time
limit's counter and the reset's random draws are part of the check); restore into a fresh env
made the same way and step the same m actions. Tolerance: none -- the results are compared
exactly (MuJoCo's integration state is restored bit for bit, and stepping is deterministic on
one machine). A control shows the fresh env without the state does differ.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from botorl.envs.registry import get_task
from botorl.envs.state import FORMAT, get_env_state, set_env_state

FAMILIES = ["pointmaze-umaze", "door-binary-v0", "pen-binary-v0", "antmaze-large-diverse-v2", "kitchen-partial-v0"]
M = 40


def _roll(env, actions):
    out = []
    for a in actions:
        o, r, te, tr, info = env.step(a)
        out.append((o.copy(), r, te, tr, info["success"]))
        if te or tr:
            o, _ = env.reset()
            out.append((o.copy(), "reset"))
    return out


def _same(a, b) -> bool:
    return len(a) == len(b) and all(
        np.array_equal(x[0], y[0]) and x[1:] == y[1:] for x, y in zip(a, b))


@pytest.mark.parametrize("task", FAMILIES)
def test_restore_continues_exactly(task):
    spec = get_task(task)
    env = spec.make_env(seed=7)
    env.reset()
    rng = np.random.default_rng(1)
    A = env.action_space.shape[0]
    # step until the episode is M/2 steps from its horizon, so the window crosses the time limit
    while env._elapsed_steps < spec.max_episode_steps - M // 2:
        _, _, te, tr, _ = env.step(rng.uniform(-1, 1, size=A).astype(np.float32))
        if te or tr:
            env.reset()
    actions = rng.uniform(-1, 1, size=(M, A)).astype(np.float32)
    k = 0
    state = json.loads(json.dumps(get_env_state(env)))  # JSON-serialisable, exactly
    assert state["format"] == FORMAT and state["mujoco"]
    ref = _roll(env, actions[k:])
    assert any(len(x) == 2 for x in ref), "the window should cross an episode end"

    fresh = spec.make_env(seed=7)
    set_env_state(fresh, state)
    assert _same(_roll(fresh, actions[k:]), ref)

    control = spec.make_env(seed=7)
    control.reset()
    assert not _same(_roll(control, actions[k:]), ref)
    for e in (env, fresh, control):
        e.close()


def test_counters_and_goal_are_in_the_state():
    spec = get_task("pointmaze-umaze")
    env = spec.make_env(seed=0)
    env.reset()
    for _ in range(3):
        env.step(np.zeros(2, np.float32))
    st = get_env_state(env)
    assert st["layers"]["wrapper0"]["class"] == "TimeLimit"
    assert st["layers"]["wrapper0"]["attrs"]["_elapsed_steps"] == 3
    assert "goal" in st["layers"]["env"]["attrs"] and st["layers"]["env"]["np_random"] is not None


def test_state_of_another_task_is_refused():
    a = get_task("pointmaze-umaze").make_env(seed=0)
    b = get_task("door-binary-v0").make_env(seed=0)
    with pytest.raises(ValueError):
        set_env_state(b, get_env_state(a))
    with pytest.raises(ValueError):
        set_env_state(a, {"format": "other"})

"""Checks that need an accelerator: the paper's full-size updates and a population of 16.

Skipped where JAX has no GPU (the CPU suite covers the same code at small sizes); on a GPU
machine, `pytest -m gpu`. They check what a CPU cannot afford to: that the `full` profile's
online step (10 critics of 4 x 256, UTD 4, actor on 1,024 rows) compiles and stays finite on
the device, and that 16 members train as one program with each member's numbers its own.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(jax.default_backend() not in ("gpu", "cuda", "rocm"), reason="needs a GPU")]


def _batch(rng, utd=4, rows=256, obs=29, act=8):
    """One update's batch at UTD 4: 4 critic minibatches of 256 rows, (4, 256, ...), the actor's 1,024."""
    n = (utd, rows)
    return {"observations": rng.normal(size=n + (obs,)).astype(np.float32),
            "actions": rng.uniform(-0.9, 0.9, n + (act,)).astype(np.float32),
            "rewards": rng.normal(size=n).astype(np.float32),
            "next_observations": rng.normal(size=n + (obs,)).astype(np.float32),
            "dones": np.zeros(n, np.float32), "mc_returns": np.zeros(n, np.float32)}


def _full_sac():
    from botorl.agents.sac import SACConfig

    return SACConfig(actor_hidden_dims=(256, 256), critic_hidden_dims=(256,) * 4, num_critics=10)


def test_full_size_online_step_on_the_device():
    from botorl.agents.sac import SACAgent

    agent = SACAgent.create(_full_sac(), obs_dim=29, action_dim=8, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(3):
        agent, info = agent.update(_batch(rng))
    assert all(np.isfinite(float(v)) for v in jax.tree_util.tree_leaves(info))
    assert agent.critic.params is not None and jax.tree_util.tree_leaves(agent.critic.params)[0].devices() <= set(jax.devices())


@pytest.mark.parametrize("precision", ["highest", "tf32", "bf16"])
def test_population_of_16_members_is_each_member_alone(precision):
    """Within the tolerance of the matmul precision (``member_tolerance``: a vmapped batch and
    the single run sum in another order; below fp32, a last-bit difference can round to the
    neighbouring input of the format). An H100 measured 2.0e-4 at JAX's default, TF32."""
    from botorl.agents import population as AP
    from botorl.agents.sac import SACAgent
    from botorl.jaxsetup import matmul_precision, member_tolerance

    cfg = _full_sac()
    members = [SACAgent.create(cfg, obs_dim=29, action_dim=8, seed=s) for s in range(16)]
    rng = np.random.default_rng(1)
    batches = [_batch(rng) for _ in range(16)]
    stacked = {k: np.stack([b[k] for b in batches]) for k in batches[0]}
    with matmul_precision(precision):
        pop, _ = AP.update(AP.stack(members), stacked)
        alone, _ = members[5].update(batches[5])
    a = jax.tree_util.tree_leaves(AP.member_of(pop, 5).actor.params)
    b = jax.tree_util.tree_leaves(alone.actor.params)
    gap = max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in zip(a, b))
    assert gap < member_tolerance(precision), f"{precision}: max |member - alone| {gap:.2g}"

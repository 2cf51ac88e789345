"""The named updates the benchmark times, built on botorl's real agents, each with the matching
d3rlpy update (``d3rlpy_algo``, timed by benchmarks/against_d3rlpy.py) where d3rlpy has one.
Sizes are the reference ones of docs/methods.md (table: docs/performance.md). A ``Bound``
workload's ``step(n)`` runs n chained updates and blocks; ``flop_fn(*flop_args)`` is one call.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable

import jax
import numpy as np

from botorl.agents.cql import CQLAgent, CQLConfig
from botorl.agents.iql import IQLAgent, IQLConfig
from botorl.agents.sac import SACAgent, SACConfig
from botorl.batch import BATCH_KEYS
from botorl.boto.config import BOTOConfig
from botorl.boto.objective import ObjectiveSettings, boto_update_many


@dataclass(frozen=True)
class Workload:
    name: str
    label: str
    algo: str  # calql | cql | iql | sac | online | boto
    num_critics: int
    critic_hidden: tuple[int, ...]
    actor_hidden: tuple[int, ...]
    obs_dim: int = 29
    action_dim: int = 8
    batch: int = 256  # rows per critic step
    utd: int = 1
    n_action_samples: int = 10  # CQL/Cal-QL: per kind (uniform, pi(s), pi(s')), and backup actions
    d3rlpy_algo: str | None = None
    note: str = ""
    layer_norm: bool = True  # WSRL/Cal-QL: LayerNorm after hidden layers; IQL: none
    scan_k: int = 1  # > 1: K updates per call via update_many (lax.scan), as the pipeline pre-trains
    d3rlpy_same_as: str | None = None  # compare with that row's d3rlpy figures (same update)

    def tiny(self) -> "Workload":
        """Same update on toy sizes (tests: compiles in seconds)."""
        return dataclasses.replace(self, label=self.label[:26] + " [tiny]", critic_hidden=(16,), actor_hidden=(16,),
                                   batch=8, num_critics=min(self.num_critics, 2), obs_dim=5, action_dim=2,
                                   n_action_samples=2)


_H2 = (256, 256)
_H4 = (256, 256, 256, 256)
_NOTE_SAC = ("d3rlpy's SAC target is min over all critics with backup entropy; botorl's is "
             "min over a random 2 of them, no backup entropy (WSRL)")
WORKLOADS: dict[str, Workload] = {w.name: w for w in [
    Workload("calql", "Cal-QL step, 2 x (256,256)", "calql", 2, _H2, _H2, d3rlpy_algo="calql",
             note="critic (10+10+10 CQL samples, max-target backup over 10) + actor + temperature; fixed CQL weight"),
    Workload("cql", "CQL step, 2 x (256,256)", "cql", 2, _H2, _H2, d3rlpy_algo="cql",
             note="as Cal-QL without the MC lower bound"),
    Workload("iql", "IQL step, 2 x (256,256)", "iql", 2, _H2, _H2, d3rlpy_algo="iql",
             layer_norm=False, note="Q + V + AWR actor + Polyak; no LayerNorm (IQL's default)"),
    Workload("sac2", "SAC step, 2 x (256,256)", "sac", 2, _H2, _H2, d3rlpy_algo="sac",
             note="critic + actor + temperature; " + _NOTE_SAC),
    Workload("sac10", "SAC step, 10 x 4x256", "sac", 10, _H4, _H2, d3rlpy_algo="sac",
             note="critic + actor + temperature; " + _NOTE_SAC),
    Workload("online_utd4", "online step UTD 4, 10 x 4x256", "online", 10, _H4, _H2, utd=4,
             d3rlpy_algo="sac_utd",
             note="4 x (critic + Polyak) on 256 rows each, then actor + temperature on the 1,024; "
                  "d3rlpy has no UTD: composed from its update_critic/update_actor"),
    Workload("boto_critic", "BOTO critic step, 10 x 4x256", "boto", 10, _H4, _H2,
             d3rlpy_algo="sac_critic",
             note="d3rlpy has no BOTO: compared with its SAC critic step (no noise/penalty)"),
    Workload("calql_k8", "Cal-QL step, 8 per call (scan)", "calql", 2, _H2, _H2, scan_k=8,
             d3rlpy_same_as="calql",
             note="update_many over 8 batches (the pipeline's pre-training path); d3rlpy: its per-call Cal-QL step"),
    Workload("sac10_k8", "SAC step 10 x 4x256, 8 per call", "sac", 10, _H4, _H2, scan_k=8,
             d3rlpy_same_as="sac10", note="update_many over 8 batches; d3rlpy: its per-call SAC step"),
    Workload("calql_adroit", "Cal-QL step, 2 x 3x512 (adroit)", "calql", 2, (512, 512, 512), (512, 512),
             obs_dim=39, action_dim=28, d3rlpy_algo="calql", note="door sizes"),
]}
QUICK = ("sac2", "calql", "online_utd4")
BOTO_STEPS_PER_CALL = 10


@dataclass
class Bound:
    step: Callable[[int], None]
    flop_fn: Callable[..., Any]
    flop_args: tuple
    updates_per_call: int = 1  # flop_fn does this many updates (the FLOPs are divided by it)


def make_batch(rows: int, obs_dim: int, action_dim: int, seed: int = 0, lead: tuple[int, ...] = ()) -> dict:
    """A random Batch (CONTRACTS.md) already on the device."""
    rng = np.random.default_rng(seed)
    u = lambda *s: rng.uniform(-1, 1, lead + s).astype(np.float32)  # noqa: E731
    values = [u(rows, obs_dim), u(rows, action_dim) * 0.99, u(rows), u(rows, obs_dim),
              (rng.uniform(size=lead + (rows,)) < 0.01).astype(np.float32), u(rows) * 10]  # drawn in this order
    return jax.device_put(dict(zip(BATCH_KEYS, values)))


def _bound(agent: Any, call: Callable, batch: Any, updates_per_call: int) -> Bound:
    """``step(n)``: n calls of ``call(agent, batch)``, each on the agent the previous returned."""
    def step(n: int) -> None:
        nonlocal agent
        for _ in range(n):
            agent, _ = call(agent, batch)
        jax.block_until_ready(agent)

    return Bound(step, call, (agent, batch), updates_per_call)


def build(w: Workload, seed: int = 0) -> Bound:
    """The botorl side of a workload."""
    nets = dict(actor_hidden_dims=w.actor_hidden, critic_hidden_dims=w.critic_hidden, num_critics=w.num_critics)
    lead = ()
    if w.algo == "boto":
        # K critic steps per jitted call (lax.scan) as the BOTO phase runs them; the q_data /
        # q_uniform forward passes once per call cost a few % of a step at K = 10
        agent = SACAgent.create(SACConfig(**nets), w.obs_dim, w.action_dim, seed)
        settings = ObjectiveSettings.resolve(BOTOConfig(), agent)
        batches = make_batch(w.batch, w.obs_dim, w.action_dim, seed, lead=(BOTO_STEPS_PER_CALL,))
        return _bound(agent, lambda a, b: boto_update_many(a, b, 0.5, settings), batches, BOTO_STEPS_PER_CALL)
    if w.algo in ("sac", "online"):
        agent = SACAgent.create(SACConfig(**nets), w.obs_dim, w.action_dim, seed)
        lead = (w.utd,) if w.utd > 1 else ()  # UTD u: u minibatches of B rows, (u, B, ...)
    elif w.algo in ("calql", "cql"):
        # a fixed CQL weight (no Lagrange step), as on the d3rlpy side
        cfg = CQLConfig(**nets, calql=w.algo == "calql", cql_n_actions=w.n_action_samples,
                        max_target_backup=True, num_backup_actions=w.n_action_samples, cql_lagrange=False)
        agent = CQLAgent.create(cfg, w.obs_dim, w.action_dim, seed)
    elif w.algo == "iql":
        agent = IQLAgent.create(IQLConfig(**nets, value_hidden_dims=w.critic_hidden), w.obs_dim, w.action_dim, seed)
    else:
        raise ValueError(f"unknown workload algo {w.algo!r}")
    batch = make_batch(w.batch, w.obs_dim, w.action_dim, seed, lead)
    if w.scan_k == 1:
        return _bound(agent, lambda a, b: a.update(b), batch, 1)
    batch = jax.tree_util.tree_map(lambda x: jax.numpy.stack([x] * w.scan_k), batch)
    return _bound(agent, lambda a, b: a.update_many(b), batch, w.scan_k)


"""Populations: N independent runs (seeds, and for BOTO alphas) trained as one program.

A population stacks its members' agent pytrees along a new leading axis (``stack``) and
trains them with one jitted call per update: every entry point below is the agent's own
traced function (``agents/common.py``, ``boto/objective.py``) mapped over that axis. On a
CPU with several cores the updates split the members over one JAX CPU device per core and
each device runs its members in turn (``_across_cores``); elsewhere, and for the per-step
policy calls, the function is ``jax.vmap``ped. A population of one takes the member out of
the axis inside the jitted function, so a single run computes exactly what the agent's own
jitted function computes (and runs as fast).

Members are independent: nothing in a vmapped function mixes members, every member carries
its own JAX key inside its agent (from its seed), and every host-side random stream (batch
indices, exploration, env seeds) is a ``numpy.random.Generator`` per member seeded from the
member's seed alone. So a member's numbers do not depend on which or how many others share
its population (tests/test_population_*.py checks this to float tolerance).

Pieces:
- ``Member`` / ``make_members``: the members from ``--seeds`` / ``--alphas`` (validated);
- ``stack`` / ``unstack`` / ``member_of`` / ``population_size``: agent pytrees <-> stacked;
- ``pop_update``, ``pop_update_many``, ``pop_update_many_on_device``, ``pop_sample``,
  ``pop_eval``, ``pop_boto_update_many``, ``pop_q_mean``: the vmapped jitted entry points
  (each compiles once per population size, config and shapes);
- ``sample_members`` / ``sample_union_members``: per-member batches from one shared Dataset
  (held once; one fancy-index gather for all members);
- ``MemberReplay``: one replay buffer with a member axis (one vectorised insert per env
  step for all members; per-member sampling, mixed with the offline data if asked);
- ``estimate_memory`` / ``check_memory``: the population's memory, estimated before any
  work, against what the machine has.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
from dataclasses import dataclass
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from botorl.agents import common as C
from botorl.data.dataset import BATCH_KEYS, Dataset
from botorl.errors import BotorlError, ConfigError

__all__ = [
    "Member", "parse_seeds", "parse_alphas", "make_members", "stack", "unstack", "member_of",
    "population_size", "pop_update", "pop_update_many", "pop_update_many_on_device", "pop_sample",
    "pop_eval", "pop_boto_update_many", "pop_q_mean", "sample_members", "sample_union_members",
    "MemberReplay", "estimate_memory", "check_memory", "available_memory",
]


# ============================================================================ members
@dataclass(frozen=True)
class Member:
    """One member: its seed and, for BOTO, its alpha (None: no BOTO phase)."""

    seed: int
    alpha: float | None = None

    @property
    def name(self) -> str:
        """Its run directory's name inside the population directory."""
        if self.alpha is None:
            return f"seed{self.seed}"
        return f"alpha{self.alpha:+.2f}-seed{self.seed}" if round(self.alpha, 2) == self.alpha else \
            f"alpha{self.alpha:+.6f}-seed{self.seed}"

    def to_json(self) -> dict:
        return {"seed": self.seed, "alpha": self.alpha, "name": self.name}


def _items(text: str, flag: str) -> list[str]:
    items = [t.strip() for t in str(text).split(",")]
    if not all(items):
        raise ConfigError(f"{flag} {text!r} has an empty item; write e.g. {flag} 0-3 or {flag} 0,2,5.")
    return items


def parse_seeds(text: str | Sequence[int]) -> list[int]:
    """``"0-7"`` (inclusive), ``"0,2,5"``, ``"0-2,7"`` or a list; a seed given twice is an error."""
    seeds: list[int] = []
    if isinstance(text, (list, tuple)):
        raw = [str(int(s)) for s in text]
    else:
        raw = _items(text, "--seeds")
    for item in raw:
        try:
            if "-" in item[1:]:
                lo, hi = (int(p) for p in item.split("-", 1))
                if hi < lo:
                    raise ValueError
                seeds.extend(range(lo, hi + 1))
            else:
                seeds.append(int(item))
        except ValueError:
            raise ConfigError(
                f"--seeds: cannot read {item!r}. Give a range like 0-7 (both ends included), a list like "
                f"0,2,5, or both (0-3,9)."
            ) from None
    if any(s < 0 for s in seeds):
        raise ConfigError(f"--seeds: seeds must be >= 0, got {[s for s in seeds if s < 0]}.")
    dup = sorted({s for s in seeds if seeds.count(s) > 1})
    if dup:
        raise ConfigError(
            f"--seeds {text}: seed(s) {dup} given twice. Two members with the same seed (and alpha) would be "
            f"the same run; give each seed once."
        )
    return seeds


def parse_alphas(text: str | Sequence[float]) -> list[float]:
    """``"-1:1:0.25"`` (start:stop:step, stop included), ``"-0.5,0,0.5"`` or a list."""
    alphas: list[float] = []
    if isinstance(text, (list, tuple)):
        raw = [repr(float(a)) for a in text]
    elif ":" in str(text) and "," not in str(text):
        raw = [str(text).strip()]
    else:
        raw = _items(text, "--alphas")
    for item in raw:
        try:
            if ":" in item:
                start, stop, step = (float(p) for p in item.split(":"))
                if not step > 0 or stop < start:
                    raise ValueError
                n = int(math.floor((stop - start) / step + 1e-9)) + 1
                alphas.extend(round(start + i * step, 6) for i in range(n))
            else:
                alphas.append(round(float(item), 6))
        except ValueError:
            raise ConfigError(
                f"--alphas: cannot read {item!r}. Give start:stop:step with the stop included (-1:1:0.25 gives "
                f"9 values) or a list like -0.5,0,0.5."
            ) from None
    alphas = [0.0 if a == 0 else a for a in alphas]
    bad = [a for a in alphas if math.isnan(a) or not -1.0 <= a <= 1.0]
    if bad:
        raise ConfigError(
            f"--alphas: {bad} outside [-1, 1]. alpha is BOTO's bias controller (> 0 conservative, < 0 "
            f"optimistic); the paper's grid is -1:1:0.1."
        )
    dup = sorted({a for a in alphas if alphas.count(a) > 1})
    if dup:
        raise ConfigError(f"--alphas {text}: alpha(s) {dup} given twice; give each alpha once.")
    return alphas


def make_members(seeds: Sequence[int], alphas: Sequence[float | None], method_uses_alpha: bool) -> list[Member]:
    """Every (seed, alpha) pair, alpha-major. ``alphas`` empty or [None]: one alpha (the preset's)."""
    alphas = list(alphas) or [None]
    if not method_uses_alpha and any(a is not None for a in alphas):
        raise ConfigError("--alphas sets BOTO's bias controller; this method has no BOTO phase. Drop --alphas or use --method boto.")
    members = [Member(int(s), None if a is None else float(a)) for a in alphas for s in seeds]
    if not members:
        raise ConfigError("the population is empty; give at least one seed (--seeds).")
    names = [m.name for m in members]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"members {dup} appear twice in the population; give each seed and alpha once.")
    return members


# ============================================================================ stacking
def stack(agents: Sequence[Any]):
    """Agent pytrees of one class and config -> one pytree with a leading member axis."""
    if not agents:
        raise ValueError("stack needs at least one agent")
    return jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *agents)


def population_size(agents) -> int:
    return int(jax.tree_util.tree_leaves(agents)[0].shape[0])


def member_of(agents, i: int):
    """Member ``i`` of a stacked pytree (an ordinary agent)."""
    return jax.tree_util.tree_map(lambda x: x[i], agents)


def unstack(agents) -> list:
    return [member_of(agents, i) for i in range(population_size(agents))]


# ============================================================================ vmapped entry points
def _member_count(axes, args) -> int:
    """Members in the first argument mapped over its leading axis."""
    return next(jax.tree_util.tree_leaves(a)[0].shape[0] for a, ax in zip(args, axes) if ax == 0)


def _per_member(fn, axes, *args):
    """``vmap(fn, in_axes=axes)(*args)``; for a population of one, ``fn`` on the member itself
    (no batch dimension in any op: the single run's program) with the axis put back."""
    if _member_count(axes, args) == 1:
        sq = [jax.tree_util.tree_map(lambda x: x[0], a) if ax == 0 else a for a, ax in zip(args, axes)]
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], fn(*sq))
    return jax.vmap(fn, in_axes=axes)(*args)


def host_shards(n: int) -> int:
    """CPU devices a population of ``n`` members trains on: one per core that the process may
    use (``jaxsetup.setup_jax`` makes them), at most ``n``; 1 off the CPU, where one device's
    vmapped kernels are the faster layout."""
    if n <= 1 or jax.default_backend() != "cpu":
        return 1
    return min(n, jax.local_device_count())


def _member_loop(fn, axes, *args):
    """``fn`` on each member in turn (``lax.map``): every member runs the single run's own
    unbatched program (XLA may still fuse it another way inside the loop: parameters equal a
    1-member population's to ~1e-8 after 3 Cal-QL updates, against ~1e-7 vmapped)."""
    mapped = tuple(a for a, ax in zip(args, axes) if ax == 0)

    def one(ms):
        it = iter(ms)
        return fn(*[next(it) if ax == 0 else a for a, ax in zip(args, axes)])

    return jax.lax.map(one, mapped)


def _across_cores(fn, axes, *args):
    """An update of every member, for the heavy entry points (the updates; not the per-step
    policy calls). On a CPU with several cores the members are split over one JAX CPU device
    per core (``shard_map``) and each device runs its members one after another: measured on
    2 cores (docs/populations.md, "What it buys"), a vmapped batch of members is slower per
    member than one member alone (its activations, N times larger, fall out of the caches),
    while members in turn keep the single run's speed on each core. The member axis is padded
    with copies of member 0 to a multiple of the devices; their results are dropped."""
    n = _member_count(axes, args)
    d = host_shards(n)
    if d == 1:
        return _per_member(fn, axes, *args)
    pad = (-n) % d

    def padded(x):
        return x if pad == 0 else jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)])

    args = [jax.tree_util.tree_map(padded, a) if ax == 0 else a for a, ax in zip(args, axes)]
    mesh = _mesh(d)
    specs = tuple(PartitionSpec("members") if ax == 0 else PartitionSpec() for ax in axes)
    out = jax.shard_map(lambda *a: _member_loop(fn, axes, *a), mesh=mesh, in_specs=specs,
                        out_specs=PartitionSpec("members"), check_vma=False)(*args)
    if pad:
        out = jax.tree_util.tree_map(lambda x: x[:n], out)
    return jax.lax.with_sharding_constraint(out, member_sharding(n))


@functools.lru_cache(maxsize=None)
def _mesh(d: int) -> Mesh:
    return Mesh(np.array(jax.local_devices()[:d]), ("members",))


def member_sharding(n: int):
    """Where a population of ``n`` members keeps its stacked arrays between updates: split
    over the devices along the member axis (replicated when ``n`` does not divide, as JAX
    shards only evenly). None for one device."""
    d = host_shards(n)
    if d == 1:
        return None
    return NamedSharding(_mesh(d), PartitionSpec("members") if n % d == 0 else PartitionSpec())


def _placed(n: int, *trees):
    """The member-axis inputs of an update where its outputs will be, so that every call
    (the first, with fresh arrays, and the later ones) compiles to one program."""
    sharding = member_sharding(n)
    if sharding is None:
        return trees

    def put(tree):
        first = jax.tree_util.tree_leaves(tree)[0]
        if isinstance(first, jax.Array) and first.sharding == sharding:
            return tree  # the agents after their first update: already there (a per-leaf check costs ms)
        return jax.device_put(tree, sharding)

    return tuple(put(t) for t in trees)


def _update_p(agents, batches):
    return _across_cores(C._update, (0, 0), agents, batches)


def _update_many_p(agents, batches):
    return _across_cores(C._update_many, (0, 0), agents, batches)


def _sample_p(agents, observations):
    return _per_member(C._sample, (0, 0), agents, observations)


def _eval_p(agents, observations):
    return _per_member(C._eval, (0, 0), agents, observations)


def _update_many_on_device_p(agents, arrays, keys, num_updates: int, batch_size: int):
    def one(agent, key):
        return C._update_many_on_device(agent, arrays, key, num_updates, batch_size)

    return _per_member(one, (0, 0), agents, keys)


def _q_mean_p(agents, observations, actions):
    def one(agent):
        return agent.critic_values(agent.critic.params, observations, actions).mean(axis=0)

    return _per_member(one, (0,), agents)


def _boto_p(agents, batches, alphas, settings):
    from botorl.boto.objective import _update_many as boto_many

    return _across_cores(lambda a, b, al: boto_many(a, b, al, settings), (0, 0, 0), agents, batches, alphas)


def _update_masked_p(agents, batches, mask, many: bool):
    """Members with ``mask`` False keep their agent (rng included): they did not update."""
    new, metrics = (_update_many_p if many else _update_p)(agents, batches)

    def pick(n, o):
        return jnp.where(mask.reshape(mask.shape + (1,) * (n.ndim - 1)), n, o)

    return jax.tree_util.tree_map(pick, new, agents), metrics


_jit_update = jax.jit(_update_p)
_jit_update_masked = jax.jit(_update_masked_p, static_argnames=("many",))
_jit_update_many = jax.jit(_update_many_p)
_jit_sample = jax.jit(_sample_p)
_jit_eval = jax.jit(_eval_p)
_jit_update_many_on_device = jax.jit(_update_many_on_device_p, static_argnames=("num_updates", "batch_size"))
_jit_q_mean = jax.jit(_q_mean_p)
_jit_boto = jax.jit(_boto_p, static_argnames=("settings",))


def _as_f32(x):
    # host arrays stay on the host until the update places them (one copy, to their devices);
    # device arrays stay on their device
    return x.astype(jnp.float32) if isinstance(x, jax.Array) else np.asarray(x, np.float32)


def _f32(batch: dict) -> dict:
    C.check_batch(batch)
    batch = C.ensure_mc_returns(batch)
    return {k: _as_f32(batch[k]) for k in BATCH_KEYS}


def pop_update(agents, batches):
    """One ``update`` per member; ``batches`` (N, B, ...). Returns (agents, metrics (N,))."""
    return _jit_update(*_placed(population_size(agents), agents, _f32(batches)))


def pop_update_masked(agents, batches, mask, *, many: bool = False):
    """``pop_update`` (or ``pop_update_many``) where only the members with ``mask`` True update;
    the others keep their agent exactly (their rows of ``batches`` are ignored)."""
    placed = _placed(population_size(agents), agents, _f32(batches), np.asarray(mask, bool))
    return _jit_update_masked(*placed, many=many)


def pop_update_many(agents, batches):
    """K updates per member under one ``lax.scan``; ``batches`` (N, K, B, ...)."""
    return _jit_update_many(*_placed(population_size(agents), agents, _f32(batches)))


def pop_update_many_on_device(agents, arrays: dict, keys, num_updates: int, batch_size: int):
    """``update_many_on_device`` per member from one shared on-device dataset; ``keys`` (N, 2)."""
    C.check_batch(arrays)
    return _jit_update_many_on_device(agents, C.ensure_mc_returns(arrays), keys, num_updates, batch_size)


def pop_sample(agents, observations):
    """Stochastic actions of every member at its own observation(s): (N, O) -> (N, A)."""
    return _jit_sample(agents, jnp.asarray(observations, jnp.float32))


def pop_eval(agents, observations):
    """Deterministic actions: (N, O) -> (N, A) or (N, E, O) -> (N, E, A)."""
    return _jit_eval(agents, jnp.asarray(observations, jnp.float32))


def pop_q_mean(agents, observations, actions):
    """Mean over each member's critic ensemble of Q(s, a) on shared (s, a): (N, B)."""
    return _jit_q_mean(agents, jnp.asarray(observations, jnp.float32), jnp.asarray(actions, jnp.float32))


def pop_boto_update_many(agents, batches, alphas, settings):
    """K BOTO critic steps per member, each member with its own alpha; ``batches`` (N, K, B, ...),
    ``alphas`` (N,); ``settings`` an ``ObjectiveSettings`` (static, shared)."""
    from botorl.boto.objective import _BATCH_KEYS, check_alpha

    check_alpha(np.asarray(alphas))
    b = {k: _as_f32(batches[k]) for k in _BATCH_KEYS}
    placed = _placed(population_size(agents), agents, b, _as_f32(alphas))
    return _jit_boto(*placed, settings)


# ============================================================================ batches per member
def sample_members(source, rngs: Sequence[np.random.Generator], batch_size: int, num_batches: int | None = None) -> dict:
    """Each member's batch from the shared ``source`` (a Dataset or anything with ``batch_at``
    and ``len``) with the member's own generator: stacked (N, [K,] B, ...).

    Member i draws exactly what ``source.sample(rngs[i], batch_size, num_batches)`` draws; the
    rows of all members are then gathered at once."""
    shape = (batch_size,) if num_batches is None else (num_batches, batch_size)
    n = len(source)
    idx = np.stack([r.integers(0, n, size=shape) for r in rngs])
    return source.batch_at(idx)


def sample_union_members(d_offline: Dataset | None, d_warmups: Sequence[Dataset | None],
                         rngs: Sequence[np.random.Generator], batch_size: int, num_batches: int) -> dict:
    """Batches from D_offline u D_warmup_i per member i, as ``boto_dataset(...).sample`` draws
    them (row r < len(D_offline) from the offline data, else from the member's warm-up data),
    without copying the offline data once per member. Stacked (N, K, B, ...)."""
    out = []
    n_off = 0 if d_offline is None else len(d_offline)
    keys = ("observations", "actions", "rewards", "next_observations", "dones")
    for rng, d_w in zip(rngs, d_warmups):
        n_w = 0 if d_w is None else len(d_w)
        if n_off + n_w == 0:
            raise ConfigError("BOTO got no data: D_offline and D_warmup are both empty; pass the offline dataset.")
        idx = rng.integers(0, n_off + n_w, size=(num_batches, batch_size))
        if n_w == 0:
            b = d_offline.batch_at(idx)
        elif n_off == 0:
            b = d_w.batch_at(idx)
        else:
            off = idx < n_off
            b_off = d_offline.batch_at(np.where(off, idx, 0))
            b_w = d_w.batch_at(np.where(off, 0, idx - n_off))
            b = {k: np.where(off.reshape(off.shape + (1,) * (b_off[k].ndim - 2)), b_off[k], b_w[k]) for k in keys}
        out.append({k: b[k] for k in keys})
    return {k: np.stack([o[k] for o in out]) for k in keys}


# ============================================================================ replay with a member axis
_FIELDS = ("observations", "actions", "rewards", "next_observations", "dones", "mc_returns")


class MemberReplay:
    """N ring buffers of equal capacity in one set of arrays (N, capacity, ...).

    Members step in lockstep, so every member inserts one row per env step: ``insert`` writes
    all N rows with one vectorised assignment per field. Each member samples its own rows with
    its own generator, exactly as ``ReplayBuffer.sample`` / ``sample_mixed`` would for it.
    """

    def __init__(self, num_members: int, capacity: int, obs_dim: int, action_dim: int):
        if capacity <= 0:
            raise ValueError(f"capacity must be positive, got {capacity}")
        self.n = int(num_members)
        self.capacity = int(capacity)
        self.obs_dim, self.action_dim = int(obs_dim), int(action_dim)
        N, C_ = self.n, self.capacity
        self.observations = np.zeros((N, C_, obs_dim), np.float32)
        self.actions = np.zeros((N, C_, action_dim), np.float32)
        self.rewards = np.zeros((N, C_), np.float32)
        self.next_observations = np.zeros((N, C_, obs_dim), np.float32)
        self.dones = np.zeros((N, C_), np.float32)
        self.mc_returns = np.zeros((N, C_), np.float32)
        self.size = 0
        self.insert_index = 0
        self.total_inserted = 0
        # rows of each member's running episode (the newest ones), as ReplayBuffer.open_rows
        self.open_rows = np.zeros(self.n, np.int64)

    def __len__(self) -> int:
        return self.size

    def end_episode(self, i: int) -> None:
        """Member i's running episode has ended: its rows become finished."""
        self.open_rows[i] = 0

    def finished_len(self, i: int) -> int:
        return int(self.size - self.open_rows[i])

    def insert(self, observations, actions, rewards, next_observations, dones) -> None:
        """One row per member: observations (N, O), actions (N, A), rewards (N,), dones (N,)."""
        i = self.insert_index
        self.observations[:, i] = observations
        self.actions[:, i] = actions
        self.rewards[:, i] = rewards
        self.next_observations[:, i] = next_observations
        self.dones[:, i] = dones
        self.mc_returns[:, i] = 0.0
        self.insert_index = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self.total_inserted += 1
        self.open_rows = np.minimum(self.open_rows + 1, self.capacity)

    def insert_datasets(self, datasets: Sequence[Dataset]) -> None:
        """Member i gets all rows of ``datasets[i]`` (equal lengths: D_warmup of each member)."""
        lengths = {len(d) for d in datasets}
        if len(datasets) != self.n or len(lengths) != 1:
            raise ValueError("insert_datasets needs one dataset per member, all of the same length")
        m = lengths.pop()
        if m > self.capacity:
            raise ValueError(f"{m} rows do not fit a buffer of capacity {self.capacity}")
        for k, field in (("observations", "observations"), ("actions", "actions"), ("rewards", "rewards"),
                         ("next_observations", "next_observations"), ("dones", "terminals"),
                         ("mc_returns", "mc_returns")):
            arr = getattr(self, k)
            for j, d in enumerate(datasets):
                v = getattr(d, field)
                rows = np.zeros(m, np.float32) if v is None else np.asarray(v, np.float32)
                idx = (self.insert_index + np.arange(m)) % self.capacity
                arr[j, idx] = rows
        self.insert_index = (self.insert_index + m) % self.capacity
        self.size = min(self.size + m, self.capacity)
        self.total_inserted += m
        self.open_rows[:] = 0

    def _gather(self, idx: np.ndarray) -> dict:
        """idx (N, ...) of row indices per member -> Batch (N, ..., ...)."""
        return self._take(np.arange(self.n), idx)

    def _take(self, members: np.ndarray, idx: np.ndarray) -> dict:
        """Rows ``idx`` (M, ...) of ``members`` (M,), one flat ``np.take`` per field: numpy's
        two-array fancy index (``arr[m, idx]``) is 4-10x slower, and with 8 members it was a
        fifth of a fine-tuning step's host time."""
        flat = (members.reshape(members.shape + (1,) * (idx.ndim - 1)) * self.capacity + idx).ravel()
        out = {}
        for k in _FIELDS:
            arr = getattr(self, k)
            tail = arr.shape[2:]
            out[k] = np.take(arr.reshape((-1,) + tail), flat, axis=0).reshape(idx.shape + tail)
        return out

    def member_rows(self, i: int, rows) -> dict:
        return {k: getattr(self, k)[i, rows] for k in _FIELDS}

    def _row_index(self, i: int, rng: np.random.Generator, shape, finished: bool) -> np.ndarray:
        """Member i's row indices as ``ReplayBuffer.sample`` (all rows) or ``FinishedRows.sample``
        (closed episodes, oldest first) draws them."""
        if not finished:
            return rng.integers(0, self.size, size=shape)
        oldest = self.insert_index if self.size == self.capacity else 0
        return (oldest + rng.integers(0, self.finished_len(i), size=shape)) % self.capacity

    def sample_active(self, rngs: Sequence[np.random.Generator], active: Sequence[bool], batch_size: int,
                      num_batches: int | None, *, finished: bool = False, offline: Dataset | None = None,
                      offline_ratio: float = 0.0) -> dict:
        """One batch per member, drawn as the single-run pipeline draws it for that member
        (``sample_mixed([offline, rows], [r, 1 - r], ...)`` or ``rows.sample``, with ``rows``
        the buffer or its finished rows); members not ``active`` draw nothing (their generator
        is not advanced) and get zeros. Stacked (N, [K,] B, ...)."""
        from botorl.data.replay import split_counts

        lead = () if num_batches is None else (num_batches,)
        out = {k: np.zeros((self.n,) + lead + (batch_size,) + tail, np.float32)
               for k, tail in (("observations", (self.obs_dim,)), ("actions", (self.action_dim,)),
                               ("rewards", ()), ("next_observations", (self.obs_dim,)), ("dones", ()),
                               ("mc_returns", ()))}
        r_idx, members, off_parts = [], [], []
        counts = None
        for i, (rng, on) in enumerate(zip(rngs, active)):
            if not on:
                continue
            n_rows = self.finished_len(i) if finished else self.size
            if offline is not None:
                ratios = [offline_ratio if len(offline) > 0 else 0.0, (1.0 - offline_ratio) if n_rows > 0 else 0.0]
                if sum(ratios) <= 0:
                    raise BotorlError("sample_mixed: every source with a positive ratio is empty; nothing to sample.")
                c_off, c_on = split_counts(ratios, batch_size)
            else:
                if n_rows == 0:
                    raise BotorlError("cannot sample from an empty replay buffer; insert transitions first.")
                c_off, c_on = 0, batch_size
            if counts is not None and counts != (c_off, c_on):
                raise AssertionError("members of one population drew batches of different compositions")
            counts = (c_off, c_on)
            # the order of sample_mixed: the offline rows, then the buffer's
            off_parts.append(rng.integers(0, len(offline), size=lead + (c_off,)) if c_off else None)
            r_idx.append(self._row_index(i, rng, lead + (c_on,), finished) if c_on else None)
            members.append(i)
        if not members:
            return out
        c_off, c_on = counts
        parts = []
        sel = np.asarray(members)
        if c_off:
            parts.append(offline.batch_at(np.stack(off_parts)))
        if c_on:
            idx = np.stack(r_idx)
            parts.append(self._take(sel, idx))
        axis = idx.ndim - 1 if c_on else np.stack(off_parts).ndim - 1
        for k in BATCH_KEYS:
            out[k][sel] = np.concatenate([p[k] for p in parts], axis=axis)
        return out

    def sample(self, rngs: Sequence[np.random.Generator], batch_size: int, num_batches: int | None = None) -> dict:
        if self.size == 0:
            raise BotorlError("cannot sample from an empty replay buffer; insert transitions first.")
        shape = (batch_size,) if num_batches is None else (num_batches, batch_size)
        return self._gather(np.stack([r.integers(0, self.size, size=shape) for r in rngs]))

    def sample_mixed(self, offline: Dataset, offline_ratio: float, rngs: Sequence[np.random.Generator],
                     batch_size: int, num_batches: int | None = None) -> dict:
        """``sample_mixed([offline, buffer_i], [r, 1 - r], rng_i, ...)`` for every member i."""
        from botorl.data.replay import split_counts

        ratios = [offline_ratio if len(offline) > 0 else 0.0, (1.0 - offline_ratio) if self.size > 0 else 0.0]
        if sum(ratios) <= 0:
            raise BotorlError("sample_mixed: every source with a positive ratio is empty; nothing to sample.")
        c_off, c_on = split_counts(ratios, batch_size)
        lead = () if num_batches is None else (num_batches,)
        off_idx, on_idx = [], []
        for r in rngs:  # per member in sample_mixed's order: the offline rows, then the buffer's
            if c_off:
                off_idx.append(r.integers(0, len(offline), size=lead + (c_off,)))
            if c_on:
                on_idx.append(r.integers(0, self.size, size=lead + (c_on,)))
        parts = []
        if c_off:
            parts.append(offline.batch_at(np.stack(off_idx)))
        if c_on:
            parts.append(self._gather(np.stack(on_idx)))
        axis = 1 if num_batches is None else 2
        return {k: np.concatenate([p[k] for p in parts], axis=axis) for k in BATCH_KEYS}

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, np.ndarray]:
        n = self.size
        state = {k: getattr(self, k)[:, :n].copy() for k in _FIELDS}
        state.update(num_members=np.asarray(self.n), capacity=np.asarray(self.capacity),
                     obs_dim=np.asarray(self.obs_dim), action_dim=np.asarray(self.action_dim),
                     size=np.asarray(self.size), insert_index=np.asarray(self.insert_index),
                     total_inserted=np.asarray(self.total_inserted), open_rows=self.open_rows.copy())
        return state

    @classmethod
    def from_state_dict(cls, state: dict) -> "MemberReplay":
        buf = cls(int(state["num_members"]), int(state["capacity"]), int(state["obs_dim"]), int(state["action_dim"]))
        n = int(state["size"])
        for k in _FIELDS:
            getattr(buf, k)[:, :n] = np.asarray(state[k])
        buf.size = n
        buf.insert_index = int(state["insert_index"])
        buf.total_inserted = int(state["total_inserted"])
        if "open_rows" in state:
            buf.open_rows = np.asarray(state["open_rows"], np.int64).copy()
        return buf


# ============================================================================ memory
def tree_bytes(tree) -> int:
    return int(sum(np.dtype(x.dtype).itemsize * int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(tree)
                   if hasattr(x, "shape")))


def available_memory() -> tuple[int, str]:
    """(bytes, what): the accelerator's memory off the CPU, else the host's MemAvailable."""
    if jax.default_backend() != "cpu":
        try:
            stats = jax.devices()[0].memory_stats() or {}
            limit = int(stats.get("bytes_limit", 0)) - int(stats.get("bytes_in_use", 0))
            if limit > 0:
                return limit, f"{jax.devices()[0].device_kind} memory"
        except Exception:
            pass
    return host_memory()


def host_memory() -> tuple[int, str]:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "available host memory (MemAvailable)"
    except OSError:
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")), "free host memory"


def _rss_bytes() -> int | None:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def env_bytes(make_env, probes: int = 6) -> int:
    """Host memory one more environment takes: the median resident-size growth over ``probes``
    envs made and reset one after another, after two that pay for imports, shared model caches
    and the allocator's first arenas (the second pointmaze env grows the process by 23 MB, each
    later one by 11.7); 0 where the resident size cannot be read. So a 44-member population
    with 20 evaluation envs a member holds ~11 GB of pointmaze environments."""
    envs = []

    def one():
        e = make_env(len(envs))
        e.reset(seed=0)
        envs.append(e)

    one()
    one()
    sizes = [_rss_bytes()]
    if sizes[0] is None:
        return 0
    for _ in range(probes):
        one()
        sizes.append(_rss_bytes() or sizes[-1])
    for e in envs:
        with contextlib.suppress(Exception):
            e.close()
    return max(0, int(np.median(np.diff(sizes))))


def estimate_memory(*, num_members: int, agent_bytes: int, buffer_rows: int, warmup_rows: int, obs_dim: int,
                    action_dim: int, batch_rows: int, activation_floats: int, offline_bytes: int,
                    env_bytes_per_member: int = 0) -> dict[str, int]:
    """Bytes the population needs, by part (an estimate made before any work).

    agent_bytes: one member's agent pytree (parameters, target parameters, Adam moments);
    buffer_rows: replay capacity per member; warmup_rows: D_warmup per member; batch_rows:
    rows of one call's batches per member (K x B); activation_floats: floats the largest update
    keeps for its backward pass per member; offline_bytes: D_offline (held once);
    env_bytes_per_member: host memory of one member's environments (its training env and its
    evaluation envs). The agent counts three times (the state, the update's output and the
    checkpoint copy on the host).
    """
    row = 4 * (2 * obs_dim + action_dim + 3)
    parts = {
        "agents": 3 * num_members * agent_bytes,
        "replay": num_members * buffer_rows * row,
        "warmup": num_members * warmup_rows * row,
        "batches": 2 * num_members * batch_rows * row,
        "activations": 4 * num_members * activation_floats,
        "offline data": offline_bytes,
        "environments": num_members * env_bytes_per_member,
    }
    parts["total"] = sum(parts.values())
    return parts


def check_memory(parts: dict[str, int], num_members: int, *, available: tuple[int, str] | None = None,
                 headroom: float = 0.85) -> None:
    """ConfigError when the estimate exceeds ``headroom`` of the available memory."""
    have, what = available or available_memory()
    need = parts["total"]
    if need > headroom * have:
        per = (need - parts.get("offline data", 0)) / max(1, num_members)
        fit = max(0, int((headroom * have - parts.get("offline data", 0)) // max(per, 1)))
        detail = ", ".join(f"{k} {v / 2**30:.2f} GiB" for k, v in parts.items() if k != "total" and v)
        raise ConfigError(
            f"a population of {num_members} members needs about {need / 2**30:.1f} GiB ({detail}), more than "
            f"{headroom:.0%} of the {have / 2**30:.1f} GiB of {what}. Use fewer members (about {fit} fit: fewer "
            "--seeds/--alphas, or --population-size for a sweep), a smaller --online.buffer_capacity, or a "
            "smaller --offline.updates_per_call" + (", or fewer --eval.num_envs (each member holds that many "
            "evaluation envs)" if parts.get("environments") else "") + "."
        )


# ============================================================================ evaluation
def run_population_episodes(policy, envs: Sequence[Sequence[Any]], *, episodes: int, success_mode: str,
                            seeds: Sequence[int], max_steps: int | None = None):
    """``evaluation.run_episodes`` for every member at once: member i runs ``episodes``
    episodes on its own ``envs[i]`` (reset seeds ``seeds[i] + episode index``), all members'
    envs stepped in lockstep with ONE policy call per step on (N, E, O) observations
    (``policy`` -> (N, E, A)). Member i's episodes are exactly those ``run_episodes`` runs
    for it alone. Returns one ``EpisodeStats`` per member."""
    from botorl.pipeline.evaluation import EpisodeStats

    if success_mode not in ("any", "last"):
        raise ValueError(f"success_mode must be 'any' or 'last', not {success_mode!r}")
    n_mem, n_envs = len(envs), len(envs[0])
    per = [{"successes": [], "returns": [], "lengths": []} for _ in range(n_mem)]
    episode_index = 0
    while episode_index < episodes:
        n = min(n_envs, episodes - episode_index)
        rows = []
        for m in range(n_mem):
            rows.append(np.stack([np.asarray(envs[m][i].reset(seed=int(seeds[m]) + episode_index + i)[0], np.float32)
                                  for i in range(n_envs)]))
        obs = np.stack(rows)
        active = np.zeros((n_mem, n_envs), dtype=bool)
        active[:, :n] = True
        ret = np.zeros((n_mem, n_envs))
        length = np.zeros((n_mem, n_envs), dtype=np.int64)
        succ_any = np.zeros((n_mem, n_envs))
        succ_last = np.zeros((n_mem, n_envs))
        while active.any():
            actions = np.asarray(policy(obs))
            for m, i in zip(*np.nonzero(active)):
                o, r, terminated, truncated, info = envs[m][i].step(actions[m, i])
                s = float(info.get("success", 0.0))
                succ_any[m, i] = max(succ_any[m, i], s)
                succ_last[m, i] = s
                ret[m, i] += float(r)
                length[m, i] += 1
                obs[m, i] = np.asarray(o, dtype=np.float32)
                if terminated or truncated or (max_steps is not None and length[m, i] >= max_steps):
                    active[m, i] = False
        got = succ_any if success_mode == "any" else succ_last
        for m in range(n_mem):
            per[m]["successes"] += got[m, :n].tolist()
            per[m]["returns"] += ret[m, :n].tolist()
            per[m]["lengths"] += length[m, :n].tolist()
        episode_index += n
    return [EpisodeStats(success=float(np.mean(p["successes"])), episode_return=float(np.mean(p["returns"])),
                         length=float(np.mean(p["lengths"])), successes=p["successes"]) for p in per]

"""Populations of agents: N agents of one class and config stacked along a leading member
axis, every call the agent's own traced function (``agents/common.py``) mapped over that axis
by ``over_members``. A single run is a population of one on this same code and computes
exactly what the agent's own jitted function computes. Members are independent: nothing
here mixes them, and each carries its own JAX key.
"""

from __future__ import annotations

import functools
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from botorl.agents import common

__all__ = [
    "stack", "unstack", "member_of", "population_size", "member_metrics", "host_shards", "member_sharding", "over_members",
    "placed", "on_members", "update", "update_then_sample", "update_many", "update_masked", "update_many_on_device",
    "sample", "eval_actions", "q_mean",
]


# ============================================================================ stacking
def stack(agents: Sequence[Any]):
    """Agent pytrees of one class and config -> one pytree with a leading member axis.

    Every leaf strongly typed: a fresh agent's step counters are Python ints (weakly typed) and
    a loaded one's int32, so a resumed run gets the uninterrupted run's compiled programs."""
    if not agents:
        raise ValueError("stack needs at least one agent")

    def strong(*xs):
        first = jnp.asarray(xs[0])
        return jnp.stack([jnp.asarray(x, dtype=first.dtype) for x in xs])

    return jax.tree_util.tree_map(strong, *agents)


def population_size(agents) -> int:
    return int(jax.tree_util.tree_leaves(agents)[0].shape[0])


def member_of(agents, i: int):
    """Member ``i`` of a stacked pytree (an ordinary agent)."""
    return jax.tree_util.tree_map(lambda x: x[i], agents)


def unstack(agents) -> list:
    return [member_of(agents, i) for i in range(population_size(agents))]


def member_metrics(metrics) -> list[dict[str, float]]:
    """Stacked metrics {name: (N,)} -> one dict of floats per member (one host transfer)."""
    host = {k: np.asarray(v) for k, v in jax.device_get(metrics).items()}
    return [{k: float(v[i]) for k, v in host.items() if v[i].size == 1} for i in range(population_size(host))]


# ============================================================================ mapping over the members
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
    use, at most ``n``; 1 off the CPU, where one device's vmapped kernels are the faster layout."""
    if n <= 1 or jax.default_backend() != "cpu":
        return 1
    return min(n, jax.local_device_count())


def _member_loop(fn, axes, *args):
    """``fn`` on each member in turn (``lax.map``): every member runs the single run's own
    unbatched program (up to how XLA fuses it inside the loop)."""
    def one(ms):
        it = iter(ms)
        return fn(*[next(it) if ax == 0 else a for a, ax in zip(args, axes)])

    return jax.lax.map(one, tuple(a for a, ax in zip(args, axes) if ax == 0))


def _across_cores(fn, axes, *args):
    """``fn`` on every member, the members split over one JAX CPU device per core
    (``shard_map``), each device running its members one after another: a vmapped batch of
    members falls out of the caches, members in turn keep the single run's speed (README "What
    it buys"). Padded with copies of member 0 to a multiple of the devices; their results are
    dropped."""
    n = _member_count(axes, args)
    d = host_shards(n)
    if d == 1:
        return _per_member(fn, axes, *args)
    if pad := (-n) % d:
        args = [jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)]), a)
                if ax == 0 else a for a, ax in zip(args, axes)]
    specs = tuple(PartitionSpec("members") if ax == 0 else PartitionSpec() for ax in axes)
    out = jax.shard_map(lambda *a: _member_loop(fn, axes, *a), mesh=_mesh(d), in_specs=specs,
                        out_specs=PartitionSpec("members"), check_vma=False)(*args)
    if pad:
        out = jax.tree_util.tree_map(lambda x: x[:n], out)
    return jax.lax.with_sharding_constraint(out, member_sharding(n))


@functools.lru_cache(maxsize=None)
def _mesh(d: int) -> Mesh:
    return Mesh(np.array(jax.local_devices()[:d]), ("members",))


def member_sharding(n: int):
    """Where a population of ``n`` members keeps its arrays between updates: split over the
    devices along the member axis (replicated when ``n`` does not divide); None for one."""
    d = host_shards(n)
    if d == 1:
        return None
    return NamedSharding(_mesh(d), PartitionSpec("members") if n % d == 0 else PartitionSpec())


def placed(*trees, every_leaf: bool = False):
    """The member-axis inputs of an update put where its outputs will be, so that every call
    compiles to one program; host arrays (a batch) travel by one explicit ``device_put`` of the
    whole tree, never as a jitted call's implicit per-argument transfers. ``every_leaf``: check
    each leaf, not only the first (a warm start's agents: a fresh rng on one device, networks
    split over the members' devices)."""
    sharding = member_sharding(population_size(trees[0]))

    def there(x) -> bool:
        return isinstance(x, jax.Array) and (sharding is None or x.sharding == sharding)

    def put(tree):
        if every_leaf:
            return jax.tree_util.tree_map(lambda x: x if there(x) else jax.device_put(x, sharding), tree)
        if there(jax.tree_util.tree_leaves(tree)[0]):
            return tree  # the agents after their first update: already there (a per-leaf check costs ms)
        return jax.device_put(tree, sharding)

    return tuple(put(t) for t in trees)


def over_members(fn, axes: tuple, *, across_cores: bool):
    """``fn(member, *args)`` of one agent as a function of the population: arguments with axis 0
    are mapped over the members, axis None shared; ``across_cores`` (the updates) splits the
    members over the CPU devices, else vmapped. Keyword arguments are static."""
    mapper = _across_cores if across_cores else _per_member

    def mapped(*args, **static):
        return mapper(functools.partial(fn, **static) if static else fn, axes, *args)

    return mapped


# ============================================================================ the entry points
def _masked(agents, batches, mask, many: bool):
    """Members with ``mask`` False keep their agent (rng included): they did not update."""
    new, metrics = (_update_many if many else _update)(agents, batches)

    def pick(n, o):
        return jnp.where(mask.reshape(mask.shape + (1,) * (n.ndim - 1)), n, o)

    return jax.tree_util.tree_map(pick, new, agents), metrics


_update = over_members(common.update_fn, (0, 0), across_cores=True)
_update_many = over_members(common.update_many_fn, (0, 0), across_cores=True)
jit_update = jax.jit(_update)
jit_update_many = jax.jit(_update_many)
jit_update_masked = jax.jit(_masked, static_argnames=("many",))
jit_update_many_on_device = jax.jit(over_members(common.update_many_on_device_fn, (0, None, 0), across_cores=False),
                                    static_argnames=("num_updates", "batch_size"))
_sample = over_members(common.sample_fn, (0, 0), across_cores=False)
jit_sample = jax.jit(_sample)
jit_eval = jax.jit(over_members(common.eval_fn, (0, 0), across_cores=False))
jit_q_mean = jax.jit(over_members(common.q_mean_fn, (0, None, None), across_cores=False))


def _act_after(learn):
    """``learn`` (an update), then every member's action at its next observation with the
    updated actor, as one program: an online step's two dispatches in one. The agents come back
    with the rng they had before the draw, and the draw's next rng beside them, so a checkpoint
    between the two holds the agents the separate calls would hold (``act`` restores the rng)."""
    def fn(agents, batches, observations):
        agents, metrics = learn(agents, batches)
        actions, rng = _sample(common.acting_view(agents), observations)
        return agents, metrics, actions, rng
    return fn


jit_act_after_update = jax.jit(_act_after(_update))
jit_act_after_update_many = jax.jit(_act_after(_update_many))


def as_f32(x):
    # host arrays stay on the host until the update places them (one copy, to their devices);
    # device arrays stay on their device
    return x.astype(jnp.float32) if isinstance(x, jax.Array) else np.asarray(x, np.float32)


def _f32(batch: dict) -> dict:
    batch = common.checked_batch(batch)
    return {k: as_f32(batch[k]) for k in common.BATCH_KEYS}


def update(agents, batches):
    """One ``update`` per member; ``batches`` (N, B, ...). Returns (agents, metrics (N,))."""
    return jit_update(*placed(agents, _f32(batches)))


def update_many(agents, batches):
    """K updates per member under one ``lax.scan``; ``batches`` (N, K, B, ...)."""
    return jit_update_many(*placed(agents, _f32(batches)))


def update_then_sample(agents, batches, observations, *, many: bool = False):
    """``update`` (``many``: ``update_many``) and then ``sample`` at ``observations`` (N, O) with
    the updated agents, in one jitted call. Returns (agents, metrics, actions, rng): the agents
    with the rng before the draw; ``agents.replace(rng=rng)`` is what ``sample`` would return."""
    agents, batches = placed(agents, _f32(batches))
    return (jit_act_after_update_many if many else jit_act_after_update)(agents, batches,
                                                                          on_members(observations, agents))


def update_masked(agents, batches, mask, *, many: bool = False):
    """``update`` (or ``update_many``) where only the members with ``mask`` True update; the
    others keep their agent exactly (their rows of ``batches`` are ignored)."""
    return jit_update_masked(*placed(agents, _f32(batches), np.asarray(mask, bool)), many=many)


def update_many_on_device(agents, arrays: dict, keys, num_updates: int, batch_size: int):
    """``update_many_on_device`` per member from one shared on-device dataset; ``keys`` (N, 2)."""
    return jit_update_many_on_device(agents, common.checked_batch(arrays), keys, num_updates=num_updates,
                                     batch_size=batch_size)


def on_members(x, like, *, shared: bool = False):
    """A host array where a population's jitted call reads it: split over the devices its agents
    ``like`` are split over (``shared``: a copy on each), by one explicit transfer; given the
    host array, a call would copy it twice (to one device, then on to the members')."""
    x = as_f32(x)
    sharding = getattr(jax.tree_util.tree_leaves(like)[0], "sharding", None)
    if not isinstance(sharding, NamedSharding):
        return jax.device_put(x)  # one device (uncommitted, as a jitted call's own copy would be)
    return jax.device_put(x, NamedSharding(sharding.mesh, PartitionSpec()) if shared else sharding)


def sample(agents, observations):
    """Stochastic actions of every member at its own observation(s): (N, O) -> (N, A)."""
    view = common.acting_view(agents)
    actions, rng = jit_sample(view, on_members(observations, view))
    return actions, agents.replace(rng=rng)


def eval_actions(agents, observations):
    """Deterministic actions: (N, O) -> (N, A) or (N, E, O) -> (N, E, A)."""
    view = common.acting_view(agents)
    return jit_eval(view, on_members(observations, view))


def q_mean(agents, observations, actions):
    """Mean over each member's critic ensemble of Q(s, a) on shared (s, a): (N, B)."""
    return jit_q_mean(agents, on_members(observations, agents, shared=True), on_members(actions, agents, shared=True))

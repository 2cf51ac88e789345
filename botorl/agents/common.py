"""Pieces every agent shares: jitted entry points, the actor-critic base, chunked gradients, checks.

Agents are ``flax.struct.PyTreeNode``s whose config is a static field, so one module-level
``jax.jit`` serves every agent class (class and config are in the jit cache key): an update
on the same shapes and config compiles once, whatever agent instance it is called with.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import optax
from flax.training.train_state import TrainState

from botorl.batch import BATCH_KEYS, TRANSITION_KEYS, Batch
from botorl.errors import ConfigError
from botorl.networks import CriticEnsemble, TanhGaussianActor, sample_tanh_gaussian

__all__ = [
    "TrainState", "acting_view", "update_fn", "update_many_fn", "sample_fn", "eval_fn", "q_mean_fn",
    "update_many_on_device_fn", "jit_agent_update", "jit_agent_update_many", "jit_agent_sample", "jit_agent_eval",
    "jit_agent_q_mean", "adam",
    "train_state", "checked_batch", "chunk_size", "summed_value_and_grad", "update_many_on_device", "sample_batches",
    "module_def", "ActorCriticAgent", "check_fields",
]


@functools.lru_cache(maxsize=None)
def adam(lr: float) -> optax.GradientTransformation:
    # Cached so the same learning rate gives the same (hashable, equal) static object and
    # agents built from equal configs share jit cache entries.
    return optax.adam(lr)


def train_state(module, key, lr: float, *inputs) -> TrainState:
    """A fresh ``TrainState`` of ``module`` initialised on ``inputs``, trained by Adam at ``lr``."""
    return TrainState.create(apply_fn=module.apply, params=module.init(key, *inputs)["params"], tx=adam(lr))


# ------------------------------------------------------------------ chunked gradients
# A loss that is a sum of per-row terms has as gradient the sum of its chunks' gradients; on
# a CPU, chunk by chunk is ~1.4-2x faster once a layer's activations outgrow the caches. The
# best chunk held ~256k floats per layer (rows x members x width), below ~128 rows the
# per-chunk overhead wins, and an accelerator wants one big batch (docs/performance.md).
CPU_CHUNK_FLOATS = 262_144
MIN_CHUNK_ROWS = 256


def auto_chunk_rows(floats_per_row: int) -> int:
    """Rows per chunk for a network whose layers hold ``floats_per_row`` activations per row
    (members x widest layer): 0 (one chunk) off the CPU."""
    if jax.default_backend() != "cpu":
        return 0
    return max(MIN_CHUNK_ROWS, CPU_CHUNK_FLOATS // max(1, floats_per_row))


def chunk_size(num: int, rows_per_item: int, chunk_rows: int | None, floats_per_row: int = 1) -> int:
    """Items per chunk: the largest divisor of ``num`` whose rows fit in ``chunk_rows`` (None:
    ``auto_chunk_rows``; 0: no chunking, ``num``)."""
    if chunk_rows is None:
        chunk_rows = auto_chunk_rows(floats_per_row)
    if chunk_rows <= 0 or num * rows_per_item <= chunk_rows:
        return num
    return max(d for d in range(1, num + 1) if num % d == 0 and (d * rows_per_item <= chunk_rows or d == 1))


def summed_value_and_grad(loss_fn, params, rows, per_chunk: int):
    """``value_and_grad(loss_fn, has_aux=True)(params, rows)`` for a ``loss_fn`` whose value
    and aux are sums over the leading axis of every leaf of ``rows``, computed over chunks of
    ``per_chunk`` rows under a ``lax.scan`` and summed. Same result up to float rounding."""
    value_and_grad = jax.value_and_grad(loss_fn, has_aux=True)
    num = jax.tree_util.tree_leaves(rows)[0].shape[0]
    if per_chunk >= num:
        return value_and_grad(params, rows)
    chunks = jax.tree_util.tree_map(lambda x: x.reshape((num // per_chunk, per_chunk) + x.shape[1:]), rows)

    def body(acc, chunk):
        return jax.tree_util.tree_map(jnp.add, acc, value_and_grad(params, chunk)), None

    shapes = jax.eval_shape(value_and_grad, params, jax.tree_util.tree_map(lambda x: x[0], chunks))
    zeros = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    return jax.lax.scan(body, zeros, chunks)[0]


# ------------------------------------------------------------------ the traced bodies
# One agent's update, update_many, action draws and Q mean as plain traced functions: the
# ``jit_agent_*`` below are these jitted for one agent (its methods call them), and a population
# maps the same functions over its member axis and jits that (``population.jit_update`` and the
# rest, agents/population.py).
def update_fn(agent, batch):
    return agent.train_step(batch)


def update_many_fn(agent, batches):
    agent, infos = jax.lax.scan(lambda a, b: a.train_step(b), agent, batches)
    # Mean over the K updates: less noisy to log than the last one.
    return agent, jax.tree_util.tree_map(jnp.mean, infos)


def acting_view(agent):
    """The agent with only what acting reads, the actor's parameters and the rng; every other
    field None: a jitted call costs per leaf of its arguments and results (docs/performance.md,
    "What a paper run costs")."""
    cleared = {f.name: None for f in dataclasses.fields(agent)
               if f.metadata.get("pytree_node", True) and f.name not in ("actor", "rng")}
    return agent.replace(actor=agent.actor.replace(opt_state=None), **cleared)


def sample_fn(view, observations):
    """(actions, next rng) of an ``acting_view``: a draw from its tanh-Gaussian ``policy``."""
    rng, key = jax.random.split(view.rng)
    actions, _ = sample_tanh_gaussian(key, *view.policy(observations))
    return actions, rng


def eval_fn(view, observations):
    return jnp.tanh(view.policy(observations)[0])  # the deterministic evaluation action of WSRL/Cal-QL


def q_mean_fn(agent, observations, actions):
    """Mean over the critic ensemble of Q(s, a): (B,)."""
    return agent.critic_values(agent.critic.params, observations, actions).mean(axis=0)


def sample_batches(arrays: dict, key, num_batches: int, batch_size: int) -> Batch:
    """``num_batches`` uniform batches (with replacement) of ``arrays``' rows, stacked (K, B, ...)."""
    n = arrays["rewards"].shape[0]
    idx = jax.random.randint(key, (num_batches, batch_size), 0, n)
    return jax.tree_util.tree_map(lambda x: x[idx], arrays)


def update_many_on_device_fn(agent, arrays, key, num_updates: int, batch_size: int):
    return update_many_fn(agent, sample_batches(arrays, key, num_updates, batch_size))


jit_agent_update = jax.jit(update_fn)
jit_agent_update_many = jax.jit(update_many_fn)
jit_agent_sample = jax.jit(sample_fn)
jit_agent_eval = jax.jit(eval_fn)
jit_agent_q_mean = jax.jit(q_mean_fn)
_jit_agent_update_many_on_device = jax.jit(update_many_on_device_fn, static_argnames=("num_updates", "batch_size"))


def update_many_on_device(agent, arrays: dict, key: jax.Array, num_updates: int, batch_size: int):
    """``agent.update_many`` on ``num_updates`` uniform batches drawn inside the jitted call
    from ``arrays`` (``Dataset.to_device()``): no host sampling or copy per call, what an
    accelerator wants (``offline.sample_on_device``). Same key, same batches."""
    return _jit_agent_update_many_on_device(agent, checked_batch(arrays), key, num_updates, batch_size)


def checked_batch(batch) -> Batch:
    """``batch`` with ``mc_returns`` (zeros when missing); ConfigError for a missing key."""
    if not isinstance(batch, dict):
        raise ConfigError(
            f"an agent update got a {type(batch).__name__}, not a batch dict; pass a dict with "
            f"the keys {', '.join(BATCH_KEYS)} (CONTRACTS.md, Batch)."
        )
    if missing := [k for k in TRANSITION_KEYS if k not in batch]:
        raise ConfigError(
            f"the batch given to an agent update lacks {', '.join(missing)}; a Batch needs "
            f"{', '.join(BATCH_KEYS)} (mc_returns may be zeros). Build it with "
            f"Dataset.sample or ReplayBuffer.sample."
        )
    if "mc_returns" not in batch:
        batch = {**batch, "mc_returns": jnp.zeros_like(batch["rewards"])}
    return batch


# ------------------------------------------------------------------ configs and networks
def check_fields(config, checks) -> None:
    """ConfigError for the first ``(field, ok(config), why)`` of ``checks`` whose ``ok`` is
    false; ``why`` may name other fields of the config in braces."""
    for field, ok, why in checks:
        if not ok(config):
            raise ConfigError(f"{type(config).__name__}.{field} = {getattr(config, field)!r} is invalid: "
                              f"{why.format_map(vars(config))}.")


def is_rate(v) -> bool:
    return math.isfinite(v) and v >= 0  # a negative rate climbs the loss


RATE_WHY = "a learning rate must be a finite number >= 0, e.g. 3e-4"
ACTOR_CRITIC_CHECKS = (
    ("num_critics", lambda c: c.num_critics >= 1, "need at least one critic"),
    *((f, lambda c, f=f: is_rate(getattr(c, f)), RATE_WHY) for f in ("actor_lr", "critic_lr")),
    ("log_std_min", lambda c: math.isfinite(c.log_std_min) and math.isfinite(c.log_std_max)
     and c.log_std_min < c.log_std_max, "the actor's log-std range needs log_std_min < log_std_max (= {log_std_max!r})"),
)


@functools.lru_cache(maxsize=None)
def module_def(cls, **fields):
    """``cls(**fields)``, cached: equal settings give the same module object, so agents built from
    equal configs share their jit cache entries."""
    return cls(**fields)


class ActorCriticAgent:
    """The public entry points (the jitted functions above) and the networks every agent has
    (SAC, CQL, IQL): a tanh-Gaussian actor, a critic ensemble and its target parameters."""

    def update(self, batch):
        """One learning step (SAC: u critic steps + 1 actor + 1 temperature on a batch of u
        minibatches, (u, B, ...), or one, (B, ...)); jitted."""
        return jit_agent_update(self, checked_batch(batch))

    def update_many(self, batches):
        """K updates in one call (``lax.scan``); batches have a leading axis K."""
        return jit_agent_update_many(self, checked_batch(batches))

    def sample_actions(self, observations):
        actions, rng = jit_agent_sample(acting_view(self), jnp.asarray(observations, jnp.float32))
        return actions, self.replace(rng=rng)

    def eval_actions(self, observations):
        return jit_agent_eval(acting_view(self), jnp.asarray(observations, jnp.float32))

    @classmethod
    def _init(cls, config, obs_dim: int, action_dim: int, seed: int):
        """``(rng, actor, critic, the key of the agent's third network, a dummy observation)``."""
        config.validate()
        if obs_dim < 1 or action_dim < 1:
            raise ConfigError(f"{cls.__name__}.create needs obs_dim >= 1 and action_dim >= 1, got {obs_dim}, {action_dim}.")
        rng, k_actor, k_critic, k_third = jax.random.split(jax.random.PRNGKey(seed), 4)
        obs = jnp.zeros((1, obs_dim), jnp.float32)
        act = jnp.zeros((1, action_dim), jnp.float32)
        a_def = module_def(
            TanhGaussianActor, hidden_dims=config.actor_hidden_dims, action_dim=action_dim,
            use_layer_norm=config.actor_layer_norm, dropout_rate=getattr(config, "actor_dropout", None),
            state_dependent_std=config.state_dependent_std, log_std_min=config.log_std_min, log_std_max=config.log_std_max,
        )
        actor = train_state(a_def, k_actor, config.actor_lr, obs)
        c_def = module_def(CriticEnsemble, hidden_dims=config.critic_hidden_dims, num=config.num_critics,
                           use_layer_norm=config.critic_layer_norm)
        critic = train_state(c_def, k_critic, config.critic_lr, obs, act)
        return rng, actor, critic, k_third, obs

    @property
    def action_dim(self) -> int:
        return self.actor.params["mean"]["kernel"].shape[-1]

    def policy(self, observations, actor_params=None, *, dropout_key=None):
        """``(mean, log_std)`` of the pre-tanh Gaussian; dropout active when given its key."""
        params = self.actor.params if actor_params is None else actor_params
        if dropout_key is None:
            return self.actor.apply_fn({"params": params}, observations)
        return self.actor.apply_fn({"params": params}, observations, training=True, rngs={"dropout": dropout_key})

    def critic_values(self, params, observations, actions) -> jax.Array:
        """All members: (N, B)."""
        return self.critic.apply_fn({"params": params}, observations, actions)

    def critic_stepped(self, grads, tau: float):
        """The agent after one gradient step of its critic and the Polyak update of its targets."""
        critic = self.critic.apply_gradients(grads=grads)
        return self.replace(critic=critic, target_critic_params=optax.incremental_update(
            critic.params, self.target_critic_params, tau))

    def target_min(self, key, observations, actions, num: int, replace: bool) -> jax.Array:
        """min over ``num`` target critics of Q'(s, a): (B,); the members drawn independently
        (``replace``, WSRL) or a random subset of distinct ones (RLPD)."""
        cfg = self.config
        sub = self.target_critic_params
        if replace or num != cfg.num_critics:
            idx = (jax.random.randint(key, (num,), 0, cfg.num_critics) if replace
                   else jax.random.permutation(key, cfg.num_critics)[:num])
            sub = jax.tree_util.tree_map(lambda p: p[idx], sub)
        sub_def = module_def(CriticEnsemble, hidden_dims=cfg.critic_hidden_dims, num=num,
                             use_layer_norm=cfg.critic_layer_norm)
        return sub_def.apply({"params": sub}, observations, actions).min(axis=0)

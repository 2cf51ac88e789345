"""Pieces every agent shares: jitted entry points, Polyak averaging, batch checks.

Agents are ``flax.struct.PyTreeNode``s whose config is a static field, so one module-level
``jax.jit`` serves every agent class: the class and config are part of the pytree
structure (the jit cache key), the arrays are traced. An update on the same shapes and
config therefore compiles once, whatever agent instance it is called with.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import optax
from flax.training.train_state import TrainState

from botorl.errors import ConfigError
from botorl.networks import sample_tanh_gaussian, tanh_gaussian_mode

__all__ = ["TrainState", "polyak", "jit_update", "jit_update_many", "jit_sample", "jit_eval", "adam", "check_batch"]

BATCH_KEYS = ("observations", "actions", "rewards", "next_observations", "dones", "mc_returns")


def polyak(params, target_params, tau: float):
    return jax.tree_util.tree_map(lambda p, t: tau * p + (1.0 - tau) * t, params, target_params)


@functools.lru_cache(maxsize=None)
def adam(lr: float) -> optax.GradientTransformation:
    # Cached so the same learning rate gives the same (hashable, equal) static object and
    # agents built from equal configs share jit cache entries.
    return optax.adam(lr)


def _update(agent, batch):
    return agent._update(batch)


def _update_many(agent, batches):
    def body(a, b):
        a, info = a._update(b)
        return a, info

    agent, infos = jax.lax.scan(body, agent, batches)
    # Mean over the K updates: less noisy to log than the last one.
    return agent, jax.tree_util.tree_map(jnp.mean, infos)


def _sample(agent, observations):
    # Every agent's actor is a tanh-Gaussian behind ``agent.policy`` (SAC, CQL, IQL alike).
    rng, key = jax.random.split(agent.rng)
    mean, log_std = agent.policy(observations)
    actions, _ = sample_tanh_gaussian(key, mean, log_std)
    return actions, agent.replace(rng=rng)


def _eval(agent, observations):
    mean, _ = agent.policy(observations)
    return tanh_gaussian_mode(mean)


jit_update = jax.jit(_update)
jit_update_many = jax.jit(_update_many)
jit_sample = jax.jit(_sample)
jit_eval = jax.jit(_eval)


def check_batch(batch, *, many: bool = False) -> None:
    """Raise ConfigError for a batch missing a key (cheap; runs before jit)."""
    if not isinstance(batch, dict):
        raise ConfigError(
            f"an agent update got a {type(batch).__name__}, not a batch dict; pass a dict with "
            f"the keys {', '.join(BATCH_KEYS)} (CONTRACTS.md, Batch)."
        )
    missing = [k for k in BATCH_KEYS if k not in batch and k != "mc_returns"]
    if missing:
        raise ConfigError(
            f"the batch given to an agent update lacks {', '.join(missing)}; a Batch needs "
            f"{', '.join(BATCH_KEYS)} (mc_returns may be zeros). Build it with "
            f"Dataset.sample or ReplayBuffer.sample."
        )


def ensure_mc_returns(batch):
    if "mc_returns" not in batch:
        batch = dict(batch)
        batch["mc_returns"] = jnp.zeros_like(batch["rewards"])
    return batch


def frozen_replace(config, **changes):
    return dataclasses.replace(config, **changes)

"""Tanh-squashed Gaussian policy and its sampling / log-prob helpers.

The module returns the mean and log-std of the Gaussian over the pre-tanh action u; the
action is a = tanh(u), and ``log pi(a|s) = sum_i [log N(u_i; mean_i, std_i) - log(1 -
tanh(u_i)^2)]``, the second term in TensorFlow Probability's stable form.
"""

from __future__ import annotations

import math
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from botorl.networks.common import MLP

_LOG_2PI = math.log(2.0 * math.pi)
# Dataset actions are clipped to +-(1 - 1e-5) on construction (CONTRACTS.md); this keeps
# atanh finite for anything that slips past.
_ATANH_CLIP = 1.0 - 1e-6


class TanhGaussianActor(nn.Module):
    """Gaussian over pre-tanh actions; ``__call__`` returns ``(mean, log_std)``, log-std clipped
    to ``[log_std_min, log_std_max]`` (one learnt vector without ``state_dependent_std``, IQL's)."""

    hidden_dims: Sequence[int]
    action_dim: int
    use_layer_norm: bool = False
    dropout_rate: float | None = None
    state_dependent_std: bool = True
    log_std_min: float = -20.0
    log_std_max: float = 2.0

    @nn.compact
    def __call__(self, observations: jax.Array, training: bool = False):
        x = MLP(self.hidden_dims, use_layer_norm=self.use_layer_norm,
                dropout_rate=self.dropout_rate)(observations, training=training)
        mean = nn.Dense(self.action_dim, kernel_init=nn.initializers.xavier_uniform(), name="mean")(x)
        if self.state_dependent_std:
            log_std = nn.Dense(self.action_dim, kernel_init=nn.initializers.xavier_uniform(), name="log_std")(x)
        else:
            log_std = self.param("log_std", nn.initializers.zeros, (self.action_dim,))
            log_std = jnp.broadcast_to(log_std, mean.shape)
        log_std = jnp.clip(log_std, self.log_std_min, self.log_std_max)
        return mean, log_std


def _log_det_tanh(u: jax.Array) -> jax.Array:
    # log(1 - tanh(u)^2), stable for large |u|
    return 2.0 * (math.log(2.0) - u - jax.nn.softplus(-2.0 * u))


def sample_tanh_gaussian(key: jax.Array, mean: jax.Array, log_std: jax.Array, num_samples: int | None = None):
    """Reparameterised sample ``a = tanh(mean + std * eps)`` and its log-prob; ``num_samples=n``
    adds an axis before the action axis: actions ``(..., n, A)``, log-probs ``(..., n)``."""
    shape = mean.shape
    if num_samples is not None:
        mean, log_std = jnp.expand_dims(mean, -2), jnp.expand_dims(log_std, -2)
        shape = mean.shape[:-2] + (num_samples, mean.shape[-1])
    return tanh_gaussian_from_noise(jax.random.normal(key, shape, mean.dtype), mean, log_std)


def tanh_gaussian_from_noise(eps: jax.Array, mean: jax.Array, log_std: jax.Array):
    """``a = tanh(mean + std * eps)`` and its log-prob, for standard normal noise drawn
    beforehand (so a batch can be processed in chunks with the noise of the whole batch)."""
    u = mean + jnp.exp(log_std) * eps
    log_prob = jnp.sum(-0.5 * eps * eps - log_std - 0.5 * _LOG_2PI, axis=-1) - jnp.sum(_log_det_tanh(u), axis=-1)
    return jnp.tanh(u), log_prob


def tanh_gaussian_log_prob(mean: jax.Array, log_std: jax.Array, actions: jax.Array) -> jax.Array:
    """log pi(a|s) of given squashed actions (e.g. dataset actions for IQL's AWR)."""
    u = jnp.arctanh(jnp.clip(actions, -_ATANH_CLIP, _ATANH_CLIP))
    z = (u - mean) * jnp.exp(-log_std)
    gaussian = jnp.sum(-0.5 * z * z - log_std - 0.5 * _LOG_2PI, axis=-1)
    return gaussian - jnp.sum(_log_det_tanh(u), axis=-1)

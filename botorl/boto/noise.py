"""Action-noise distributions q_sigma(a_bar | a) for the BOTO objective, vectorised in JAX.

* **hybrid** (paper B.1, after Oh & Lee 2025): ``t = exp(U(log_sigma, 0))`` per row, then
  ``a_bar ~ w(t) * Uniform([-1, 1]^A) + (1 - w(t)) * Normal(a, t^2 I)``; **w(t) = t is OUR
  choice** (no source gives it; docs/methods.md, "BOTO: the choices the paper leaves open").
* **gaussian**: ``a_bar ~ Normal(a, sigma^2 I)`` (the bandit figure 3, unclipped there to
  compare with the closed-form Q*).
* **none**: ``a_bar = a``, so the penalty is 0 and the BOTO stage is a soft-backup re-fit of
  the critic on D_offline u D_warmup: the ablation's *re-fit control*, the same data, steps
  and optimiser as BOTO with no bound. Its target keeps BOTO's entropy term (unless
  ``backup_entropy`` is off), which pre-training and fine-tuning do not use: not a plain
  re-fit with their own target (docs/results/why-boto.md).

All return ``(a_bar, info)``, ``info`` per row: ``uniform`` (drawn from the uniform component)
and ``t`` (the noise scale; sigma for the Gaussian kind).
"""

from __future__ import annotations

import math
from typing import Callable, Union

import jax
import jax.numpy as jnp

from botorl.errors import ConfigError

WeightSpec = Union[str, float, Callable[[jax.Array], jax.Array]]

ACTION_LOW, ACTION_HIGH = -1.0, 1.0


def resolve_weight_fn(weight_fn: WeightSpec) -> Callable[[jax.Array], jax.Array]:
    """``t -> w(t)``: ``"linear"`` (w = t), ``"zero"``, a constant p in [0, 1], or a callable
    from [0, 1] to [0, 1], used as is."""
    if callable(weight_fn):
        return weight_fn
    if isinstance(weight_fn, str):
        name = weight_fn.strip().lower()
        if name == "linear":
            return lambda t: t
        try:
            weight_fn = 0.0 if name == "zero" else float(name)
        except ValueError:
            raise ConfigError(
                f"boto noise weight_fn={weight_fn!r} is not known. Use 'linear' (w(t) = t, the "
                "default), 'zero', or a constant probability such as 0.1."
            ) from None
    p = float(weight_fn)
    if not 0.0 <= p <= 1.0 or math.isnan(p):
        raise ConfigError(
            f"boto noise weight_fn={weight_fn!r}: a constant mixing weight must be a probability "
            "in [0, 1]. Use e.g. 0.05, or 'linear' for w(t) = t."
        )
    return lambda t: jnp.full_like(t, p)


def _check_log_sigma(log_sigma: float) -> None:
    if not (log_sigma < 0.0) or math.isinf(log_sigma):
        raise ConfigError(
            f"boto log_sigma={log_sigma!r} must be a finite negative number (the hybrid noise "
            "draws log t uniformly from [log_sigma, 0]); the paper uses -20, and -30 on "
            "antmaze-large-diverse."
        )


def hybrid_noise(key: jax.Array, actions: jax.Array, log_sigma: float, weight_fn: WeightSpec = "linear", *,
                 clip: bool = True) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Draw a_bar ~ q_sigma^hyb(. | a) for every row of ``actions`` (shape (..., A)).

    ``log_sigma`` may be a Python float (checked) or a traced scalar (not checked).
    """
    if isinstance(log_sigma, (int, float)):
        _check_log_sigma(float(log_sigma))
    w = resolve_weight_fn(weight_fn)
    k_lam, k_mix, k_uni, k_gauss = jax.random.split(key, 4)
    batch_shape = actions.shape[:-1]
    lam = jax.random.uniform(k_lam, batch_shape, minval=log_sigma, maxval=0.0)
    t = jnp.exp(lam)
    uniform = jax.random.uniform(k_mix, batch_shape) < w(t)
    a_uni = jax.random.uniform(k_uni, actions.shape, minval=ACTION_LOW, maxval=ACTION_HIGH, dtype=actions.dtype)
    a_gauss = actions + t[..., None] * jax.random.normal(k_gauss, actions.shape, actions.dtype)
    a_bar = jnp.where(uniform[..., None], a_uni, a_gauss)
    if clip:
        a_bar = jnp.clip(a_bar, ACTION_LOW, ACTION_HIGH)
    return a_bar, {"uniform": uniform, "t": t}


def gaussian_noise(key: jax.Array, actions: jax.Array, sigma: float, *,
                   clip: bool = True) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Draw a_bar ~ Normal(a, sigma^2 I) for every row of ``actions``."""
    if isinstance(sigma, (int, float)) and not sigma > 0.0:
        raise ConfigError(f"boto gaussian noise sigma={sigma!r} must be positive (e.g. 0.25).")
    a_bar = actions + sigma * jax.random.normal(key, actions.shape, actions.dtype)
    if clip:
        a_bar = jnp.clip(a_bar, ACTION_LOW, ACTION_HIGH)
    batch_shape = actions.shape[:-1]
    return a_bar, {"uniform": jnp.zeros(batch_shape, bool), "t": jnp.full(batch_shape, sigma, actions.dtype)}


NOISE_KINDS = ("hybrid", "gaussian", "none")


def make_noise_fn(kind: str, *, log_sigma: float = -20.0, sigma: float = 0.25, weight_fn: WeightSpec = "linear",
                  clip: bool = True) -> Callable[[jax.Array, jax.Array], tuple[jax.Array, dict[str, jax.Array]]]:
    """``(key, actions) -> (a_bar, info)`` for ``kind`` in ``NOISE_KINDS``; checks the
    settings now so that a bad value fails before anything is compiled."""
    if kind == "hybrid":
        _check_log_sigma(float(log_sigma))
        w = resolve_weight_fn(weight_fn)
        return lambda key, a: hybrid_noise(key, a, log_sigma, w, clip=clip)
    if kind == "gaussian":
        if not sigma > 0.0:
            raise ConfigError(f"boto gaussian noise sigma={sigma!r} must be positive (e.g. 0.25).")
        return lambda key, a: gaussian_noise(key, a, sigma, clip=clip)
    if kind == "none":  # a_bar = a, the re-fit control: no action is perturbed, so nothing is bounded
        return lambda key, a: (a, {"uniform": jnp.zeros(a.shape[:-1], bool), "t": jnp.zeros(a.shape[:-1], a.dtype)})
    raise ConfigError(f"boto noise kind={kind!r} is not known; use one of {', '.join(NOISE_KINDS)}.")

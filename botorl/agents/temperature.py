"""The SAC temperature at which a pre-trained actor's spread is already optimal.

A warm start from IQL carries no temperature, and starting SAC's at 1.0 widens IQL's narrow
actor for thousands of steps. ``stationary_temperature`` picks ``tau = mean k_d sigma_d^2``
instead, where SAC's actor objective under the pre-trained critic leaves the spread where it
is; the derivation is on the docs' Methods page ("The temperature after IQL"). The mean over
(state, dimension) pairs zeroes the derivative along a common rescaling of all stds: for a
state-independent std (IQL's on antmaze) exactly that parameter's gradient direction. With the
tanh squashing, ``sigma_eff = (1 - tanh(mean)^2) exp(log_std)`` is the std in action space (to
first order).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from botorl.errors import ConfigError

__all__ = ["stationary_temperature", "curvature_and_spread", "MIN_TEMP", "INIT_TEMP_RULES"]

# SACConfig.init_temp_rule: how a warm start without a temperature (from IQL) sets it.
INIT_TEMP_RULES = ("stationary", "fixed")

MIN_TEMP = 1e-4
# States per vmapped Hessian chunk: bounds the memory of the A tangents through N critics.
_CHUNK = 128


@jax.jit
def curvature_and_spread(actor, critic, observations):
    """``(k, sigma_eff)``, each (B, A): ``k = -diag d^2 Q / da^2`` of the ensemble-mean Q at
    ``a = tanh(mean)``, and the tanh-squashed policy's std in action space there, from the
    actor and critic TrainStates of any botorl agent (IQL, SAC, CQL)."""
    mean, log_std = actor.apply_fn({"params": actor.params}, observations)
    a0 = jnp.tanh(mean)
    sigma_eff = (1.0 - a0 * a0) * jnp.exp(log_std)

    def one(xs):
        obs, act = xs
        # the ensemble-mean Q of this one (observation, action) pair, a scalar
        hess = jax.hessian(lambda a: critic.apply_fn({"params": critic.params}, obs[None], a[None]).mean())(act)
        return -jnp.diagonal(hess)

    k = jax.lax.map(one, (observations, a0), batch_size=min(_CHUNK, observations.shape[0]))
    return k, sigma_eff


def stationary_temperature(agent, observations, init_temp: float = 1.0, min_temp: float = MIN_TEMP):
    """The temperature at which SAC's actor objective is stationary in the pre-trained actor's
    std (module docstring): ``(tau0, info)``. Pairs with ``k <= 0`` (no stationary spread) are
    left out; with none left (a critic piecewise linear in the action) ``tau0 = init_temp``.

    ``observations``: (B, O) probe states, e.g. ~1,000 rows of the offline data. ``info``:
    ``rule`` ("stationary" or "fallback"), ``tau_raw`` (before clipping; None on fallback),
    ``used`` (fraction of (state, dim) pairs with positive curvature), ``tau_per_dim`` (the
    rule per action dimension, NaN where no state has positive curvature), ``mean_sigma_eff``,
    ``clipped`` and ``reason``. Pure: the agent is not changed."""
    obs = np.asarray(observations, np.float32)
    if obs.ndim != 2 or obs.shape[0] < 1 or not np.all(np.isfinite(obs)):
        raise ConfigError(
            f"stationary_temperature: observations must be a finite (B, obs_dim) array with B >= 1 "
            f"(a probe of dataset states), got shape {obs.shape}."
        )
    if not (0 < min_temp <= init_temp):
        raise ConfigError(f"stationary_temperature: need 0 < min_temp <= init_temp, got {min_temp}, {init_temp}.")
    k, sigma = curvature_and_spread(agent.actor, agent.critic, jnp.asarray(obs))
    k, sigma = np.asarray(k, np.float64), np.asarray(sigma, np.float64)
    tau_sd = k * sigma * sigma
    ok = (k > 0) & np.isfinite(tau_sd)
    with np.errstate(invalid="ignore"):
        per_dim = np.where(ok.any(0), np.where(ok, tau_sd, 0.0).sum(0) / ok.sum(0), np.nan)
    info = {"used": float(ok.mean()), "tau_per_dim": per_dim.tolist(), "mean_sigma_eff": float(sigma.mean()),
            "mean_curvature": float(k.mean())}
    if not ok.any():
        return float(init_temp), {
            **info, "rule": "fallback", "tau_raw": None, "clipped": False,
            "reason": (f"the critic has no positive curvature in the action at any probe state and dimension "
                       f"(flat or convex, e.g. a ReLU critic without LayerNorm); the temperature starts at "
                       f"init_temp = {init_temp}"),
        }
    raw = float(tau_sd[ok].mean())
    tau0 = float(min(max(raw, min_temp), init_temp))
    return tau0, {
        **info, "rule": "stationary", "tau_raw": raw, "clipped": tau0 != raw,
        "reason": f"mean of k * sigma_eff^2 over {int(ok.sum())} of {ok.size} (state, dim) pairs"
                  + (f", clipped to [{min_temp}, {init_temp}]" if tau0 != raw else ""),
    }

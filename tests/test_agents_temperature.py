"""The initial SAC temperature after a warm start without one (agents/temperature.py).

Probe with a known answer: a critic that is exactly Q(s, a) = -0.5 sum_d k_d(s) (a_d - c_d)^2
and an actor with known mean and log-std give tau0 = mean over (state, dim) with k > 0 of
k_d(s) sigma_eff_d^2, sigma_eff = (1 - tanh(mean)^2) exp(log_std), computed here by hand.
"""

from __future__ import annotations

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from botorl.agents.cql import CQLAgent, CQLConfig
from botorl.agents.iql import IQLAgent, IQLConfig
from botorl.agents.sac import SACAgent, SACConfig
from botorl.agents.temperature import MIN_TEMP, stationary_temperature
from botorl.errors import ConfigError

O, A, P = 3, 3, 16
NET = dict(actor_hidden_dims=(8,), critic_hidden_dims=(8,), num_critics=2)
MEAN = np.array([0.3, -0.5, 0.1], np.float32)
LOG_STD = np.array([-1.0, -2.0, -0.5], np.float32)
# Per member: the ensemble mean of the curvatures counts; dim 2 is convex (excluded).
K = np.array([[2.0, 0.4, -1.0], [1.0, 0.8, -3.0]], np.float32)
C = np.array([0.2, 0.0, -0.4], np.float32)


def quadratic_critic(variables, observations, actions):
    k = variables["params"]["k"]  # (N, A), as parameters: one compile for every scale
    ks = k[:, None, :] * (1.0 + observations[None, :, :1] ** 2)  # k_d(s) varies with s
    return -0.5 * jnp.sum(ks * (actions[None] - C) ** 2, axis=-1)  # (N, B)


def flat_critic(variables, observations, actions):
    return jnp.stack([actions.sum(-1) + observations.sum(-1)] * 2)  # linear in a: no curvature


def expected_tau(obs, scale=1.0):
    k = K.mean(0)[None] * scale * (1.0 + obs[:, :1].astype(np.float64) ** 2)  # (P, A)
    sigma = (1.0 - np.tanh(MEAN.astype(np.float64)) ** 2) * np.exp(LOG_STD.astype(np.float64))
    return float((k * sigma**2)[:, :2].mean())


@pytest.fixture(scope="module")
def obs():
    return np.random.default_rng(0).normal(size=(P, O)).astype(np.float32)


@pytest.fixture(scope="module")
def known_actor_agent():
    """A SAC agent whose actor outputs MEAN and LOG_STD at every state."""
    agent = SACAgent.create(SACConfig(**NET), O, A, seed=0)
    p = jax.tree_util.tree_map(lambda x: x, agent.actor.params)
    p["mean"] = {"kernel": jnp.zeros_like(p["mean"]["kernel"]), "bias": jnp.asarray(MEAN)}
    p["log_std"] = {"kernel": jnp.zeros_like(p["log_std"]["kernel"]), "bias": jnp.asarray(LOG_STD)}
    return agent.replace(actor=agent.actor.replace(params=p))


def with_critic(agent, apply_fn, params=None):
    return agent.replace(critic=agent.critic.replace(apply_fn=apply_fn, params=params))


@pytest.mark.parametrize("scale", [1.0, 1e3, 1e-6])
def test_quadratic_probe_known_answer(known_actor_agent, obs, scale):
    tau0, info = stationary_temperature(with_critic(known_actor_agent, quadratic_critic, {"k": jnp.asarray(K * scale)}), obs, init_temp=1.0)
    want = expected_tau(obs, scale)
    assert info["rule"] == "stationary"
    assert info["used"] == pytest.approx(2 / 3)  # the convex dimension is left out
    assert math.isnan(info["tau_per_dim"][2])
    assert info["tau_raw"] == pytest.approx(want, rel=1e-5)
    # scale 1: inside [1e-4, 1]; 1e3: clipped to init_temp; 1e-6: clipped to MIN_TEMP
    assert tau0 == pytest.approx(min(max(want, MIN_TEMP), 1.0), rel=1e-5)
    assert info["clipped"] == (scale != 1.0)


def test_flat_critic_falls_back_to_init_temp(known_actor_agent, obs):
    tau0, info = stationary_temperature(with_critic(known_actor_agent, flat_critic), obs, init_temp=0.7)
    assert tau0 == 0.7 and info["rule"] == "fallback" and info["tau_raw"] is None
    assert "init_temp" in info["reason"]


def test_relu_critic_without_layer_norm_falls_back(obs):
    # A ReLU network is piecewise linear in the action: its Hessian is 0, no curvature to use.
    agent = SACAgent.create(SACConfig(**NET, critic_layer_norm=False), O, A, seed=1)
    tau0, info = stationary_temperature(agent, obs, init_temp=1.0)
    assert (tau0, info["rule"], info["used"]) == (1.0, "fallback", 0.0)


def test_bad_probe_is_a_config_error(known_actor_agent):
    with pytest.raises(ConfigError, match="observations"):
        stationary_temperature(known_actor_agent, np.zeros((0, O), np.float32))


@pytest.fixture(scope="module")
def iql_agent():
    cfg = IQLConfig(**NET, value_hidden_dims=(8,), actor_layer_norm=True, critic_layer_norm=True)
    return IQLAgent.create(cfg, O, A, seed=3)


def sac_config_for(agent, **kw):
    fields = {f: getattr(agent.config, f) for f in
              ("actor_layer_norm", "critic_layer_norm", "state_dependent_std", "log_std_min", "log_std_max")}
    return SACConfig(**NET, **fields, **kw)


def test_from_iql_starts_at_the_rules_value(iql_agent, obs):
    cfg = sac_config_for(iql_agent)
    want, info = stationary_temperature(iql_agent, obs, init_temp=cfg.init_temp)
    assert info["rule"] == "stationary" and not info["clipped"]  # else the checks below prove little
    sac = SACAgent.from_pretrained(iql_agent, cfg, seed=0, observations=obs)
    assert float(sac.temperature()) == pytest.approx(want, rel=1e-5)
    assert abs(want - cfg.init_temp) > 1e-3
    # the rule off, or no probe: init_temp
    fixed = SACAgent.from_pretrained(iql_agent, sac_config_for(iql_agent, init_temp_rule="fixed"), 0, obs)
    assert float(fixed.temperature()) == pytest.approx(cfg.init_temp, rel=1e-6)
    assert float(SACAgent.from_pretrained(iql_agent, cfg, 0).temperature()) == pytest.approx(cfg.init_temp, rel=1e-6)
    # the new temperature trains (fresh Adam state): an entropy below target raises it
    stepped, _ = sac.temp_step(jnp.asarray(sac.config.target_entropy - 1.0))
    assert float(stepped.temperature()) > float(sac.temperature())


def test_from_iql_without_curvature_warns_and_uses_init_temp(obs):
    cfg = IQLConfig(**NET, value_hidden_dims=(8,), actor_layer_norm=True, critic_layer_norm=False)
    iql = IQLAgent.create(cfg, O, A, seed=4)
    with pytest.warns(UserWarning, match="no positive curvature"):
        sac = SACAgent.from_pretrained(iql, sac_config_for(iql, init_temp=0.5), 0, obs)
    assert float(sac.temperature()) == pytest.approx(0.5, rel=1e-6)


def test_from_calql_keeps_the_carried_temperature(obs):
    cfg = CQLConfig(**NET, cql_n_actions=2, num_backup_actions=2, calql=True)
    calql = CQLAgent.create(cfg, O, A, seed=5)
    calql = calql.replace(temp=calql.temp.replace(params={"log_temp": jnp.asarray(math.log(0.037), jnp.float32)}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sac = SACAgent.from_pretrained(calql, sac_config_for(calql), 0, observations=obs)
    assert float(sac.temperature()) == pytest.approx(0.037, rel=1e-6)


def test_init_temp_rule_is_validated():
    with pytest.raises(ConfigError, match="init_temp_rule"):
        SACAgent.create(SACConfig(**NET, init_temp_rule="adaptive"), O, A)
    SACConfig(init_temp_rule="fixed").validate()

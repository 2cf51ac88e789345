"""CQL and Cal-QL (offline pre-training, stage 1): SAC plus the conservative penalty.

Facts taken from the public Cal-QL code (nakamotoo/Cal-QL, JaxCQL/conservative_sac.py) and
kept here; the code is ours:
- Penalty samples per state s: n uniform actions in [-1, 1]^A, n actions from pi(.|s) and
  n from pi(.|s'); all of them are scored by Q(s, .) (the s' samples too).
- Importance sampling: the logsumexp is over [Q(s, a_unif) - log(0.5^A),
  Q(s, a_pi(s')) - log pi(a|s'), Q(s, a_pi(s)) - log pi(a|s)] (the data action is not in
  it); without IS it is over [Q_unif, Q(s, a_data), Q_pi(s'), Q_pi(s)].
  Then ``ood = cql_temp * logsumexp(cat / cql_temp)`` and
  ``diff = mean_B clip(ood - Q(s, a_data), clip_min, clip_max)``, per ensemble member.
- Cal-QL: before the IS correction, Q of the pi(s) and pi(s') samples is replaced by
  ``max(Q, mc_return(s, a_data))``; the uniform samples are not bounded.
- Fixed weight: penalty = cql_weight * diff. Lagrange: penalty =
  alpha' * cql_weight * (diff - target_action_gap), alpha' = clip(exp(log alpha'), 0, 1e6),
  log alpha' starts at 1.0 with the critic learning rate; the multiplier loss is
  -mean_members(alpha' * cql_weight * (diff - gap)) (diff held fixed), so alpha' grows while
  the gap exceeds the target. Antmaze: weight 5.0, Lagrange, gap 0.8 (scripts/run_antmaze.sh).
- Max-target backup on (min over the critic subset, then max over n next actions).

Our choice: all 3n + 1 actions per state (data, uniform, pi(s), pi(s')) of every ensemble
member are evaluated in ONE critic call -- the observations are repeated 3n + 1 times into
the batch and the vmapped ensemble evaluates all members at once -- since this step
dominates pre-training time. Members' losses are averaged (Cal-QL sums its two critics'
losses; with Adam the scale does not matter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from botorl.agents.common import TrainState, adam, polyak
from botorl.agents.sac import SACAgent, SACConfig, temp_def
from botorl.networks import sample_tanh_gaussian


@dataclass(frozen=True)
class CQLConfig(SACConfig):
    """CQL / Cal-QL pre-training; defaults are Cal-QL on antmaze (algorithms.md s5)."""

    num_critics: int = 10  # WSRL pre-trains with the fine-tuning ensemble size
    utd_ratio: int = 1
    max_target_backup: bool = True
    num_backup_actions: int = 10
    backup_entropy: bool = False
    cql_n_actions: int = 10
    cql_importance_sample: bool = True
    cql_temp: float = 1.0
    cql_weight: float = 5.0
    cql_lagrange: bool = True
    cql_target_action_gap: float = 0.8
    cql_lagrange_init_log: float = 1.0
    cql_lagrange_lr: float = 3e-4
    cql_clip_diff_min: float = -math.inf
    cql_clip_diff_max: float = math.inf
    calql: bool = False

    def validate(self) -> None:
        super().validate()
        from botorl.errors import ConfigError

        if self.cql_n_actions < 1:
            raise ConfigError(f"CQLConfig.cql_n_actions = {self.cql_n_actions} is invalid: need at least 1 sample.")
        if self.cql_temp <= 0:
            raise ConfigError(f"CQLConfig.cql_temp = {self.cql_temp} is invalid: must be positive.")


class CQLAgent(SACAgent):
    """SAC-family agent with the CQL / Cal-QL critic loss; ``lagrange`` holds log alpha'."""

    lagrange: TrainState = None  # CQL weight multiplier alpha' (used when cql_lagrange)

    @classmethod
    def _default_config(cls):
        return CQLConfig()

    @classmethod
    def _extra_fields(cls, config, rng) -> dict:
        l_def = temp_def(math.exp(config.cql_lagrange_init_log))
        params = l_def.init(jax.random.PRNGKey(0))["params"]
        return {"lagrange": TrainState.create(apply_fn=l_def.apply, params=params, tx=adam(config.cql_lagrange_lr))}

    def lagrange_value(self, params=None) -> jax.Array:
        params = self.lagrange.params if params is None else params
        return jnp.clip(self.lagrange.apply_fn({"params": params}), 0.0, 1e6)

    def cql_penalty(self, params, batch, key) -> tuple[jax.Array, jax.Array, dict]:
        """Per-member ``diff`` (N,), the data Q values (N, B), and logging info."""
        cfg = self.config
        obs, next_obs, data_a = batch["observations"], batch["next_observations"], batch["actions"]
        bsz, adim = data_a.shape
        n = cfg.cql_n_actions
        k_unif, k_cur, k_next = jax.random.split(key, 3)
        unif = jax.random.uniform(k_unif, (bsz, n, adim), minval=-1.0, maxval=1.0)
        mean, log_std = self.policy(obs)
        cur_a, cur_logp = sample_tanh_gaussian(k_cur, mean, log_std, n)  # (B, n, A), (B, n)
        mean_n, log_std_n = self.policy(next_obs)
        next_a, next_logp = sample_tanh_gaussian(k_next, mean_n, log_std_n, n)
        cur_a, cur_logp, next_a, next_logp = jax.lax.stop_gradient((cur_a, cur_logp, next_a, next_logp))

        # One pass: per state, [data, n uniform, n pi(s), n pi(s')] all scored at s.
        m = 3 * n + 1
        acts = jnp.concatenate([data_a[:, None], unif, cur_a, next_a], axis=1)  # (B, m, A)
        q_all = self.critic_values(params, jnp.repeat(obs, m, axis=0), acts.reshape(bsz * m, adim))
        q_all = q_all.reshape(q_all.shape[0], bsz, m)  # (N, B, m)
        q_data = q_all[:, :, 0]
        q_unif = q_all[:, :, 1 : 1 + n]
        q_cur = q_all[:, :, 1 + n : 1 + 2 * n]
        q_next = q_all[:, :, 1 + 2 * n :]

        info = {}
        if cfg.calql:
            bound = batch["mc_returns"][None, :, None]
            info["calql_bound_rate"] = jnp.mean(jnp.concatenate([q_cur, q_next], -1) < bound)
            q_cur = jnp.maximum(q_cur, bound)
            q_next = jnp.maximum(q_next, bound)
        if cfg.cql_importance_sample:
            log_unif_density = adim * math.log(0.5)
            cat = jnp.concatenate([q_unif - log_unif_density, q_next - next_logp[None], q_cur - cur_logp[None]], axis=-1)
        else:
            cat = jnp.concatenate([q_unif, q_data[..., None], q_next, q_cur], axis=-1)
        ood = jax.scipy.special.logsumexp(cat / cfg.cql_temp, axis=-1) * cfg.cql_temp  # (N, B)
        diff = jnp.clip(ood - q_data, cfg.cql_clip_diff_min, cfg.cql_clip_diff_max).mean(axis=-1)  # (N,)
        info.update(q_uniform=q_unif.mean(), q_pi=q_cur.mean(), cql_diff=diff.mean())
        return diff, q_data, info

    def critic_loss(self, params, batch, target, key):
        cfg = self.config
        diff, q_data, info = self.cql_penalty(params, batch, key)
        bellman = jnp.mean((q_data - target[None]) ** 2, axis=-1)  # (N,)
        if cfg.cql_lagrange:
            penalty = jax.lax.stop_gradient(self.lagrange_value()) * cfg.cql_weight * (diff - cfg.cql_target_action_gap)
        else:
            penalty = cfg.cql_weight * diff
        loss = jnp.mean(bellman + penalty)
        info.update(critic_loss=loss, bellman_loss=bellman.mean(), cql_loss=penalty.mean(), q_data=q_data.mean(), _diff=diff)
        return loss, info

    def lagrange_loss(self, lagrange_params, diff):
        cfg = self.config
        value = self.lagrange_value(lagrange_params)
        return -jnp.mean(value * cfg.cql_weight * (jax.lax.stop_gradient(diff) - cfg.cql_target_action_gap))

    def critic_step(self, batch, key):
        k_target, k_loss = jax.random.split(key)
        target, t_info = self.target_values(batch, k_target)
        grads, info = jax.grad(self.critic_loss, has_aux=True)(self.critic.params, batch, target, k_loss)
        diff = info.pop("_diff")
        critic = self.critic.apply_gradients(grads=grads)
        target_params = polyak(critic.params, self.target_critic_params, self.config.tau)
        agent = self.replace(critic=critic, target_critic_params=target_params)
        if self.config.cql_lagrange:
            l_loss, l_grads = jax.value_and_grad(self.lagrange_loss)(self.lagrange.params, diff)
            agent = agent.replace(lagrange=self.lagrange.apply_gradients(grads=l_grads))
            info.update(lagrange_loss=l_loss, cql_alpha_prime=self.lagrange_value())
        return agent, {**info, **t_info}

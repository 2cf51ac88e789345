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
- Fixed weight: penalty = cql_weight * diff. Lagrange: penalty = alpha' * (diff -
  target_action_gap), alpha' = clip(exp(log alpha'), 0, 1e6), with the multiplier loss
  -mean_members(alpha' * (diff - gap)) (diff held fixed), so alpha' grows while the gap
  exceeds the target. That is WSRL's CQL (wsrl/agents/cql.py, critic_loss_fn: the auto-tuned
  multiplier times mean(diff - gap), no cql_weight factor); Cal-QL's JaxCQL multiplies by
  cql_min_q_weight as well, 5x on antmaze. botorl follows WSRL, whose protocol it runs; with
  Lagrange on, cql_weight is unused (docs/methods.md).

Our choices: all 3n + 1 actions per state of every member are evaluated in ONE critic call,
since this step dominates pre-training time. Members' losses are averaged (Cal-QL sums its two
critics'; with Adam the scale does not matter). With a penalised subset of K members
(``cql_penalty_critics``) the loss is the mean Bellman error over all N members plus weight x
the mean penalty over the K: the weight means WSRL's whatever K / N is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from botorl.agents.common import (
    RATE_WHY, TrainState, check_fields, chunk_size, is_rate, module_def, summed_value_and_grad, train_state,
)
from botorl.agents.sac import SAC_CHECKS, SACAgent, SACConfig
from botorl.networks import CriticEnsemble, LagrangeMultiplier, sample_tanh_gaussian


@dataclass(frozen=True)
class CQLConfig(SACConfig):
    """CQL / Cal-QL pre-training; defaults are Cal-QL on antmaze (the docs' Methods page)."""

    num_critics: int = 10  # WSRL pre-trains with the fine-tuning ensemble size
    max_target_backup: bool = True
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
    # Members the penalty applies to: a random subset of this many, drawn with replacement each
    # critic step (WSRL's 10-critic Cal-QL penalises 2). None: all members (Cal-QL's own 2).
    cql_penalty_critics: int | None = None

    def validate(self) -> None:
        check_fields(self, CQL_CHECKS)


CQL_CHECKS = SAC_CHECKS + (
    ("cql_n_actions", lambda c: c.cql_n_actions >= 1, "need at least 1 sample"),
    ("cql_lagrange_lr", lambda c: is_rate(c.cql_lagrange_lr), RATE_WHY),
    ("cql_temp", lambda c: c.cql_temp > 0, "must be positive"),
    ("cql_penalty_critics", lambda c: c.cql_penalty_critics is None or c.cql_penalty_critics >= 1,
     "give a member count >= 1, or None to penalise every member"),
)


class CQLAgent(SACAgent):
    """SAC-family agent with the CQL / Cal-QL critic loss; ``lagrange`` holds log alpha'."""

    lagrange: TrainState = None  # CQL weight multiplier alpha' (used when cql_lagrange)

    @classmethod
    def create(cls, config: CQLConfig | None = None, obs_dim: int = 0, action_dim: int = 0, seed: int = 0):
        agent = super().create(CQLConfig() if config is None else config, obs_dim, action_dim, seed)
        l_def = module_def(LagrangeMultiplier, init_value=math.exp(agent.config.cql_lagrange_init_log))
        lagrange = train_state(l_def, jax.random.PRNGKey(0), agent.config.cql_lagrange_lr)
        return agent.replace(lagrange=lagrange)

    def lagrange_value(self, params=None) -> jax.Array:
        params = self.lagrange.params if params is None else params
        return jnp.clip(self.lagrange.apply_fn({"params": params}), 0.0, 1e6)

    def cql_samples(self, batch, key) -> dict:
        """Per state, the actions the penalty scores -- [data, n uniform, n pi(s), n pi(s')]
        as ``cql_actions`` (B, 3n + 1, A) -- and the policy samples' log-densities (B, n)."""
        n = self.config.cql_n_actions
        obs, next_obs, data_a = batch["observations"], batch["next_observations"], batch["actions"]
        bsz, adim = data_a.shape
        k_unif, k_cur, k_next = jax.random.split(key, 3)
        unif = jax.random.uniform(k_unif, (bsz, n, adim), minval=-1.0, maxval=1.0)
        cur_a, cur_logp = sample_tanh_gaussian(k_cur, *self.policy(obs), n)  # (B, n, A), (B, n)
        next_a, next_logp = sample_tanh_gaussian(k_next, *self.policy(next_obs), n)
        acts = jnp.concatenate([data_a[:, None], unif, cur_a, next_a], axis=1)
        return jax.lax.stop_gradient({"cql_actions": acts, "cur_logp": cur_logp, "next_logp": next_logp})

    def penalty_members(self, key) -> jax.Array | None:
        """Indices of the members the penalty applies to in this step (None: all); drawn from a
        key of their own, so the penalty's action samples do not depend on them."""
        if (k := self.config.cql_penalty_critics) is None:
            return None
        return jax.random.randint(jax.random.fold_in(key, 0x9E), (k,), 0, self.config.num_critics)

    def _penalty_rows(self, params, rows, members=None) -> tuple[jax.Array, jax.Array, dict]:
        """Per penalised member and state: clip(ood - Q(s, a_data)) (K, b), and Q(s, a_data) of
        every member (N, b), plus sums for logging, for the b states of ``rows`` (``_rows``);
        ``members`` (K,) picks the penalised members (None: all, K = N)."""
        cfg = self.config
        n = cfg.cql_n_actions
        obs, acts = rows["observations"], rows["cql_actions"]
        bsz, m, adim = acts.shape
        if members is None:
            q_all = self.critic_values(params, jnp.repeat(obs, m, axis=0), acts.reshape(bsz * m, adim))
        else:
            # every member on the data actions (Bellman error), the picked ones on all 3n + 1
            q_data_all = self.critic_values(params, obs, acts[:, 0])
            sub = jax.tree_util.tree_map(lambda p: p[members], params)
            sub_def = module_def(CriticEnsemble, hidden_dims=cfg.critic_hidden_dims, num=members.shape[0],
                                 use_layer_norm=cfg.critic_layer_norm)
            q_all = sub_def.apply({"params": sub}, jnp.repeat(obs, m, axis=0), acts.reshape(bsz * m, adim))
        q_all = q_all.reshape(q_all.shape[0], bsz, m)  # (N or K, b, m)
        q_data = q_all[:, :, 0]
        q_unif = q_all[:, :, 1 : 1 + n]
        q_cur = q_all[:, :, 1 + n : 1 + 2 * n]
        q_next = q_all[:, :, 1 + 2 * n :]

        sums = {"q_uniform": q_unif.sum(), "q_pi": q_cur.sum()}
        if cfg.calql:
            bound = rows["mc_returns"][None, :, None]
            sums["calql_bound_rate"] = jnp.sum(jnp.concatenate([q_cur, q_next], -1) < bound).astype(q_all.dtype)
            q_cur = jnp.maximum(q_cur, bound)
            q_next = jnp.maximum(q_next, bound)
        if cfg.cql_importance_sample:  # minus the log-densities: 0.5^A of the uniform actions, pi of the policy samples
            cat = jnp.concatenate([q_unif - adim * math.log(0.5), q_next - rows["next_logp"][None],
                                   q_cur - rows["cur_logp"][None]], axis=-1)
        else:
            cat = jnp.concatenate([q_unif, q_data[..., None], q_next, q_cur], axis=-1)
        ood = jax.scipy.special.logsumexp(cat / cfg.cql_temp, axis=-1) * cfg.cql_temp  # (N, b)
        diff_rows = jnp.clip(ood - q_data, cfg.cql_clip_diff_min, cfg.cql_clip_diff_max)
        return diff_rows, q_data if members is None else q_data_all, sums

    def _sums_to_info(self, sums: dict, bsz: int, num: int) -> dict:
        """Means over the whole batch from the sums of its chunks."""
        n = self.config.cql_n_actions
        info = {"q_uniform": sums["q_uniform"] / (num * bsz * n), "q_pi": sums["q_pi"] / (num * bsz * n)}
        if "calql_bound_rate" in sums:
            info["calql_bound_rate"] = sums["calql_bound_rate"] / (num * bsz * 2 * n)
        return info

    def _rows(self, batch, key, target=None) -> dict:
        """The per-state arrays the penalty and the loss read (all with leading axis B)."""
        rows = {"observations": batch["observations"], **self.cql_samples(batch, key)}
        if self.config.calql:
            rows["mc_returns"] = batch["mc_returns"]
        if target is not None:
            rows["target"] = target
        return rows

    def cql_penalty(self, params, batch, key) -> tuple[jax.Array, jax.Array, dict]:
        """Per penalised member ``diff`` (K,), the data Q values (N, B), and logging info."""
        rows = self._rows(batch, key)
        diff_rows, q_data, sums = self._penalty_rows(params, rows, self.penalty_members(key))
        diff = diff_rows.mean(axis=-1)
        return diff, q_data, {**self._sums_to_info(sums, q_data.shape[1], diff.shape[0]), "cql_diff": diff.mean()}

    def _penalty_weight(self):
        """Per unit of ``diff``: alpha' (Lagrange, held fixed here; WSRL's scale) or cql_weight."""
        return jax.lax.stop_gradient(self.lagrange_value()) if self.config.cql_lagrange else self.config.cql_weight

    def _loss_sum(self, params, rows, bsz: int, members=None):
        """These states' share of the critic loss (their terms over the whole batch size,
        without the constant Lagrange offset), and the sums they contribute to the info."""
        diff_rows, q_data, sums = self._penalty_rows(params, rows, members)
        bellman_sum = jnp.sum((q_data - rows["target"][None]) ** 2, axis=-1)  # (N,)
        diff_sum = diff_rows.sum(axis=-1)  # (K,)
        # WSRL's scale: the mean over the K penalised members of diff (module docstring)
        loss = (jnp.mean(bellman_sum) + self._penalty_weight() * jnp.mean(diff_sum)) / bsz
        return loss, {**sums, "bellman_sum": bellman_sum, "diff_sum": diff_sum, "q_data": q_data.sum()}

    def _loss_info(self, loss_part, sums, bsz: int) -> tuple[jax.Array, dict]:
        cfg = self.config
        diff = sums["diff_sum"] / bsz
        bellman = sums["bellman_sum"] / bsz
        weight = self._penalty_weight()
        offset = weight * cfg.cql_target_action_gap if cfg.cql_lagrange else 0.0
        loss = loss_part - offset
        penalty = weight * diff - offset
        info = self._sums_to_info(sums, bsz, diff.shape[0])
        info.update(critic_loss=loss, bellman_loss=bellman.mean(), cql_loss=penalty.mean(), cql_diff=diff.mean(),
                    q_data=sums["q_data"] / (bellman.shape[0] * bsz), _diff=diff)
        return loss, info

    def critic_loss(self, params, batch, target, key):
        """mean over members of [Bellman error + weight * (diff - gap)] on the whole batch."""
        bsz = batch["rewards"].shape[0]
        loss_part, sums = self._loss_sum(params, self._rows(batch, key, target), bsz, self.penalty_members(key))
        return self._loss_info(loss_part, sums, bsz)

    def chunk_states(self, bsz: int) -> int:
        """States per chunk of ``critic_grads`` (``bsz``: one chunk)."""
        return chunk_size(bsz, 3 * self.config.cql_n_actions + 1, self.config.chunk_rows, self.critic_floats_per_row)

    def critic_grads(self, params, batch, target, key) -> tuple[dict, dict]:
        """Gradient of ``critic_loss`` and its info, summed over chunks of states: the penalty's
        3n + 1 actions per state outgrow a CPU's caches (agents/common.py, chunked gradients).
        The random actions are drawn once for the whole batch, so chunking does not change them."""
        bsz = batch["rewards"].shape[0]
        rows = self._rows(batch, key, target)
        members = self.penalty_members(key)  # the same members in every chunk
        (loss_part, sums), grads = summed_value_and_grad(
            lambda p, r: self._loss_sum(p, r, bsz, members), params, rows, self.chunk_states(bsz)
        )
        _, info = self._loss_info(loss_part, sums, bsz)
        return grads, info

    def lagrange_loss(self, lagrange_params, diff):
        value = self.lagrange_value(lagrange_params)
        return -jnp.mean(value * (jax.lax.stop_gradient(diff) - self.config.cql_target_action_gap))

    def critic_step(self, batch, key):
        """SAC's critic step with the CQL loss, then the Lagrange multiplier's step."""
        agent, info = super().critic_step(batch, key)
        diff = info.pop("_diff")
        if self.config.cql_lagrange:
            l_loss, l_grads = jax.value_and_grad(self.lagrange_loss)(self.lagrange.params, diff)
            agent = agent.replace(lagrange=self.lagrange.apply_gradients(grads=l_grads))
            info.update(lagrange_loss=l_loss, cql_alpha_prime=self.lagrange_value())
        return agent, info

"""SAC with a critic ensemble: the online learner of the WSRL protocol (stage 3).

One ``update(batch)`` is one environment step's worth of learning at UTD ratio u, as WSRL
does it: the batch holds u minibatches of B rows, stacked (u, B, ...); each gets a critic step
followed by its Polyak update (tau); then one actor step and one temperature step use all u*B
rows. The UTD is the batch's leading axis, so it is no config field: one fact, the run's
``online.utd``, passed with the batch (WSRL: zhouzypaul/wsrl, "utd" handling in the SAC
agent's update; RLPD's ``update(batch, utd_ratio)`` does the same).

WSRL's and RLPD's choices are ``SACConfig`` fields (``subsample_replace``,
``actor_objective``). The max-target backup (antmaze) takes, over ``num_backup_actions`` next
actions, the max of their min over the critic subset and, with backup entropy, the log-prob of
that argmax action (as Cal-QL/JaxCQL's ``cql_max_target_backup``). The SAC entropy coefficient
is ``temperature``/``temp`` here; BOTO's ``alpha`` is something else.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from typing import Any

import flax.struct as struct
import jax
import jax.numpy as jnp
import numpy as np

from botorl.agents.common import (
    ACTOR_CRITIC_CHECKS, RATE_WHY, ActorCriticAgent, TrainState, check_fields, chunk_size, is_rate, module_def,
    summed_value_and_grad, train_state,
)
from botorl.agents.temperature import INIT_TEMP_RULES, stationary_temperature
from botorl.errors import ConfigError
from botorl.networks import Temperature, sample_tanh_gaussian, tanh_gaussian_from_noise


@dataclass(frozen=True)
class SACConfig:
    """SAC settings; defaults are WSRL's online fine-tuning on antmaze (the docs' Methods page)."""

    actor_hidden_dims: tuple[int, ...] = (256, 256)
    critic_hidden_dims: tuple[int, ...] = (256, 256, 256, 256)
    actor_layer_norm: bool = True
    critic_layer_norm: bool = True
    state_dependent_std: bool = True
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    num_critics: int = 10
    num_min_critics: int = 2
    subsample_replace: bool = True
    actor_objective: str = "min"  # "min" (WSRL) | "mean" (RLPD)
    actor_lr: float = 1e-4
    critic_lr: float = 3e-4
    temp_lr: float = 1e-4
    discount: float = 0.99
    tau: float = 0.005
    init_temp: float = 1.0
    # A warm start from an agent without a temperature (IQL): "stationary" starts it where
    # SAC's actor objective keeps the pre-trained actor's std (agents/temperature.py; needs
    # probe observations, else init_temp), "fixed" at init_temp. Also the rule's upper clip.
    init_temp_rule: str = "stationary"
    target_entropy: float | None = None  # None -> -action_dim
    backup_entropy: bool = False
    max_target_backup: bool = False
    num_backup_actions: int = 10
    # Rows per chunk of a gradient that is a sum over rows (agents/common.py): None -> sized to
    # the CPU's caches, 0 -> one chunk. Speed only: the same result up to float rounding.
    chunk_rows: int | None = None

    def validate(self) -> None:
        check_fields(self, SAC_CHECKS)


def _widths(v) -> bool:
    return isinstance(v, tuple) and all(isinstance(h, int) and h > 0 for h in v)


SAC_CHECKS = ACTOR_CRITIC_CHECKS + (
    # drawn with replacement or not, a subset larger than the ensemble only repeats its members
    ("num_min_critics", lambda c: 1 <= c.num_min_critics <= c.num_critics,
     "must be in [1, num_critics = {num_critics}] (--network.num-critics)"),
    ("actor_objective", lambda c: c.actor_objective in ("min", "mean"), 'use "min" (WSRL) or "mean" (RLPD)'),
    ("tau", lambda c: 0.0 < c.tau <= 1.0, "the Polyak rate must be in (0, 1]"),
    ("discount", lambda c: 0.0 <= c.discount <= 1.0, "must be in [0, 1]"),
    ("init_temp", lambda c: c.init_temp > 0, "the temperature must be positive"),
    ("init_temp_rule", lambda c: c.init_temp_rule in INIT_TEMP_RULES,
     'use "stationary" (the temperature at which SAC keeps the pre-trained actor\'s std) or "fixed" (init_temp)'),
    ("num_backup_actions", lambda c: c.num_backup_actions >= 1, "must be >= 1"),
    ("temp_lr", lambda c: is_rate(c.temp_lr), RATE_WHY),
    ("chunk_rows", lambda c: c.chunk_rows is None or (isinstance(c.chunk_rows, int) and c.chunk_rows >= 0),
     "give a row count, 0 for no chunking, or None for the device's default"),
    *((f, lambda c, f=f: _widths(getattr(c, f)), "give a tuple of positive layer widths, e.g. (256, 256)")
      for f in ("actor_hidden_dims", "critic_hidden_dims")),
)


class SACAgent(ActorCriticAgent, struct.PyTreeNode):
    """SAC-family agent. Fields shared with CQL/Cal-QL (CONTRACTS.md)."""

    actor: TrainState
    critic: TrainState  # ensemble: every parameter leaf has leading axis num_critics
    target_critic_params: Any
    temp: TrainState  # SAC entropy temperature (exp of the log_temp parameter)
    rng: jax.Array
    config: SACConfig = struct.field(pytree_node=False)

    # ------------------------------------------------------------------ construction
    @classmethod
    def create(cls, config: SACConfig | None = None, obs_dim: int = 0, action_dim: int = 0, seed: int = 0):
        config = SACConfig() if config is None else config
        if config.target_entropy is None:
            config = dataclasses.replace(config, target_entropy=-float(action_dim))
        rng, actor, critic, k_temp, _ = cls._init(config, obs_dim, action_dim, seed)
        temp = train_state(module_def(Temperature, init_value=config.init_temp), k_temp, config.temp_lr)
        return cls(actor=actor, critic=critic, target_critic_params=critic.params, temp=temp, rng=rng, config=config)

    @classmethod
    def from_pretrained(cls, agent, config: SACConfig, seed: int | None = None, observations=None) -> "SACAgent":
        """WSRL warm start: the online SAC learner from a pre-trained agent (SAC, CQL, Cal-QL, IQL).

        Takes the actor, the critics, their targets and any temperature, each with its optimiser
        state, as WSRL restores the whole agent. From IQL, which has no temperature, it starts at
        ``stationary_temperature`` (``init_temp_rule`` "stationary" with probe ``observations``),
        else at ``config.init_temp``, with a fresh Adam state. The networks in ``config`` must be
        the pre-trained ones: N critics are never copies of fewer (copies stay identical forever).
        """
        try:
            first = agent.critic.params["members"]["MLP_0"]["Dense_0"]["kernel"]  # (N, O + A, H)
            action_dim = int(agent.actor.params["mean"]["kernel"].shape[-1])
        except (AttributeError, KeyError, TypeError) as err:
            raise ConfigError(
                f"from_pretrained: {type(agent).__name__} has no botorl actor/critic ensemble ({err}); "
                f"pass a SACAgent, CQLAgent or IQLAgent."
            ) from None
        fresh = cls.create(config, int(first.shape[1]) - action_dim, action_dim, seed=0)
        m = first.shape[0]
        if m != config.num_critics:
            raise ConfigError(
                f"from_pretrained: the pre-trained agent has {m} critics and SACConfig.num_critics is "
                f"{config.num_critics}. Pre-train with the fine-tuning ensemble size (WSRL does; botorl's "
                f"pipeline sets both from --network.num_critics), or set num_critics={m}."
            )
        _check_same_shapes("actor", fresh.actor.params, agent.actor.params, config)
        _check_same_shapes("critic", fresh.critic.params, agent.critic.params, config)
        if hasattr(agent, "temp"):
            temp = _carry(fresh.temp, agent.temp)
        elif config.init_temp_rule == "stationary" and observations is not None:
            tau0, info = stationary_temperature(agent, observations, init_temp=config.init_temp)
            if info["rule"] == "fallback":
                warnings.warn(f"SACAgent.from_pretrained: {info['reason']}.", stacklevel=2)
            temp = fresh.temp.replace(params={"log_temp": jnp.asarray(math.log(tau0), jnp.float32)})
        else:
            temp = fresh.temp
        rng = jax.random.fold_in(agent.rng if seed is None else jax.random.PRNGKey(seed), 0x5AC)
        return fresh.replace(
            actor=_carry(fresh.actor, agent.actor), critic=_carry(fresh.critic, agent.critic),
            target_critic_params=getattr(agent, "target_critic_params", agent.critic.params), temp=temp, rng=rng,
        )

    # ------------------------------------------------------------------ pieces (traced)
    @property
    def critic_floats_per_row(self) -> int:
        """Activations per input row in the widest layer of the critic ensemble."""
        return self.config.num_critics * max(self.config.critic_hidden_dims)

    def temperature(self) -> jax.Array:
        return self.temp.apply_fn({"params": self.temp.params})

    def target_values(self, batch, key) -> tuple[jax.Array, dict]:
        """TD target y = r + discount (1 - done) V'(s'), shape (B,)."""
        cfg = self.config
        k_act, k_sub = jax.random.split(key)
        next_obs = batch["next_observations"]
        bsz = next_obs.shape[0]
        mean, log_std = self.policy(next_obs)
        k, replace = cfg.num_min_critics, cfg.subsample_replace
        if cfg.max_target_backup:
            n = cfg.num_backup_actions
            next_a, next_logp = sample_tanh_gaussian(k_act, mean, log_std, n)  # (B, n, A), (B, n)
            obs_rep = jnp.repeat(next_obs, n, axis=0)  # row b*n + j <-> (b, j)
            q = self.target_min(k_sub, obs_rep, next_a.reshape(bsz * n, -1), k, replace).reshape(bsz, n)
            best = jnp.argmax(q, axis=1)[:, None]
            next_q = jnp.take_along_axis(q, best, axis=1)[:, 0]
            next_logp = jnp.take_along_axis(next_logp, best, axis=1)[:, 0]
        else:
            next_a, next_logp = sample_tanh_gaussian(k_act, mean, log_std)
            next_q = self.target_min(k_sub, next_obs, next_a, k, replace)
        if cfg.backup_entropy:
            next_q = next_q - self.temperature() * next_logp
        target = batch["rewards"] + cfg.discount * (1.0 - batch["dones"]) * next_q
        return jax.lax.stop_gradient(target), {"target_q": target.mean()}

    def critic_loss(self, params, batch, target, key) -> tuple[jax.Array, dict]:
        q = self.critic_values(params, batch["observations"], batch["actions"])  # (N, B)
        # Mean over members and batch (WSRL/RLPD); with Adam the scale is immaterial.
        loss = jnp.mean((q - target[None]) ** 2)
        return loss, {"critic_loss": loss, "q_data": q.mean()}

    def critic_grads(self, params, batch, target, key) -> tuple[dict, dict]:
        return jax.grad(self.critic_loss, has_aux=True)(params, batch, target, key)

    def critic_step(self, batch, key):
        k_target, k_loss = jax.random.split(key)
        target, t_info = self.target_values(batch, k_target)
        grads, info = self.critic_grads(self.critic.params, batch, target, k_loss)
        return self.critic_stepped(grads, self.config.tau), {**info, **t_info}

    def _actor_rows(self, batch, key) -> dict:
        obs = batch["observations"]
        # The reparameterisation noise of the whole batch, drawn as sample_tanh_gaussian does.
        eps = jax.random.normal(key, (obs.shape[0], self.action_dim), obs.dtype)
        return {"observations": obs, "eps": eps}

    def _actor_loss_sum(self, actor_params, rows, bsz: int):
        """These rows' share of the actor loss (over the whole batch size) and -sum log pi."""
        obs = rows["observations"]
        actions, log_prob = tanh_gaussian_from_noise(rows["eps"], *self.policy(obs, actor_params))
        q = self.critic_values(self.critic.params, obs, actions)
        q = q.min(axis=0) if self.config.actor_objective == "min" else q.mean(axis=0)
        return jnp.sum(self.temperature() * log_prob - q) / bsz, -jnp.sum(log_prob)

    def actor_loss(self, actor_params, batch, key) -> tuple[jax.Array, dict]:
        bsz = batch["observations"].shape[0]
        loss, neg_logp_sum = self._actor_loss_sum(actor_params, self._actor_rows(batch, key), bsz)
        return loss, {"actor_loss": loss, "entropy": neg_logp_sum / bsz}

    def actor_step(self, batch, key):
        """One actor step; on large batches (the 1,024 rows of UTD 4 through 10 critics) the
        gradient is summed over chunks of rows, 1.4x faster on a CPU (agents/common.py)."""
        bsz = batch["observations"].shape[0]
        per = chunk_size(bsz, 1, self.config.chunk_rows, self.critic_floats_per_row)
        (loss, neg_logp_sum), grads = summed_value_and_grad(
            lambda p, r: self._actor_loss_sum(p, r, bsz), self.actor.params, self._actor_rows(batch, key), per
        )
        info = {"actor_loss": loss, "entropy": neg_logp_sum / bsz}
        return self.replace(actor=self.actor.apply_gradients(grads=grads)), info

    def temp_loss(self, temp_params, entropy) -> tuple[jax.Array, dict]:
        # d/dlog_temp = temp * (entropy - target): entropy below target raises the temperature.
        temp = self.temp.apply_fn({"params": temp_params})
        loss = temp * (jax.lax.stop_gradient(entropy) - self.config.target_entropy)
        return loss, {"temp_loss": loss, "temperature": temp}

    def temp_step(self, entropy):
        grads, info = jax.grad(self.temp_loss, has_aux=True)(self.temp.params, entropy)
        return self.replace(temp=self.temp.apply_gradients(grads=grads)), info

    def train_step(self, batch):
        """One update at UTD u: ``batch`` is u critic minibatches stacked (u, B, ...), an online
        step's (u = ``online.utd``), or one minibatch (B, ...), u = 1 (pre-training, benchmarks)."""
        rng, k_critic, k_actor = jax.random.split(self.rng, 3)
        agent = self.replace(rng=rng)
        if batch["rewards"].ndim == 1:
            batch = jax.tree_util.tree_map(lambda x: x[None], batch)
        u = batch["rewards"].shape[0]
        agent, c_infos = jax.lax.scan(lambda a, xs: a.critic_step(*xs), agent, (batch, jax.random.split(k_critic, u)))
        info = {k: v[-1] for k, v in c_infos.items()}
        rows = jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), batch)  # the actor's: all u x B
        agent, a_info = agent.actor_step(rows, k_actor)
        agent, t_info = agent.temp_step(a_info["entropy"])
        return agent, {**info, **a_info, **t_info}


def _carry(fresh: TrainState, pre: TrainState) -> TrainState:
    """``fresh``'s apply function and optimiser (so its learning rate) with ``pre``'s parameters,
    step and optimiser state."""
    if jax.tree_util.tree_structure(fresh.opt_state) != jax.tree_util.tree_structure(pre.opt_state):
        raise ConfigError(
            "from_pretrained: the pre-trained optimiser state does not match the fine-tuning optimiser "
            "(botorl's agents all use Adam); pass an agent trained by botorl."
        )
    return fresh.replace(step=pre.step, params=pre.params, opt_state=pre.opt_state)


def _check_same_shapes(name, want, got, config) -> None:
    if (jax.tree_util.tree_structure(want) != jax.tree_util.tree_structure(got)
            or jax.tree_util.tree_map(np.shape, want) != jax.tree_util.tree_map(np.shape, got)):
        raise ConfigError(
            f"from_pretrained: the pre-trained {name} does not match the network that {type(config).__name__} "
            f"describes (hidden sizes, LayerNorm, state_dependent_std, ensemble size). Set those fields of the "
            f"fine-tuning config to the pre-training values."
        )

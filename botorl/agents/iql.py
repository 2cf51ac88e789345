"""IQL (Kostrikov et al. 2021): expectile value, TD critic, AWR actor -- offline pre-training.

One update, in the order of the IQL reference code (ikostrikov/implicit_q_learning):
1. V: expectile regression of V(s) toward Q'(s, a) = min over a random pair of TARGET Q members
   (IQL's twin-Q min; a pair drawn from the larger ensemble fine-tuning carries over),
   ``L = mean |expectile - 1[Q' - V < 0]| (Q' - V)^2``;
2. actor: AWR, ``L = -mean min(exp(awr_beta * (Q'(s,a) - V(s))), 100) log pi(a|s)``, with the
   V just updated and dropout active when ``actor_dropout`` is set;
3. Q: ``L = mean_members mean_B (Q_i(s,a) - r - discount (1 - done) V(s'))^2``, new V;
4. Polyak update of the target Q (tau).

Policy: the same tanh-squashed Gaussian as SAC, so ``SACAgent.from_pretrained`` takes it over
unchanged (dataset actions are mapped back with atanh for the log-prob). The IQL paper's policy
is an unsquashed Gaussian with tanh on the mean; we keep its state-independent log-std and
range [-5, 2] but squash, and use a constant actor learning rate (IQL's decays with a cosine).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import flax.struct as struct
import jax
import jax.numpy as jnp

from botorl.agents.common import (
    ACTOR_CRITIC_CHECKS, RATE_WHY, ActorCriticAgent, TrainState, check_fields, is_rate, module_def, train_state,
)
from botorl.networks import ValueNetwork, tanh_gaussian_log_prob


@dataclass(frozen=True)
class IQLConfig:
    """IQL settings; defaults are antmaze (expectile 0.9, beta 10; the docs' Methods page).
    Adroit/kitchen: expectile 0.7, awr_beta 0.5, actor_dropout 0.1."""

    actor_hidden_dims: tuple[int, ...] = (256, 256)
    critic_hidden_dims: tuple[int, ...] = (256, 256)
    value_hidden_dims: tuple[int, ...] = (256, 256)
    actor_layer_norm: bool = False
    critic_layer_norm: bool = False
    actor_dropout: float | None = None
    state_dependent_std: bool = False
    log_std_min: float = -5.0
    log_std_max: float = 2.0
    num_critics: int = 2
    num_min_critics: int = 2
    """Q'(s, a) = min over a random subset of this many distinct target members: IQL's twin-Q
    pessimism whatever the ensemble size fine-tuning carries over."""
    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    value_lr: float = 3e-4
    discount: float = 0.99
    tau: float = 0.005
    expectile: float = 0.9
    awr_beta: float = 10.0  # IQL's "temperature": inverse temperature of the AWR weights
    exp_adv_max: float = 100.0

    def validate(self) -> None:
        check_fields(self, IQL_CHECKS)


IQL_CHECKS = ACTOR_CRITIC_CHECKS + (
    ("expectile", lambda c: 0.0 < c.expectile < 1.0, "must be in (0, 1), e.g. 0.7 or 0.9"),
    ("awr_beta", lambda c: c.awr_beta >= 0, "must be >= 0"),
    ("num_min_critics", lambda c: 1 <= c.num_min_critics <= c.num_critics, "must be in [1, num_critics = {num_critics}]"),
    ("value_lr", lambda c: is_rate(c.value_lr), RATE_WHY),
    ("actor_dropout", lambda c: c.actor_dropout is None or 0.0 <= c.actor_dropout < 1.0, "must be in [0, 1) or None"),
)


class IQLAgent(ActorCriticAgent, struct.PyTreeNode):
    actor: TrainState
    critic: TrainState  # Q ensemble, leading axis num_critics
    target_critic_params: Any
    value: TrainState
    rng: jax.Array
    config: IQLConfig = struct.field(pytree_node=False)

    @classmethod
    def create(cls, config: IQLConfig | None = None, obs_dim: int = 0, action_dim: int = 0, seed: int = 0):
        config = IQLConfig() if config is None else config
        rng, actor, critic, k_value, obs = cls._init(config, obs_dim, action_dim, seed)
        v_def = module_def(ValueNetwork, hidden_dims=config.value_hidden_dims, use_layer_norm=config.critic_layer_norm)
        value = train_state(v_def, k_value, config.value_lr, obs)
        return cls(actor=actor, critic=critic, target_critic_params=critic.params, value=value, rng=rng, config=config)

    # ------------------------------------------------------------------ pieces
    def target_q(self, batch, key):
        """Q'(s, a) on the batch: min over a random subset of distinct target members."""
        return self.target_min(key, batch["observations"], batch["actions"], self.config.num_min_critics, False)

    def value_loss(self, value_params, batch, q):
        v = self.value.apply_fn({"params": value_params}, batch["observations"])
        diff = jax.lax.stop_gradient(q) - v
        weight = jnp.where(diff < 0, 1.0 - self.config.expectile, self.config.expectile)  # the expectile's asymmetry
        loss = jnp.mean(weight * diff**2)
        return loss, {"value_loss": loss, "v": v.mean()}

    def actor_loss(self, actor_params, batch, key, q):
        cfg = self.config
        obs = batch["observations"]
        v = self.value.apply_fn({"params": self.value.params}, obs)
        weights = jax.lax.stop_gradient(jnp.minimum(jnp.exp((q - v) * cfg.awr_beta), cfg.exp_adv_max))
        mean, log_std = self.policy(obs, actor_params, dropout_key=key if cfg.actor_dropout else None)
        log_prob = tanh_gaussian_log_prob(mean, log_std, batch["actions"])
        loss = -jnp.mean(weights * log_prob)
        return loss, {"actor_loss": loss, "adv_weight": weights.mean(), "log_prob_data": log_prob.mean()}

    def critic_loss(self, critic_params, batch):
        cfg = self.config
        next_v = self.value.apply_fn({"params": self.value.params}, batch["next_observations"])
        target = batch["rewards"] + cfg.discount * (1.0 - batch["dones"]) * next_v
        q = self.critic_values(critic_params, batch["observations"], batch["actions"])
        loss = jnp.mean((q - jax.lax.stop_gradient(target)[None]) ** 2)
        return loss, {"critic_loss": loss, "q_data": q.mean(), "target_q": target.mean()}

    def train_step(self, batch):
        rng, k_actor, k_sub = jax.random.split(self.rng, 3)
        agent = self.replace(rng=rng)
        q = jax.lax.stop_gradient(agent.target_q(batch, k_sub))  # the same Q' for V and the AWR weights
        g, v_info = jax.grad(agent.value_loss, has_aux=True)(agent.value.params, batch, q)
        agent = agent.replace(value=agent.value.apply_gradients(grads=g))
        g, a_info = jax.grad(agent.actor_loss, has_aux=True)(agent.actor.params, batch, k_actor, q)
        agent = agent.replace(actor=agent.actor.apply_gradients(grads=g))
        g, c_info = jax.grad(agent.critic_loss, has_aux=True)(agent.critic.params, batch)
        agent = agent.critic_stepped(g, agent.config.tau)
        return agent, {**v_info, **a_info, **c_info}

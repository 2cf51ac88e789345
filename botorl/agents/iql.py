"""IQL (Kostrikov et al. 2021): expectile value, TD critic, AWR actor -- offline pre-training.

One update, in the order of the IQL reference code (ikostrikov/implicit_q_learning):
1. V: expectile regression of V(s) toward Q'(s, a) = min over a random pair of TARGET Q members
   (IQL's twin-Q min; a pair drawn from the larger ensemble fine-tuning carries over),
   ``L = mean |expectile - 1[Q' - V < 0]| (Q' - V)^2``;
2. actor: AWR, ``L = -mean min(exp(awr_beta * (Q'(s,a) - V(s))), 100) log pi(a|s)``, with the
   V just updated and dropout active when ``actor_dropout`` is set;
3. Q: ``L = mean_members mean_B (Q_i(s,a) - r - discount (1 - done) V(s'))^2``, new V;
4. Polyak update of the target Q (tau).

Policy: the same tanh-squashed Gaussian as SAC (``TanhGaussianActor``), so its actions lie
in [-1, 1], ``sample_tanh_gaussian``/``tanh_gaussian_log_prob`` give actions and log-probs
(with the tanh correction; dataset actions are mapped back with atanh) and
``SACAgent.from_pretrained`` can take it over unchanged. The IQL paper's policy is an
unsquashed Gaussian with tanh on the mean and a state-independent log-std; we keep the
state-independent log-std (``state_dependent_std=False``) but squash -- our choice. The
log-std range is [-5, 2] (IQL's actor uses log_std_min -5). The IQL reference decays the
actor learning rate with a cosine schedule; we use a constant rate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import flax.struct as struct
import jax
import jax.numpy as jnp

from botorl.agents.common import AgentAPI, TrainState, adam, polyak
from botorl.agents.sac import actor_def, critic_def
from botorl.errors import ConfigError
from botorl.networks import ValueNetwork, subsample_ensemble, tanh_gaussian_log_prob

import functools


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
    # Q'(s, a) in the value and actor losses = min over a random subset of this many distinct
    # target members (IQL's min of its twin Qs when num_critics = 2). With the 10-critic
    # ensemble that fine-tuning carries over, each member is trained, and the pessimism of
    # the target stays IQL's rather than a min over all 10.
    num_min_critics: int = 2
    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    value_lr: float = 3e-4
    discount: float = 0.99
    tau: float = 0.005
    expectile: float = 0.9
    awr_beta: float = 10.0  # IQL's "temperature": inverse temperature of the AWR weights
    exp_adv_max: float = 100.0

    def validate(self) -> None:
        if not 0.0 < self.expectile < 1.0:
            raise ConfigError(f"IQLConfig.expectile = {self.expectile} is invalid: must be in (0, 1), e.g. 0.7 or 0.9.")
        if self.awr_beta < 0:
            raise ConfigError(f"IQLConfig.awr_beta = {self.awr_beta} is invalid: must be >= 0.")
        if self.num_critics < 1:
            raise ConfigError(f"IQLConfig.num_critics = {self.num_critics} is invalid: need at least one.")
        if not 1 <= self.num_min_critics <= self.num_critics:
            raise ConfigError(
                f"IQLConfig.num_min_critics = {self.num_min_critics} is invalid: must be in [1, num_critics = "
                f"{self.num_critics}]."
            )
        for f in ("actor_lr", "critic_lr", "value_lr"):
            v = getattr(self, f)
            if not (v >= 0 and v < float("inf")):  # a negative rate climbs the loss
                raise ConfigError(f"IQLConfig.{f} = {v} is invalid: a learning rate must be a finite number >= 0.")
        if not (-float("inf") < self.log_std_min < self.log_std_max < float("inf")):
            raise ConfigError(f"IQLConfig.log_std_min = {self.log_std_min} is invalid: the actor's log-std range "
                              f"needs log_std_min < log_std_max (= {self.log_std_max}).")
        if self.actor_dropout is not None and not 0.0 <= self.actor_dropout < 1.0:
            raise ConfigError(f"IQLConfig.actor_dropout = {self.actor_dropout} is invalid: must be in [0, 1) or None.")


@functools.lru_cache(maxsize=None)
def value_def(hidden_dims: tuple[int, ...], layer_norm: bool) -> ValueNetwork:
    return ValueNetwork(hidden_dims=hidden_dims, use_layer_norm=layer_norm)


def expectile_loss(diff: jax.Array, expectile: float) -> jax.Array:
    """Asymmetric squared loss of diff = Q - V (mean)."""
    weight = jnp.where(diff < 0, 1.0 - expectile, expectile)
    return jnp.mean(weight * diff**2)


class IQLAgent(AgentAPI, struct.PyTreeNode):
    actor: TrainState
    critic: TrainState  # Q ensemble, leading axis num_critics
    target_critic_params: Any
    value: TrainState
    rng: jax.Array
    config: IQLConfig = struct.field(pytree_node=False)

    @classmethod
    def create(cls, config: IQLConfig | None = None, obs_dim: int = 0, action_dim: int = 0, seed: int = 0):
        config = IQLConfig() if config is None else config
        config.validate()
        if obs_dim < 1 or action_dim < 1:
            raise ConfigError(f"IQLAgent.create needs obs_dim >= 1 and action_dim >= 1, got {obs_dim}, {action_dim}.")
        rng = jax.random.PRNGKey(seed)
        rng, k_actor, k_critic, k_value = jax.random.split(rng, 4)
        obs = jnp.zeros((1, obs_dim), jnp.float32)
        act = jnp.zeros((1, action_dim), jnp.float32)
        a_def = actor_def(config, action_dim)
        actor = TrainState.create(apply_fn=a_def.apply, params=a_def.init(k_actor, obs)["params"], tx=adam(config.actor_lr))
        c_def = critic_def(config.critic_hidden_dims, config.num_critics, config.critic_layer_norm)
        critic_params = c_def.init(k_critic, obs, act)["params"]
        critic = TrainState.create(apply_fn=c_def.apply, params=critic_params, tx=adam(config.critic_lr))
        v_def = value_def(config.value_hidden_dims, config.critic_layer_norm)
        value = TrainState.create(apply_fn=v_def.apply, params=v_def.init(k_value, obs)["params"], tx=adam(config.value_lr))
        return cls(actor=actor, critic=critic, target_critic_params=critic_params, value=value, rng=rng, config=config)

    # ------------------------------------------------------------------ pieces
    def policy(self, observations, actor_params=None, *, dropout_key=None):
        params = self.actor.params if actor_params is None else actor_params
        if dropout_key is None:
            return self.actor.apply_fn({"params": params}, observations)
        return self.actor.apply_fn({"params": params}, observations, training=True, rngs={"dropout": dropout_key})

    def critic_values(self, params, observations, actions):
        return self.critic.apply_fn({"params": params}, observations, actions)

    def target_q(self, batch, key):
        """Q'(s, a) on the batch: min over a random subset of distinct target members."""
        cfg = self.config
        sub = subsample_ensemble(key, self.target_critic_params, cfg.num_min_critics, cfg.num_critics, False)
        sub_def = critic_def(cfg.critic_hidden_dims, cfg.num_min_critics, cfg.critic_layer_norm)
        return sub_def.apply({"params": sub}, batch["observations"], batch["actions"]).min(axis=0)

    def value_loss(self, value_params, batch, q):
        v = self.value.apply_fn({"params": value_params}, batch["observations"])
        loss = expectile_loss(jax.lax.stop_gradient(q) - v, self.config.expectile)
        return loss, {"value_loss": loss, "v": v.mean()}

    def actor_loss(self, actor_params, batch, key, q):
        cfg = self.config
        obs = batch["observations"]
        v = self.value.apply_fn({"params": self.value.params}, obs)
        weights = jnp.minimum(jnp.exp((q - v) * cfg.awr_beta), cfg.exp_adv_max)
        weights = jax.lax.stop_gradient(weights)
        use_dropout = cfg.actor_dropout is not None and cfg.actor_dropout > 0
        mean, log_std = self.policy(obs, actor_params, dropout_key=key if use_dropout else None)
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
        critic = agent.critic.apply_gradients(grads=g)
        agent = agent.replace(critic=critic, target_critic_params=polyak(critic.params, agent.target_critic_params, agent.config.tau))
        return agent, {**v_info, **a_info, **c_info}

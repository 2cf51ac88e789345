"""The BOTO critic update (paper eq. 1-2 and section 4.1).

For a batch (s, a, r, s', done) of D_BOTO and a perturbed action a_bar ~ q_sigma(.|a):

    y_bar = r - alpha ||a - a_bar||^2
              + gamma (1 - done) (min_{j in subset} Q'_j(s', a~) - tau log pi(a~|s')),  a~ ~ pi(.|s')
    loss  = mean_i mean_B (Q_i(s, a_bar) - y_bar)^2

then a Polyak update of the target critics; the choices the paper leaves open are on
docs/methods.md. Any botorl agent works, its critic keeping its optimiser state from
pre-training. ``alpha`` is traced, not static: changing it does not recompile, and ``jax.vmap``
over alpha trains several critics in one program.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from botorl.agents.common import ActorCriticAgent, checked_batch
from botorl.agents.population import as_f32, over_members, placed
from botorl.batch import TRANSITION_KEYS
from botorl.boto.config import BOTOConfig, check_alpha
from botorl.boto.noise import make_noise_fn
from botorl.errors import ConfigError
from botorl.networks import sample_tanh_gaussian


@dataclass(frozen=True)
class ObjectiveSettings:
    """What one BOTO critic step reads, every value resolved (``resolve``: a ``BOTOConfig``'s
    None fields taken from the agent it trains); static and hashable, as the jitted step keys on it."""

    noise: str
    log_sigma: float
    sigma: float
    weight_fn: str | float
    clip: bool
    num_min_critics: int
    subsample_replace: bool
    backup_entropy: bool
    discount: float
    tau: float
    train_actor: bool

    @classmethod
    def resolve(cls, config: BOTOConfig, agent) -> "ObjectiveSettings":
        config.validate()
        if not isinstance(agent, ActorCriticAgent):
            raise ConfigError(f"BOTO needs an agent with a critic ensemble and a policy; {type(agent).__name__} is "
                              f"none. Pass a SACAgent, CQLAgent (Cal-QL) or IQLAgent.")
        acfg = agent.config
        n = int(jax.tree_util.tree_leaves(agent.critic.params)[0].shape[0])
        k = config.num_min_critics or getattr(acfg, "num_min_critics", n)
        replace = getattr(acfg, "subsample_replace", False) if config.subsample_replace is None else config.subsample_replace
        if not replace and k > n:
            raise ConfigError(
                f"BOTOConfig.num_min_critics = {k} exceeds the agent's {n} critics; without "
                f"replacement the subset must be at most {n} (or set subsample_replace=True)."
            )
        if config.train_actor and not (hasattr(agent, "actor_step") and hasattr(agent, "temp")):
            raise ConfigError(
                f"BOTOConfig.train_actor=True needs a SAC-family agent (SAC, CQL, Cal-QL) with a "
                f"temperature; {type(agent).__name__} has none. Convert it first with "
                f"SACAgent.from_pretrained(agent), or keep the actor frozen (train_actor=False)."
            )
        return cls(
            noise=config.noise,
            log_sigma=float(config.log_sigma),
            sigma=float(config.sigma),
            weight_fn=config.weight_fn,
            clip=bool(config.clip),
            num_min_critics=int(k),
            subsample_replace=bool(replace),
            backup_entropy=bool(config.backup_entropy and hasattr(agent, "temp")),
            discount=float(acfg.discount if config.discount is None else config.discount),
            tau=float(acfg.tau if config.tau is None else config.tau),
            train_actor=bool(config.train_actor),
        )


# ----------------------------------------------------------------------------- pure pieces


def compute_target(agent, batch, alpha, settings: ObjectiveSettings, k_noise, k_next):
    """The BOTO target of every row: ``(y_bar (B,), a_bar (B, A), ||a - a_bar||^2 (B,), noise info)``."""
    a_bar, ninfo = make_noise_fn(settings.noise, log_sigma=settings.log_sigma, sigma=settings.sigma,
                                 weight_fn=settings.weight_fn, clip=settings.clip)(k_noise, batch["actions"])
    next_obs = batch["next_observations"]
    k_act, k_sub = jax.random.split(k_next)
    mean, log_std = agent.policy(next_obs)
    next_a, next_logp = sample_tanh_gaussian(k_act, mean, log_std)
    next_v = agent.target_min(k_sub, next_obs, next_a, settings.num_min_critics, settings.subsample_replace)
    if settings.backup_entropy:
        next_v = next_v - agent.temperature() * next_logp
    sq_dist = jnp.sum((batch["actions"] - a_bar) ** 2, axis=-1)
    target = batch["rewards"] - alpha * sq_dist + settings.discount * (1.0 - batch["dones"]) * next_v
    return jax.lax.stop_gradient(target), a_bar, sq_dist, ninfo


def boto_critic_step(agent, batch, alpha, settings: ObjectiveSettings):
    """One BOTO critic step (+ Polyak update, + actor/temperature step if ``train_actor``)."""
    rng, k_noise, k_next, k_actor = jax.random.split(agent.rng, 4)
    agent = agent.replace(rng=rng)
    target, a_bar, sq_dist, ninfo = compute_target(agent, batch, alpha, settings, k_noise, k_next)
    obs = batch["observations"]

    def loss_fn(params):
        q = agent.critic_values(params, obs, a_bar)  # (N, B)
        return jnp.mean((q - target[None]) ** 2), q

    (loss, q_bar), grads = jax.value_and_grad(loss_fn, has_aux=True)(agent.critic.params)
    agent = agent.critic_stepped(grads, settings.tau)
    info = {
        "critic_loss": loss,
        "q_perturbed": q_bar.mean(),
        "target": target.mean(),
        "penalty": (alpha * sq_dist).mean(),
        "sq_dist": sq_dist.mean(),
        "uniform_share": ninfo["uniform"].astype(jnp.float32).mean(),
    }
    if settings.train_actor:
        agent, a_info = agent.actor_step(batch, k_actor)
        agent, t_info = agent.temp_step(a_info["entropy"])
        info.update(actor_loss=a_info["actor_loss"], entropy=a_info["entropy"], temperature=t_info["temperature"])
    return agent, info


def boto_update_many_fn(agent, batches, alpha, settings: ObjectiveSettings):
    """K BOTO critic steps under one ``lax.scan`` (traced; ``boto_update_many`` jits it, and
    ``population_update_many`` maps it over a population)."""
    agent, infos = jax.lax.scan(lambda a, b: boto_critic_step(a, b, alpha, settings), agent, batches)
    info = jax.tree_util.tree_map(jnp.mean, infos)
    # mean Q (over members and rows) at the last batch's dataset actions and at uniform actions
    obs, act = batches["observations"][-1], batches["actions"][-1]
    rng, key = jax.random.split(agent.rng)
    uni = jax.random.uniform(key, act.shape, act.dtype, -1.0, 1.0)
    info.update(q_data=agent.critic_values(agent.critic.params, obs, act).mean(),
                q_uniform=agent.critic_values(agent.critic.params, obs, uni).mean())
    return agent.replace(rng=rng), info


_jit_update_many = jax.jit(boto_update_many_fn, static_argnames=("settings",))
_jit_population_update_many = jax.jit(over_members(boto_update_many_fn, (0, 0, 0), across_cores=True),
                                      static_argnames=("settings",))


def _check_batches(batches, many: bool) -> None:
    checked_batch(batches)
    if jnp.ndim(batches["actions"]) != (3 if many else 2):
        raise ConfigError(
            f"BOTO {'update_many' if many else 'update'}: actions have shape {jnp.shape(batches['actions'])}; "
            f"expected {'(K, B, A)' if many else '(B, A)'}."
        )


def boto_update_many(agent, batches, alpha: float, config: BOTOConfig | ObjectiveSettings):
    """K BOTO critic steps under one jitted ``lax.scan`` (batches stacked as (K, B, ...)).

    Returns ``(agent, metrics)``: the means over the K steps of ``boto_critic_step``'s info, and
    q_data / q_uniform, the mean Q after the last step at the last batch's dataset actions and at
    uniform actions.
    """
    check_alpha(alpha)
    settings = config if isinstance(config, ObjectiveSettings) else ObjectiveSettings.resolve(config, agent)
    _check_batches(batches, many=True)
    batches = {k: jnp.asarray(batches[k], jnp.float32) for k in TRANSITION_KEYS}
    return _jit_update_many(agent, batches, jnp.float32(alpha), settings)


def boto_update(agent, batch, alpha: float, config: BOTOConfig | ObjectiveSettings):
    """One BOTO critic step (the K = 1 case of ``boto_update_many``)."""
    _check_batches(batch, many=False)
    return boto_update_many(agent, {k: jnp.asarray(batch[k])[None] for k in TRANSITION_KEYS}, alpha, config)


def population_update_many(agents, batches, alphas, settings: ObjectiveSettings):
    """``boto_update_many`` of every member of a population (agents/population.py), each with its
    own alpha; ``batches`` (N, K, B, ...), ``alphas`` (N,), checked where they entered (the run's config,
    ``configs.resolve.validate``, or ``phase.train_boto``), not here."""
    b = {k: as_f32(batches[k]) for k in TRANSITION_KEYS}
    return _jit_population_update_many(*placed(agents, b, as_f32(alphas)), settings=settings)

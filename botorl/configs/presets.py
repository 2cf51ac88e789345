"""Presets: the default RunConfig of a (task, profile, method). The profiles: docs/running.md's
table; the ``full`` profile's sources: docs/methods.md ("Reference settings"). Generated tasks
get the settings of the paper domain they stand in for (pointmaze -> antmaze, door-binary-local
-> door-binary).

The ``quick`` profile (``_quick``) cuts sizes and budgets for speed: a 10-critic 2 x 128 SAC update
at UTD 4 cost ~100 ms of CPU, so 20k online steps alone took over 30 minutes. On pointmaze, Cal-QL
with 2 action samples per kind and 128-row batches (~3x cheaper a step) solves the umaze in 20k
pre-training steps, which every algorithm gets there (docs/results/pretraining.md).

The ``mid`` profile (docs/results/one-size-up.md) grows quick's ensemble and BOTO steps, not its
networks, which pre-train worse on the medium maze (docs/results/pretraining.md).

Our choices for tasks outside the paper: pointmaze uses antmaze's alpha (-1.0, the
"diverse" value: the maze2d-style data are diverse, goals re-drawn) and log sigma -20;
door-binary-local uses door-binary's alpha 0.0; a user's task: docs/own-task.md's table.
"""

from __future__ import annotations

from dataclasses import asdict, replace

from botorl.agents.cql import CQLConfig
from botorl.agents.iql import IQLConfig
from botorl.agents.sac import SACConfig
from botorl.boto.config import BOTOConfig
from botorl.envs.metric import of_task as metric_of_task
from botorl.envs.registry import get_task
from botorl.errors import ConfigError
from botorl.configs.schema import (
    DataConfig,
    EnvConfig,
    MetricConfig,
    NetworkConfig,
    OfflineConfig,
    OnlineConfig,
    RunConfig,
    WarmupConfig,
)

PROFILES = ("quick", "mid", "full", "smoke")

# Paper domain each task's settings come from.
_STANDS_IN = {"pointmaze": "antmaze"}

# Cal-QL / CQL pre-training per domain (Cal-QL's and WSRL's code; docs/methods.md).
_PRETRAIN_STEPS = {"antmaze": 1_000_000, "adroit": 20_000, "kitchen": 250_000, "bandit": 20_000,
                   "custom": 100_000}
_CQL = {
    "antmaze": dict(cql_weight=5.0, cql_lagrange=True, cql_target_action_gap=0.8, cql_importance_sample=True),
    "adroit": dict(cql_weight=1.0, cql_lagrange=False, cql_importance_sample=True),
    "kitchen": dict(cql_weight=5.0, cql_lagrange=False, cql_importance_sample=False),
    "bandit": dict(cql_weight=1.0, cql_lagrange=False, cql_importance_sample=True),
    "custom": dict(cql_weight=1.0, cql_lagrange=False, cql_importance_sample=True),
}
# IQL: expectile 0.9 / temperature 10 on antmaze; 0.7 / 0.5 and actor dropout 0.1 otherwise.
_IQL = {
    "antmaze": dict(expectile=0.9, awr_beta=10.0, actor_dropout=None),
    "adroit": dict(expectile=0.7, awr_beta=0.5, actor_dropout=0.1),
    "kitchen": dict(expectile=0.7, awr_beta=0.5, actor_dropout=0.1),
    "bandit": dict(expectile=0.7, awr_beta=0.5, actor_dropout=None),
    "custom": dict(expectile=0.7, awr_beta=3.0, actor_dropout=None),
}
# Cal-QL MC returns: raw reward of a failing sparse trajectory (None elsewhere); finite horizon
# everywhere (WSRL computes kitchen's returns with infinite_horizon=False; Cal-QL's code has no
# kitchen).
_MC_SPARSE_NEGATIVE_REWARD = {"antmaze": 0.0, "adroit": -1.0}
# Our choices for tasks the paper does not have (see the module docstring).
_DEFAULT_PAPER = {"pointmaze": (-1.0, 100_000, -20.0), "adroit": (0.0, 100_000, -20.0), "bandit": (0.0, 20_000, -20.0),
                  "custom": (0.0, 100_000, -20.0)}


def paper_settings(spec) -> tuple[float, int, float]:
    """(alpha, boto_steps, log_sigma) of a task: the paper's (Table 2, B.1), ours for the others."""
    if spec.paper is not None:
        return spec.paper.alpha, spec.paper.boto_steps, spec.paper.log_sigma
    return _DEFAULT_PAPER.get(spec.domain, (0.0, 100_000, -20.0))


def make_preset(task: str, profile: str = "quick", method: str = "boto", pretrain: str | None = None) -> RunConfig:
    """The default config of ``task`` under ``profile`` for ``method``."""
    if profile not in PROFILES:
        raise ConfigError(f"unknown profile {profile!r} (--profile). Choose one of: {', '.join(PROFILES)}.")
    spec = get_task(task)
    dom = _STANDS_IN.get(spec.domain, spec.domain)
    _, boto_steps, log_sigma = paper_settings(spec)

    net = NetworkConfig(actor_hidden_dims=tuple(spec.networks.actor), critic_hidden_dims=tuple(spec.networks.critic))
    # WSRL's actor: a state-independent log-std on antmaze ("uniform"), state-dependent on
    # adroit and kitchen; the same in pre-training and fine-tuning.
    std = dict(state_dependent_std=(dom != "antmaze"))
    # WSRL pre-trains Cal-QL with its 10-critic ensemble and the conservative penalty on a
    # random pair of members per step (its "redq" config).
    cql = replace(CQLConfig(), max_target_backup=True, backup_entropy=False, cql_penalty_critics=2, **std,
                  **_CQL[dom])
    iql = replace(IQLConfig(), **_IQL[dom])
    offline = OfflineConfig(steps=_PRETRAIN_STEPS[dom], cql=cql, iql=iql,
                            mc_sparse_negative_reward=_MC_SPARSE_NEGATIVE_REWARD.get(dom))
    sac = replace(SACConfig(), max_target_backup=(dom == "antmaze"), backup_entropy=False, **std)
    boto = replace(BOTOConfig(), boto_steps=boto_steps, log_sigma=log_sigma)
    # A user's task reads the file it was registered with (None: data held in memory).
    data_path = (spec.dataset_source.ref or None) if spec.user is not None else None
    cfg = RunConfig(task=task, method=method, pretrain=pretrain, profile=profile, data=DataConfig(path=data_path),
                    env=env_record(spec), metric=MetricConfig(**asdict(metric_of_task(spec))), network=net,
                    offline=offline, boto=boto, online=OnlineConfig(sac=sac))
    if spec.domain == "adroit":
        # The 25 DAPG human demos (door2_sparse.npy / door_human_demos.npz) hold actions up to
        # |a| = 1.37; the env clips actions to the box, so the Dataset's clip to +-1 keeps what
        # the env executed. Accept them instead of rejecting the file.
        cfg = replace(cfg, data=replace(cfg.data, action_tolerance=0.5))
    reduce = {"quick": _quick, "mid": _mid, "smoke": _smoke}.get(profile)  # full: the preset as it is
    return _method_defaults(cfg if reduce is None else reduce(cfg, spec), dom)


def env_record(spec) -> EnvConfig:
    """What config.json records of a user's task (botorl/envs/user.py); empty for botorl's tasks."""
    u = spec.user
    if u is None:
        return EnvConfig()
    return EnvConfig(entry=u.entry, path=u.path, max_steps=spec.max_episode_steps, success_key=u.success_key,
                     success_off=u.success_off, domain=None if spec.domain == "custom" else spec.domain,
                     reward_scale=spec.reward_scale, reward_bias=spec.reward_bias, obs_keys=u.obs_keys,
                     obs_dim=u.obs_dim, action_dim=u.action_dim, action_low=u.action_low, action_high=u.action_high)


# Cal-QL pre-training steps of the quick profile on pointmaze (see _quick).
QUICK_POINTMAZE_PRETRAIN = 20_000


def _quick(cfg: RunConfig, spec) -> RunConfig:
    cql = replace(cfg.offline.cql, cql_n_actions=5)
    if spec.domain in ("pointmaze", "antmaze"):
        cql = replace(cql, cql_lagrange=False, cql_weight=5.0)
    sac = cfg.online.sac
    data = cfg.data
    offline_steps = 10_000
    batch = cfg.offline.batch_size
    if spec.domain == "pointmaze":
        # Why no max-target backup, 2 samples, 128 rows and 20k steps: the module docstring; more
        # steps stop helping the medium maze (0.6 over 8 seeds from 20k to 40k; docs/results/pretraining.md).
        cql = replace(cql, max_target_backup=False, cql_n_actions=2)
        sac = replace(sac, max_target_backup=False)
        data = replace(data, steps=200_000)
        batch = 128
        offline_steps = QUICK_POINTMAZE_PRETRAIN
    elif spec.name == "door-binary-local":
        data = replace(data, steps=20_000)
    return replace(
        cfg,
        data=data,
        network=replace(cfg.network, actor_hidden_dims=(64, 64), critic_hidden_dims=(64, 64), num_critics=4),
        offline=replace(cfg.offline, steps=offline_steps, batch_size=batch, cql=cql, log_every=500),
        boto=replace(cfg.boto, boto_steps=5_000, steps_per_call=500),
        online=replace(cfg.online, steps=20_000, sac=sac, log_every=500),
        # the dip is read over evaluations every 500 steps from the warm-up's end to 10k
        eval=replace(cfg.eval, interval=2_500, dense_interval=500),
        checkpoint_every=5_000,
    )


def _mid(cfg: RunConfig, spec) -> RunConfig:
    cfg = _quick(cfg, spec)
    return replace(cfg, network=replace(cfg.network, num_critics=10), boto=replace(cfg.boto, boto_steps=10_000))


def _smoke(cfg: RunConfig, spec) -> RunConfig:
    cql = replace(cfg.offline.cql, cql_n_actions=2, num_backup_actions=2, cql_lagrange=False)
    sac = replace(cfg.online.sac, num_backup_actions=2)
    data = cfg.data
    if spec.domain == "pointmaze":
        data = replace(data, steps=2_000)
    elif spec.name == "door-binary-local":
        data = replace(data, steps=200)
    return replace(
        cfg,
        data=data,
        network=replace(cfg.network, actor_hidden_dims=(16,), critic_hidden_dims=(16,), num_critics=2),
        offline=replace(cfg.offline, steps=10, batch_size=32, updates_per_call=5, log_every=5, cql=cql),
        warmup=WarmupConfig(steps=30),
        boto=replace(cfg.boto, boto_steps=10, batch_size=32, steps_per_call=5),
        online=replace(cfg.online, steps=40, batch_size=16, log_every=10, sac=sac),
        eval=replace(cfg.eval, episodes=2, num_envs=2, interval=20, q_pairs=64),
        checkpoint_every=20,
    )


def _method_defaults(cfg: RunConfig, dom: str) -> RunConfig:
    """Settings that depend on the method on the paper domain ``dom``, as WSRL's code runs each
    (WSRL's launch scripts and configs, zhouzypaul/wsrl; docs/methods.md)."""
    m = cfg.method
    online = cfg.online
    network = cfg.network
    if m in ("calql", "cql", "iql"):
        # Their own loss continued online, UTD 1, batch 256, with the networks of their own
        # papers as WSRL ran its Cal-QL/CQL baselines: 2 critics, no LayerNorm. Offline data
        # kept: 50/50 batches (Cal-QL's scripts; 25% offline on kitchen). WSRL's launch scripts
        # leave its mixing ratio at 0 (offline data loaded, not sampled); we follow Cal-QL's.
        network = replace(network, num_critics=2, layer_norm=False)
        online = replace(online, utd=1, offline_ratio=0.25 if dom == "kitchen" else 0.5, random_steps=0)
        # WSRL runs them without a critic subset (critic_subsample_size None): the penalty on
        # both critics and the target the min of both. The 10-critic subset of BOTO/WSRL's
        # pre-training (a pair drawn with replacement) would penalise one critic twice and take
        # one critic as the target in half of the steps.
        cql = replace(cfg.offline.cql, cql_penalty_critics=None, num_min_critics=network.num_critics,
                      subsample_replace=False)
        cfg = replace(cfg, offline=replace(cfg.offline, cql=cql))
    elif m == "rlpd":
        # RLPD from scratch as WSRL ran it: 10 critics (LayerNorm), 50/50 offline/online, UTD 4
        # with WSRL's batch layout (4 x 256 critic rows, actor on 1,024), target entropy -|A|/2
        # (its Method's), no backup entropy, min over 2 distinct critics (1 on antmaze: WSRL's and
        # RLPD's num_min_qs=1), mean-over-critics actor, 5,000 steps of the untrained policy
        # before the first update. The RLPD paper's UTD 20 is `--online.utd 20`.
        sac = replace(online.sac, subsample_replace=False, actor_objective="mean", backup_entropy=False,
                      num_min_critics=1 if dom == "antmaze" else 2)
        random_steps = 5_000 if cfg.profile == "full" else min(5_000, max(1, online.steps // 10))
        online = replace(online, offline_ratio=0.5, random_steps=random_steps, sac=sac)
    else:  # boto, wsrl: WSRL's SAC (its target entropy: Method.target_entropy_per_dim), offline data dropped
        online = replace(online, utd=4, offline_ratio=0.0, random_steps=0)
    return replace(cfg, network=network, online=online)

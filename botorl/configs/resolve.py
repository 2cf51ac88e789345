"""Make a RunConfig consistent (``resolve``) and reject bad values (``validate``) before any work:
a ``ConfigError`` (exit code 2) that names the field and says what to change."""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import replace

from botorl.boto.config import check_alpha
from botorl.configs.custom import ensure_task
from botorl.configs.members import parse_alphas, parse_seeds
from botorl.configs.methods import get_method, resolve_pretrain
from botorl.configs.presets import PROFILES, paper_settings
from botorl.configs.schema import RunConfig
from botorl.data.safe import machine_memory
from botorl.envs.metric import check_refs
from botorl.envs.registry import get_task
from botorl.errors import ConfigError
from botorl.io import check_path_text
from botorl.jaxsetup import check_precision


# Agent-config fields that copy a run-config field (schema.py: one fact, one field), each with
# that field: ``derive`` sets them; the command line refuses their flags (configs/build.py).
DERIVED = {
    "actor_hidden_dims": "network.actor_hidden_dims",
    "critic_hidden_dims": "network.critic_hidden_dims",
    "value_hidden_dims": "network.critic_hidden_dims",  # IQL's value network
    "actor_layer_norm": "network.layer_norm",
    "critic_layer_norm": "network.layer_norm",
    "num_critics": "network.num_critics",
    "calql": "pretrain",
}


def _at(cfg: RunConfig, path: str):
    """The field at a dotted path, e.g. ``network.num_critics``."""
    return functools.reduce(getattr, path.split("."), cfg)


def _source(cfg: RunConfig, field: str):
    """The value of ``DERIVED[field]`` as the agents' configs hold it."""
    v = _at(cfg, DERIVED[field])
    if field == "calql":
        return v == "calql"  # the CQL loss is Cal-QL's when Cal-QL pre-trains
    return tuple(v) if isinstance(v, list) else v  # hashable: the jitted functions key on configs


def derive(agent_cfg, cfg: RunConfig, **special):
    """``agent_cfg`` (an agent's config) with its ``DERIVED`` fields taken from ``cfg``; ``special``
    gives values that are no copy (IQL's critic subset, the log-std range a warm start inherits)."""
    derived = {f: _source(cfg, f) for f in DERIVED if hasattr(agent_cfg, f)}
    return replace(agent_cfg, **{**derived, **special})


AGENT_CONFIGS = ("offline.cql", "offline.iql", "online.sac")


def check_derived(cfg: RunConfig) -> None:
    """ConfigError for a config read back (``--config``, a run's config.json) whose agent configs
    disagree with a field they copy: the agents build from their own configs, so such a copy would
    escape every check of its source (the size bounds among them)."""
    for section in AGENT_CONFIGS:
        agent_cfg = _at(cfg, section)
        for f in DERIVED:
            if hasattr(agent_cfg, f) and (got := getattr(agent_cfg, f)) != (want := _source(cfg, f)):
                raise ConfigError(f"{section}.{f} = {got!r} differs from {DERIVED[f]} = {want!r}, the one field that "
                                  f"sets it for every agent: the config was edited. Set {DERIVED[f]} "
                                  f"(--{DERIVED[f].replace('_', '-')}) instead.")


def resolve(cfg: RunConfig) -> RunConfig:
    """Fill the derived fields: pretrain, alpha, and what the pipeline owns in agent configs."""
    spec = get_task(cfg.task)
    method = get_method(cfg.method)
    cfg = replace(cfg, pretrain=resolve_pretrain(cfg.method, cfg.pretrain))  # first: Cal-QL's switch copies it
    # a population's shared config holds its first member's seed and alpha
    seed = cfg.seed if cfg.seeds is None else parse_seeds(cfg.seeds)[0]
    alpha = cfg.alpha  # a method without BOTO keeps the one given, which validate refuses
    if method.uses_alpha:
        given = cfg.alpha if cfg.alphas is None else parse_alphas(cfg.alphas)[0]
        alpha = float(paper_settings(spec)[0] if given is None else given)  # None: the task's, the paper's

    # The UTD is no agent field: an update's batch carries it (online: online.utd minibatches, SAC's
    # train_step), so pre-training takes one batch per critic step, as WSRL's and Cal-QL's loops do.
    cql = derive(cfg.offline.cql, cfg)
    sac = derive(cfg.online.sac, cfg)
    # IQL pre-trains the networks fine-tuning takes over (the paper's: sizes, LayerNorm,
    # ensemble, state-dependent std); its value network has the critic's hidden sizes. It keeps
    # IQL's log-std range [-5, 2], which the SAC learner then inherits.
    iql = derive(cfg.offline.iql, cfg, num_min_critics=min(cfg.offline.iql.num_min_critics, cfg.network.num_critics),
                 state_dependent_std=sac.state_dependent_std)
    if cfg.pretrain == "iql" and method.finetune_start == "warm_start":
        sac = replace(sac, log_std_min=iql.log_std_min, log_std_max=iql.log_std_max)
    if sac.target_entropy is None and method.target_entropy_per_dim is not None:
        sac = replace(sac, target_entropy=method.target_entropy_per_dim * spec.action_dim)
    return replace(cfg, seed=seed, alpha=alpha, offline=replace(cfg.offline, cql=cql, iql=iql),
                   online=replace(cfg.online, sac=sac))


BUDGETS = ("offline.steps", "warmup.steps", "boto.boto_steps", "online.steps", "online.random_steps")
POSITIVE = ("offline.batch_size", "offline.updates_per_call", "offline.log_every", "online.batch_size", "online.utd",
            "online.log_every", "eval.episodes", "eval.interval", "eval.num_envs", "eval.q_pairs", "eval.dense_until",
            "checkpoint_every", "network.num_critics")
MAX_BATCH = 1 << 20  # rows of one batch: 4096x the paper's 256
MAX_WIDTH = 1 << 16  # units of one hidden layer

# Caps (``check_bounds``) on counts a config (a run directory's file, or a typo) could make unbounded: far
# above any setting the papers use (256-unit layers, 10 critics, 10 sampled actions, 1M steps), they stop a
# value that would only hang or exhaust memory.
BOUNDS = {
    "network.num_critics": 1024,  # SAC-N's largest ensemble is 500
    "offline.cql.cql_n_actions": 1024,
    "offline.cql.num_backup_actions": 1024,
    "online.sac.num_backup_actions": 1024,
    "offline.steps": 10**12,
    "warmup.steps": 10**12,
    "boto.boto_steps": 10**12,
    "online.steps": 10**12,
    "online.random_steps": 10**12,
    "data.steps": 10**9,  # rows a generator makes
    # one evaluation: 1,000 episodes of a 300-step maze, or 64 envs made (about 0.3 s each), take
    # minutes on a 2-core machine; 10**6 episodes took hours, 1,024 envs half an hour to make
    "eval.episodes": 1_000,
    "eval.num_envs": 64,
    "env.max_steps": 10**7,  # an episode's horizon
    "env.obs_dim": 1 << 20,  # a task of one's own: the policy's input and output widths
    "env.action_dim": 1 << 16,
    "checkpoint_every": 10**12,
}
MAX_DEPTH = 64  # hidden layers of one network
# Weights of the hidden layers of the actor and of the whole critic ensemble together: 2**28 (1 GiB of
# float32, before Adam's two moments and the target copy) is 100x the paper's 4x256 critics x 10; a
# layer within MAX_WIDTH can still ask for more (65536 x 65536 is 4 billion weights).
MAX_PARAMS = 1 << 28
# Float fields where inf means something (no tolerance, no clip); NaN is never a setting.
INF_MEANS = ("data.action_tolerance", "offline.cql.cql_clip_diff_min", "offline.cql.cql_clip_diff_max")


def _floats(obj, prefix: str = ""):
    """(dotted name, value) of every float of a config, inside tuples too."""
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            yield from _floats(v, f"{prefix}{f.name}.")
        for x in (v if isinstance(v, tuple) else (v,)):
            if isinstance(x, float):
                yield prefix + f.name, x


def check_bounds(cfg: RunConfig) -> None:
    """ConfigError for a count or size beyond its cap (``BOUNDS``, ``MAX_WIDTH``, ``MAX_DEPTH``),
    or of the wrong type, or an agent's copy of a network size that differs from it
    (``check_derived``); needs no task, data or JAX, so it runs first on a config read back from
    a run directory."""
    for name, cap in BOUNDS.items():
        v = _at(cfg, name)
        if v is None and name.startswith(("data.steps", "env.")):
            continue
        if isinstance(v, bool) or not isinstance(v, int):
            raise ConfigError(f"--{name} = {v!r} is invalid: give an integer.")
        if v > cap:  # too small a value is ``validate``'s, with its own message
            raise ConfigError(f"--{name} = {v!r} is invalid: give at most {cap:,} (a larger value would only "
                              f"exhaust time or memory).")
    for name in ("network.actor_hidden_dims", "network.critic_hidden_dims"):
        dims = _at(cfg, name)
        if not isinstance(dims, (list, tuple)) or not 1 <= len(dims) <= MAX_DEPTH or not all(
                isinstance(d, int) and not isinstance(d, bool) and 1 <= d <= MAX_WIDTH for d in dims):
            raise ConfigError(f"--{name} = {dims!r} is invalid: give positive layer widths, e.g. 256 256, 1 to "
                              f"{MAX_DEPTH} layers; a layer is at most {MAX_WIDTH:,} units wide.")
    net = cfg.network
    dims = [net.actor_hidden_dims, *[net.critic_hidden_dims] * net.num_critics]
    params = sum(a * b for d in dims for a, b in zip(d, d[1:]))
    if params > MAX_PARAMS:
        raise ConfigError(f"--network.actor-hidden-dims {' '.join(map(str, net.actor_hidden_dims))} and "
                          f"--network.critic-hidden-dims {' '.join(map(str, net.critic_hidden_dims))} x "
                          f"--network.num-critics {net.num_critics} make {params:,} hidden-layer weights, more than "
                          f"{MAX_PARAMS:,}; give narrower layers or fewer critics.")
    tol = cfg.data.action_tolerance
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not tol >= 0:  # NaN too
        raise ConfigError(f"--data.action-tolerance = {tol!r} is invalid: give a number >= 0 (the largest "
                          f"|action| - 1 accepted in the data; inf accepts any).")
    for name, v in _floats(cfg):
        if math.isnan(v) or (math.isinf(v) and name not in INF_MEANS):
            raise ConfigError(f"--{name} = {v!r} is invalid: give a finite number.")
    if cfg.out is not None:
        check_path_text("--out", cfg.out)
    check_derived(cfg)  # and so the agents build what the bounds above checked


def _check_sizes(cfg: RunConfig, method, need) -> None:
    """Batch sizes and the replay buffer against a cap and against this machine's memory, before
    anything is allocated (a huge value is exit 2, not a MemoryError)."""
    for name in ("offline.batch_size", "online.batch_size", "boto.batch_size"):
        need(name, lambda v: isinstance(v, int) and 1 <= v <= MAX_BATCH,
             f"a batch size must be an integer in [1, {MAX_BATCH:,}]")
    try:
        spec = get_task(cfg.task)
    except ConfigError:
        return  # an unknown task is refused where the task is looked up, naming the valid ones
    warm = cfg.warmup.steps if "warmup" in method.stages else 0
    rows = cfg.online.buffer_capacity or (cfg.online.steps + warm + 1)
    if cfg.online.buffer_capacity is not None and "finetune" in method.stages:
        # the warm-up's transitions go into the buffer, and Cal-QL samples finished episodes only
        least = max(warm, spec.max_episode_steps)
        need("online.buffer_capacity", lambda v: v >= least,
             f"the replay buffer must hold the warm-up's {warm} transitions and one whole episode "
             f"({spec.max_episode_steps} steps on {cfg.task}); give at least {least}, or leave it unset (None: the "
             f"whole online budget)")
    members = (1 if cfg.seeds is None else len(parse_seeds(cfg.seeds))) * \
        (1 if cfg.alphas is None else len(parse_alphas(cfg.alphas)))  # each capped at MAX_MEMBERS
    row_bytes = 4 * (2 * spec.obs_dim + spec.action_dim + 4)
    have = machine_memory()
    if have and rows * row_bytes * members > have:
        what = "--online.buffer_capacity" if cfg.online.buffer_capacity else "--online.steps (the buffer holds them all)"
        raise ConfigError(
            f"the replay buffer would hold {rows:,} transitions ({rows * row_bytes * members / 2**30:.1f} GiB"
            f"{f' for {members} members' if members > 1 else ''}), more than this machine's "
            f"{have / 2**30:.1f} GiB of memory. Lower {what}{' or use fewer members (--seeds/--alphas)' if members > 1 else ''}.")
    call_rows = max(cfg.offline.updates_per_call * cfg.offline.batch_size, cfg.online.utd * cfg.online.batch_size,
                    cfg.boto.steps_per_call * cfg.boto.batch_size)
    if have and call_rows * row_bytes * members > have:
        raise ConfigError(
            f"one jitted call's batches would hold {call_rows:,} rows ({call_rows * row_bytes / 2**30:.1f} GiB per "
            f"member), more than this machine's {have / 2**30:.1f} GiB of memory. Lower the batch sizes, "
            f"--offline.updates-per-call, --boto.steps-per-call or --online.utd.")


def validate(cfg: RunConfig) -> None:
    """Raise ConfigError for any value that cannot run (call after ``resolve``)."""
    check_bounds(cfg)
    ensure_task(cfg)  # a task of one's own: registered in this process (never imported from the file)

    method = get_method(cfg.method)
    if cfg.profile not in PROFILES:
        raise ConfigError(f"unknown profile {cfg.profile!r} (--profile); choose one of {', '.join(PROFILES)}.")
    # alpha enters here, whatever gave the config (flags, a sweep, a file read back), and is checked
    # here alone: the population's members and the BOTO stage take it as checked
    if flag := next((f for f, v in (("--alpha", cfg.alpha), ("--alphas", cfg.alphas)) if v is not None), None):
        method.refuse_alpha(flag)
    if method.uses_alpha:
        check_alpha(cfg.alpha)

    def need(field: str, ok, what: str) -> None:  # ``ok(the value of field)``, else ConfigError
        if not ok(value := _at(cfg, field)):
            raise ConfigError(f"--{field} = {value!r} is invalid: {what}.")

    if cfg.pretrained is not None and "pretrain" not in method.stages:
        raise ConfigError(f"--pretrained {cfg.pretrained}: --method {cfg.method} has no pre-training to skip; "
                          f"drop --pretrained.")
    check_precision(cfg.precision)  # a config file's value: the command line's is checked by tyro
    for name in ("seed", "data.seed", "online_reseed"):
        # NumPy's generators take only non-negative seeds; 2**31 keeps JAX keys in int32
        need(name, lambda v: isinstance(v, int) and 0 <= v < 2**31, "a seed must be an integer in [0, 2**31)")

    for names, least, what in ((BUDGETS, 0, "a step budget must be a non-negative integer (0 skips the work)"),
                               (POSITIVE, 1, "must be a positive integer")):
        for name in names:
            need(name, lambda v: isinstance(v, int) and v >= least, what)
    need("eval.dense_interval", lambda v: isinstance(v, int) and v >= 0,
         "give the env steps between dense evaluations, or 0 for none")
    need("online.offline_ratio", lambda v: 0.0 <= v <= 1.0, "must lie in [0, 1]")
    need("online.buffer_capacity", lambda v: v is None or v >= 1, "must be positive or None")
    _check_sizes(cfg, method, need)  # the layer widths: check_bounds
    parse_seeds(cfg.seeds)  # None: no population, nothing to check
    parse_alphas(cfg.alphas)
    if "warmup" in method.stages and cfg.online.steps <= cfg.warmup.steps:
        raise ConfigError(f"--online.steps = {cfg.online.steps} leaves no fine-tuning after the "
                          f"{cfg.warmup.steps}-step warm-up: the warm-up's env steps count as online steps (WSRL's "
                          "accounting), so online.steps is the whole online budget. Raise --online.steps above "
                          "--warmup.steps or lower --warmup.steps.")
    if method.pretrains:
        (cfg.offline.iql if cfg.pretrain == "iql" else cfg.offline.cql).validate()
    if method.finetune_start in ("warm_start", "scratch"):
        cfg.online.sac.validate()
    if "boto" in method.stages:
        cfg.boto.validate()
    if cfg.metric.name == "score":
        check_refs(cfg.metric.ref_min_score, cfg.metric.ref_max_score, f"task {cfg.task!r}")

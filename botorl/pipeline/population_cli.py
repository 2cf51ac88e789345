"""``botorl run --seeds ... [--alphas ...]`` and ``botorl resume POPDIR``: a population.

    botorl run --seeds 0-7                                  # 8 seeds of BOTO, quick, one program
    botorl run --method boto --seeds 0-3 --alphas -1:1:0.5  # 4 seeds x 5 alphas = 20 members
    botorl resume runs/pointmaze-umaze-boto-pop8-...        # after a crash or kill -9

The members are every (seed, alpha) pair; all other settings are shared (any config field
may be set as for `botorl run`). The population directory holds ``population.json``
(members, status, the shared config), ``checkpoints/`` (one checkpoint of the whole
population) and one ordinary run directory per member, named ``seed<k>`` or
``alpha<+0.50>-seed<k>`` (botorl.configs.members.Member.name), which `botorl report` and
`botorl eval` read like any run. Before any work the population's memory is estimated and
compared with what the machine has (exit 2 if it does not fit).
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

from botorl.errors import ConfigError
from botorl.pipeline import preempt

def estimate(cfg, n: int, d_raw, spec=None) -> dict[str, int]:
    """The population's memory by part (population.estimate_memory), from one template member;
    with the task's ``spec``, its environments measured (one training env and
    eval.envs_per_member evaluation envs per member)."""
    from botorl.pipeline import population as P
    from botorl.pipeline import stages as S
    from botorl.configs.methods import get_method

    # envs first: made after JAX has built its first arrays, the first ~16 pointmaze envs grow the
    # process by twice what each later one does (allocator arenas), which would double the estimate.
    # Measured only for populations: one member's envs are a few hundred MB at most.
    per_env = 0 if spec is None or n < 2 else P.env_bytes(lambda i: spec.make_env(seed=i, evaluation=True))
    method = get_method(cfg.method)
    O, A = d_raw.obs_dim, d_raw.action_dim
    agent_bytes = P.tree_bytes(S.make_online_agent_template(cfg, O, A, 0))
    if method.pretrains:
        agent_bytes += P.tree_bytes(S.make_pretrain_agent(cfg, O, A, 0))
    oc = cfg.online
    warm = cfg.warmup.steps if "warmup" in method.stages else 0
    rows = oc.buffer_capacity or (oc.steps + warm + 1)
    cql = cfg.offline.cql
    width = max(max(cfg.network.critic_hidden_dims), max(cfg.network.actor_hidden_dims))
    layers = len(cfg.network.critic_hidden_dims)
    act = max(cfg.offline.batch_size * (3 * cql.cql_n_actions + 1) * cql.num_critics,
              oc.utd * oc.batch_size * cfg.network.num_critics) * width * layers * 2
    batch_rows = max(cfg.offline.updates_per_call * cfg.offline.batch_size, cfg.boto.steps_per_call * cfg.boto.batch_size,
                     oc.utd * oc.batch_size)
    offline_bytes = 3 * sum(getattr(d_raw, k).nbytes for k in ("observations", "actions", "rewards",
                                                             "next_observations", "terminals"))
    envs = 1 + cfg.eval.envs_per_member
    return P.estimate_memory(num_members=n, agent_bytes=agent_bytes, buffer_rows=rows, warmup_rows=warm, obs_dim=O,
                             action_dim=A, batch_rows=batch_rows, activation_floats=act, offline_bytes=offline_bytes,
                             env_bytes_per_member=envs * per_env)


def _default_out(cfg, n: int) -> Path:
    return Path("runs") / f"{cfg.task}-{cfg.method}-pop{n}-{time.strftime('%Y%m%d-%H%M%S')}"


def run_population_main(cfg) -> int:
    """Run the population ``cfg`` describes (a built config with ``seeds`` or ``alphas``)."""
    from botorl.configs.schema import to_dict
    from botorl.envs.registry import get_task
    from botorl.jaxsetup import setup_jax
    from botorl.pipeline import population as P
    from botorl.pipeline.rundir import check_out, io_fault, owned
    from botorl.io import atomic_write_json
    from botorl.pipeline.rundir import RunDir
    from botorl.pipeline.runner import POPULATION_FILE, load_offline, write_population_file

    from botorl.configs.members import population

    setup_jax()
    members, member_cfgs = population(cfg)
    out = Path(cfg.out) if cfg.out else _default_out(cfg, len(members))
    check_out(out)

    def already():
        if (out / POPULATION_FILE).exists() or (out / "config.json").exists():
            raise ConfigError(f"--out {out} already holds a run or population. Continue it with `botorl resume {out}`, "
                              f"or pick another --out.")

    already()
    cfg = replace(cfg, out=str(out))
    spec = get_task(cfg.task)
    d_raw = load_offline(cfg, spec)  # a missing dataset fails here, before any directory exists
    if cfg.pretrained is not None:  # so does a --pretrained without every seed's pre-training
        from botorl.pipeline import shared_pretrain

        shared_pretrain.match(member_cfgs, cfg.pretrained)
    parts = estimate(cfg, len(members), d_raw, spec)
    import jax

    if jax.default_backend() == "cpu":
        P.check_memory(parts, len(members))
    else:  # environments live in host memory, the rest on the accelerator
        envs = parts.pop("environments")
        parts["total"] -= envs
        P.check_memory(parts, len(members))
        P.check_memory({"environments": envs, "total": envs}, len(members), available=P.host_memory())
    runs = [RunDir(out / m.name) for m in members]
    member_cfgs = [replace(c, out=str(r.root)) for c, r in zip(member_cfgs, runs)]
    with owned(out):
        already()
        try:
            for c, r in zip(member_cfgs, runs):
                r.create()
                atomic_write_json(r.config, to_dict(c))
            write_population_file(out, cfg, member_cfgs, "running", ["running"] * len(members), {})
        except OSError as err:
            fault = io_fault(err, out)
            if fault is None:
                raise
            raise fault from None
        print(f"botorl: {cfg.method} on {cfg.task} (profile {cfg.profile}), a population of {len(members)}: "
              f"{', '.join(m.name for m in members)} -> {out}", file=sys.stderr)
        with preempt.resumable(f"botorl resume {out}"):
            summaries = _execute(cfg, member_cfgs, out, runs, d_raw, resume=False)
    print(format_population(summaries))
    return 0


def _execute(cfg, member_cfgs, out: Path, runs, d_raw, *, resume: bool):
    """execute_population with I/O faults turned into exit 2 and a truthful population status."""
    from botorl.errors import BotorlError
    from botorl.pipeline.rundir import io_fault
    from botorl.pipeline.runner import execute_population

    try:
        return execute_population(cfg, member_cfgs, out, runs, d_raw, resume=resume, single=False)
    except OSError as err:
        fault = io_fault(err, out)
        if fault is None:
            raise
        _mark_population_failed(out, str(fault))
        raise fault from None
    except BotorlError as err:
        _mark_population_failed(out, str(err))
        raise


def _mark_population_failed(out: Path, reason: str) -> None:
    from botorl.io import atomic_write_json
    from botorl.pipeline.rundir import read_json
    from botorl.pipeline.runner import POPULATION_FILE

    try:
        data = read_json(out / POPULATION_FILE)
        data.update(status="failed", error=reason)
        atomic_write_json(out / POPULATION_FILE, data)
    except (OSError, ValueError):
        pass


def member_dir(root: Path, entry) -> Path:
    """The run directory of a population member named in population.json: only a name botorl
    itself makes (``seed<k>``, ``alpha<+0.50>-seed<k>``: configs.members.Member.name) of a
    real folder directly inside ``root``; ConfigError (exit 2) for anything else."""
    from botorl.configs.members import MEMBER_NAME

    name = entry.get("name") if isinstance(entry, dict) else None
    if not isinstance(name, str) or not MEMBER_NAME.fullmatch(name):
        raise ConfigError(f"{root / 'population.json'} names a member {name!r}, which is not a member name botorl "
                          f"makes (seed<k> or alpha<+a.aa>-seed<k>); the file was edited or is not botorl's.")
    path = root / name
    if path.is_symlink() or (path.exists() and path.resolve().parent != root.resolve()):
        raise ConfigError(f"{path} is a link out of the population directory {root}; a member's run directory must "
                          f"be a folder inside it.")
    return path


def load_population(directory: str | Path):
    """(shared config, member configs, member run dirs) of a population directory."""
    from botorl.configs.members import member_config
    from botorl.configs.resolve import validate
    from botorl.configs.schema import RunConfig, from_dict
    from botorl.pipeline.rundir import RunDir, read_json
    from botorl.pipeline.runner import POPULATION_FILE

    root = Path(directory)
    try:
        data = read_json(root / POPULATION_FILE)
        cfg = from_dict(RunConfig, data["config"])
        if not isinstance(data["members"], list) or not data["members"]:
            raise ValueError("no member list")
        runs = [RunDir(member_dir(root, m)) for m in data["members"]]
        member_cfgs = [from_dict(RunConfig, read_json(r.config)) for r in runs]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise ConfigError(f"{root / POPULATION_FILE} (or a member's config.json) cannot be read ({err}); "
                          f"was it edited by hand?") from None
    if len({r.root.name for r in runs}) != len(runs):
        raise ConfigError(f"{root / POPULATION_FILE} names a member twice; was it edited by hand?")
    validate(cfg)
    for r, mc in zip(runs, member_cfgs):
        # a member differs from the population in its seed, alpha and folder only
        want = member_config(cfg, mc.seed, mc.alpha, mc.out)
        if replace(mc, progress=cfg.progress) != want:
            raise ConfigError(f"{r.config} does not describe a member of the population in {root} (its settings "
                              f"other than seed and alpha differ from {root / POPULATION_FILE}'s config); was it "
                              f"edited by hand?")
    # where the members are is where they were found, whatever the files say
    member_cfgs = [replace(mc, out=str(r.root)) for r, mc in zip(runs, member_cfgs)]
    return replace(cfg, out=str(root)), member_cfgs, runs, data


def resume_population_main(directory: str, *, no_progress: bool = False, allow_pickle: bool = False) -> int:
    from botorl.envs.registry import get_task
    from botorl.jaxsetup import setup_jax
    from botorl.pipeline.rundir import owned
    from botorl.pipeline.runner import load_offline, read_summary

    setup_jax()
    cfg, member_cfgs, runs, data = load_population(directory)
    root = Path(directory)
    if cfg.wandb:
        from botorl.pipeline.tracking import require_wandb

        require_wandb()
    with owned(root):
        if no_progress:
            cfg = replace(cfg, progress=False)
            member_cfgs = [replace(c, progress=False) for c in member_cfgs]
        if data.get("status") == "finished":
            print(f"botorl: {root} has finished already; nothing to resume.", file=sys.stderr)
            summaries = [read_summary(r) for r in runs]
            try:
                print(format_population(summaries))
            except (KeyError, TypeError, ValueError, AttributeError):  # a member's summary edited by hand
                print("\n".join(f"{r.root.name}: status {s.get('status')!r}" for r, s in zip(runs, summaries)))
            return 0
        if allow_pickle:
            d_raw = load_offline(cfg, get_task(cfg.task))
        else:  # a pickle named in population.json is not the user's to run (as for a run's config.json)
            from botorl.data.loaders import refuse_pickle

            with refuse_pickle(f"the population directory's {root / 'population.json'}"):
                d_raw = load_offline(cfg, get_task(cfg.task))
        with preempt.resumable(f"botorl resume {root}"):
            summaries = _execute(cfg, member_cfgs, root, runs, d_raw, resume=True)
    print(format_population(summaries))
    return 0


def format_population(summaries: list[dict]) -> str:
    def f(v):
        return "-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))

    lines = [f"{'member':<22} {'status':<9} {'initial':>8} {'10k':>8} {'final':>8}  run directory"]
    for s in summaries:
        name = Path(s["run_dir"]).name
        lines.append(f"{name:<22} {s['status']:<9} {f(s['success_initial']):>8} {f(s['success_10k']):>8} "
                     f"{f(s['success_final']):>8}  {s['run_dir']}")
    secs = summaries[0].get("stage_seconds", {}) if summaries else {}
    lines.append("stage seconds (whole population): " + ", ".join(f"{k} {v:.1f}" for k, v in secs.items()))
    return "\n".join(lines)

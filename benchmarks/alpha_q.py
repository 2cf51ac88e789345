"""What BOTO's alpha does to Q on a real task: Q after BOTO at several distances from the data.

    python benchmarks/alpha_q.py --task pointmaze-medium --seeds 100-101 --out alpha-q

For each seed, one pre-training and warm-up (a `botorl run` of WSRL that stops after its
warm-up, reused when it exists), then BOTO from that same pre-trained agent for every *arm*:
alpha in {-1, 0, +1} (the paper's objective), and two ablations of the preset's alpha, without
the entropy term in the target (``backup_entropy`` off) and without the warm-up rows (D_BOTO =
D_offline). At each of ``--steps`` BOTO steps, over ``--states`` dataset states: the mean Q of
the ensemble on the dataset actions, on actions at distance 0.1, 0.3, 1 and 2 from them (a
uniform direction, clipped to the action box, so the realised distance is also recorded) and
on uniform actions. Theorem 2 orders Q off the data by alpha: larger alpha, lower Q.

Also the size of what alpha multiplies: the hybrid noise's squared distance ||a - a_bar||^2 on
the dataset actions (its mean, and the share of draws above 0.01 and 0.1) against the reward
scale and the entropy term tau * log pi(a~|s') of the target.

Writes ``alpha_q.csv`` (one row per seed, arm and step), ``alpha_q.md`` (means over seeds) and
``alpha_q.png`` (Q against distance per alpha; the Q gap data - uniform against BOTO steps).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

DISTANCES = (0.1, 0.3, 1.0, 2.0)


def _pretrained(task: str, seed: int, root: Path, profile: str):
    """The pre-trained agent, D_offline (transformed) and D_warmup of a WSRL run that stops
    after its warm-up (made once, resumed if it was cut)."""
    from botorl.agents import agent_file
    from botorl.configs.presets import make_preset
    from botorl.configs.schema import RunConfig, from_dict
    from botorl.data.dataset import Dataset
    from botorl.envs.registry import get_task
    from botorl.pipeline.checkpoint import CheckpointManager
    from botorl.pipeline.rundir import read_json
    from botorl.pipeline.runner import load_offline, transform_dataset
    from botorl.pipeline.stages import make_pretrain_agent

    run = root / f"seed{seed}"
    if not ((run / "summary.json").exists() and read_json(run / "summary.json").get("status") == "finished"):
        if (run / "config.json").exists():
            cmd = ["resume", str(run)]
        else:
            warm = make_preset(task, profile, "wsrl").warmup.steps
            cmd = ["run", "--task", task, "--method", "wsrl", "--seed", str(seed), "--profile", profile,
                   "--online.steps", str(warm + 1), "--no-progress", "--no-tensorboard", "--out", str(run)]
        subprocess.run([sys.executable, "-m", "botorl.cli", *cmd], check=True)
    cfg = from_dict(RunConfig, read_json(run / "config.json"))
    spec = get_task(cfg.task)
    d_off = transform_dataset(cfg, spec, load_offline(cfg, spec))
    ckpt = CheckpointManager(run / "checkpoints")
    agent = agent_file.load(ckpt.file("pretrain-final", "agent.ckpt"),
                            like=make_pretrain_agent(cfg, d_off.obs_dim, d_off.action_dim, cfg.seed))
    a = ckpt.arrays("warmup-final", "warmup")
    d_warm = Dataset(a["observations"], a["actions"], a["rewards"], a["next_observations"], a["terminals"],
                     a["episode_ends"], a.get("mc_returns"), metadata={"source": "D_warmup"})
    return cfg, agent, d_off, d_warm


def q_profile(agent, obs: np.ndarray, acts: np.ndarray, rng: np.random.Generator) -> dict[str, float]:
    """Mean ensemble Q on the data actions, at each distance, and on uniform actions."""
    import jax.numpy as jnp

    def q(a):
        return float(jnp.mean(agent.critic_values(agent.critic.params, jnp.asarray(obs), jnp.asarray(a, jnp.float32))))

    out = {"q_data": q(acts)}
    for d in DISTANCES:
        u = rng.normal(size=acts.shape)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        moved = np.clip(acts + d * u, -1.0, 1.0)
        out[f"q_d{d:g}"] = q(moved)
        out[f"dist_d{d:g}"] = float(np.linalg.norm(moved - acts, axis=1).mean())
    out["q_uniform"] = q(rng.uniform(-1, 1, acts.shape))
    return out


def noise_scale(agent, cfg, d_off, rng: np.random.Generator, n: int = 20_000) -> dict[str, float]:
    """||a - a_bar||^2 of the hybrid noise on dataset actions, and the target's other terms."""
    import jax
    import jax.numpy as jnp

    from botorl.boto.noise import make_noise_fn

    idx = rng.integers(0, len(d_off), n)
    a = jnp.asarray(d_off.actions[idx])
    noise = make_noise_fn(cfg.boto.noise, log_sigma=cfg.boto.log_sigma, sigma=cfg.boto.sigma,
                          weight_fn=cfg.boto.weight_fn, clip=cfg.boto.clip)
    a_bar, info = noise(jax.random.PRNGKey(0), a)
    sq = np.asarray(jnp.sum((a - a_bar) ** 2, axis=-1))
    obs = jnp.asarray(d_off.next_observations[idx[:2_000]])
    mean, log_std = agent.policy(obs)
    from botorl.networks import sample_tanh_gaussian

    _, logp = sample_tanh_gaussian(jax.random.PRNGKey(1), mean, log_std)
    tau = float(agent.temperature())
    return {"sq_dist_mean": float(sq.mean()), "share_sq_dist_gt_0.01": float((sq > 0.01).mean()),
            "share_sq_dist_gt_0.1": float((sq > 0.1).mean()), "uniform_share": float(np.asarray(info["uniform"]).mean()),
            "reward_abs_mean": float(np.abs(d_off.rewards).mean()), "tau": tau,
            "tau_logp_mean": tau * float(np.asarray(logp).mean()), "discount": float(agent.config.discount)}


def _weight(text: str | None):
    if text is None:
        return None
    try:
        return float(text)
    except ValueError:
        return text


def arms(preset_alpha: float) -> dict[str, dict]:
    return {"alpha=-1": {"alpha": -1.0}, "alpha=0": {"alpha": 0.0}, "alpha=+1": {"alpha": 1.0},
            f"alpha={preset_alpha:+g}, no entropy term": {"alpha": preset_alpha, "backup_entropy": False},
            f"alpha={preset_alpha:+g}, no warm-up rows": {"alpha": preset_alpha, "warmup": False}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python benchmarks/alpha_q.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="pointmaze-medium")
    p.add_argument("--profile", default="quick")
    p.add_argument("--seeds", default="100-101", help="e.g. 100-101 or 100,105")
    p.add_argument("--steps", default="1000,5000,20000,100000", help="BOTO steps at which Q is measured")
    p.add_argument("--states", type=int, default=1000)
    p.add_argument("--arms", default=None, help="comma-separated arm names (default: all)")
    p.add_argument("--weight-fn", default=None,
                   help="the hybrid noise's mixing weight for every arm: linear (w = t, the default) or a constant share")
    p.add_argument("--log-sigma", type=float, default=None, help="the hybrid noise's log sigma for every arm")
    p.add_argument("--runs", default=None, help="folder of the pre-training runs (default: OUT/runs); share it "
                                                "between probes to compare them on the same pre-trainings")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    from botorl.jaxsetup import setup_jax

    setup_jax()
    from botorl.boto.phase import run_boto
    from botorl.configs.members import parse_seeds

    seeds = parse_seeds(args.seeds)
    steps = sorted(int(s) for s in args.steps.split(","))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from botorl.configs.presets import make_preset
    from botorl.configs.resolve import resolve

    # the pre-training runs are WSRL's (no alpha): the ablations use BOTO's preset alpha for the task
    preset_alpha = resolve(make_preset(args.task, args.profile, "boto")).alpha
    # arm names hold ", " themselves ("alpha=-1, no entropy term"): split only at a bare comma
    chosen = set(re.split(r",(?=\S)", args.arms)) if args.arms else set()
    unknown = chosen - set(arms(preset_alpha))
    if unknown:
        from botorl.errors import ConfigError

        raise ConfigError(f"--arms: unknown arm(s) {sorted(unknown)}; choose from {list(arms(preset_alpha))}.")
    rows: list[dict] = []
    scales: list[dict] = []
    done: set[tuple[int, str]] = set()
    if (out / "alpha_q.csv").exists():  # resume: keep the arms already measured
        with open(out / "alpha_q.csv", newline="") as f:
            rows = [{k: (v if k == "arm" else float(v)) for k, v in r.items()} for r in csv.DictReader(f)]
        for r in rows:
            r["seed"], r["step"] = int(r["seed"]), int(r["step"])
        done = {(r["seed"], r["arm"]) for r in rows if r["step"] == steps[-1]}
        rows = [r for r in rows if (r["seed"], r["arm"]) in done or r["arm"] == "pre-trained"]
    for seed in seeds:
        cfg, agent0, d_off, d_warm = _pretrained(args.task, seed, Path(args.runs) if args.runs else out / "runs",
                                                 args.profile)
        noise = {k: v for k, v in (("weight_fn", _weight(args.weight_fn)), ("log_sigma", args.log_sigma))
                 if v is not None}
        cfg = dataclasses.replace(cfg, boto=dataclasses.replace(cfg.boto, **noise))
        rng = np.random.default_rng(seed)
        pick = rng.choice(len(d_off), size=min(args.states, len(d_off)), replace=False)
        obs, acts = d_off.observations[pick], d_off.actions[pick]
        scales.append({"seed": seed, **noise_scale(agent0, cfg, d_off, np.random.default_rng(seed))})
        if not any(r["seed"] == seed and r["arm"] == "pre-trained" for r in rows):
            rows.append({"seed": seed, "arm": "pre-trained", "alpha": math.nan, "step": 0,
                         **q_profile(agent0, obs, acts, np.random.default_rng(7))})
        for name, arm in arms(preset_alpha).items():
            if (chosen and name not in chosen) or (seed, name) in done:
                continue
            boto = dataclasses.replace(cfg.boto, boto_steps=steps[-1],
                                       backup_entropy=arm.get("backup_entropy", cfg.boto.backup_entropy))

            def measure(step, agent, _record, name=name, arm=arm):
                if step in steps:
                    rows.append({"seed": seed, "arm": name, "alpha": arm["alpha"], "step": step,
                                 **q_profile(agent, obs, acts, np.random.default_rng(7))})

            run_boto(agent0, d_off, d_warm if arm.get("warmup", True) else None, boto, alpha=arm["alpha"],
                     seed=cfg.online_seed, callback=measure,
                     progress=False)
            print(f"seed {seed} {name}: done", flush=True)
            _write(out, rows, scales, steps)
        _write(out, rows, scales, steps)
    return 0


def _write(out: Path, rows, scales, steps) -> None:
    from botorl.experiments.stats import csv_text, pyplot
    from botorl.io import atomic_save_figure, atomic_write_text

    keys = list(rows[0])
    atomic_write_text(out / "alpha_q.csv", csv_text(keys, ([r[k] for k in keys] for r in rows)))
    qcols = ["q_data"] + [f"q_d{d:g}" for d in DISTANCES] + ["q_uniform"]
    md = ["# alpha on Q after BOTO", "",
          f"Means over seeds {sorted({r['seed'] for r in rows})}; Q of the ensemble, mean over dataset states.", "",
          "| arm | BOTO steps | " + " | ".join(qcols) + " | gap data - uniform |",
          "|---|---|" + "---|" * (len(qcols) + 1)]
    groups: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["arm"], r["step"]), []).append(r)
    for (arm, step), g in groups.items():
        means = [float(np.mean([r[c] for r in g])) for c in qcols]
        md.append(f"| {arm} | {step} | " + " | ".join(f"{m:.2f}" for m in means) + f" | {means[0] - means[-1]:.2f} |")
    dists = {d: float(np.mean([r[f"dist_d{d:g}"] for r in rows])) for d in DISTANCES}
    md += ["", "Realised mean distance after clipping to the box: "
           + ", ".join(f"{d:g} -> {v:.2f}" for d, v in dists.items()), "",
           "## What alpha multiplies", "", "| seed | " + " | ".join(k for k in scales[0] if k != "seed") + " |",
           "|---|" + "---|" * (len(scales[0]) - 1)]
    for s in scales:
        md.append(f"| {s['seed']} | " + " | ".join(f"{v:.4g}" for k, v in s.items() if k != "seed") + " |")
    atomic_write_text(out / "alpha_q.md", "\n".join(md) + "\n")
    keys = list(scales[0])
    atomic_write_text(out / "alpha_q_scale.csv", csv_text(keys, ([s[k] for k in keys] for s in scales)))
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    names = [a for a in dict.fromkeys(r["arm"] for r in rows) if a != "pre-trained"]
    color = {a: f"C{i}" for i, a in enumerate(names)} | {"pre-trained": "grey"}
    xs = [0.0] + list(DISTANCES)
    for (arm, step), g in groups.items():
        if step != steps[-1] and arm != "pre-trained":
            continue
        ys = [float(np.mean([r[c] for r in g])) for c in qcols[:-1]]
        ax1.plot(xs, ys, marker="o", ms=3, label=arm, color=color[arm], ls="--" if arm == "pre-trained" else "-")
    ax1.set_xlabel("distance from the dataset action")
    ax1.set_ylabel("mean Q")
    ax1.set_title(f"Q after {steps[-1]:,} BOTO steps", fontsize=9)
    ax1.legend(fontsize=7)
    by_arm: dict[str, list[tuple[int, float]]] = {}
    for (arm, step), g in groups.items():
        if arm == "pre-trained":
            continue
        by_arm.setdefault(arm, []).append((step, float(np.mean([r["q_data"] - r["q_uniform"] for r in g]))))
    for arm, pts in by_arm.items():
        pts.sort()
        ax2.plot([p[0] for p in pts], [p[1] for p in pts], "-o", ms=3, label=arm, color=color[arm])
    pre = groups.get(("pre-trained", 0))
    if pre:
        ax2.axhline(float(np.mean([r["q_data"] - r["q_uniform"] for r in pre])), color="grey", ls="--",
                    label="pre-trained")
    ax2.set_xscale("log")
    ax2.set_xlabel("BOTO steps")
    ax2.set_ylabel("Q(data) - Q(uniform)")
    ax2.set_title("the gap between data and uniform actions", fontsize=9)
    ax2.legend(fontsize=7)
    fig.tight_layout()
    atomic_save_figure(fig, out / "alpha_q.png")


if __name__ == "__main__":
    sys.exit(main())

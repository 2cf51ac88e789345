"""What writing checkpoints costs the online loop, at the quick profile's interval (issue 15, item 6).

    python benchmarks/checkpoint_cost.py [--task pointmaze-medium] [--steps 1000] [--every 250] [--json PATH]

Three fine-tuning runs of the quick profile in this one process (pre-training and BOTO cut to
a few steps: what they train does not change what a checkpoint holds or what an online step
costs; the warm-up keeps the profile's 5,000 steps, so the replay buffer holds what it holds
there): one short run to compile everything, then the same ``--steps`` online steps twice --
with a mid-stage checkpoint every ``--every`` steps (A) and with none (B). The runs are
deterministic (same seed), so A and B do the same work apart from the checkpoints.

Printed:
* ``step_s``: B's online loop time per env step (fine-tuning stage time minus evaluations);
* ``ckpt_s``: the mean wall time of one mid-stage checkpoint in A (``RunContext.save`` at a
  fine-tuning step: agent file, replay buffer, env states, manifest with sha256, fsyncs, summary);
* ``ratio``: ckpt_s / (checkpoint_every x step_s), the share of the online loop checkpoints
  take at the profile's interval (quick: every 5,000 steps); the goal is <= 5 %;
* ``ratio_ab``: the same from the difference of A's and B's loop times (noisier: it carries
  the machine's load).

A checkpoint's buffer holds ``size`` rows, so at the profile's later checkpoints (up to the
20,000 online steps) it is larger than here; ``buffer_mb`` says how large it was and
``buffer_mb_at_end`` how large it would be at the last one, to judge the difference.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path


def _run(argv: list[str], out: Path) -> dict:
    from botorl.envs.registry import get_task
    from botorl.pipeline import runner
    from botorl.configs.build import build_config
    from botorl.pipeline.rundir import RunDir

    cfg = build_config([*argv, "--out", str(out)])
    d_raw = runner.load_offline(cfg, get_task(cfg.task))
    timers = {"save_mid": [], "evaluate": []}
    orig_save, orig_eval = runner.RunContext.save, runner.RunContext.evaluate

    def save(self, stage, step, *a, **kw):
        t = time.perf_counter()
        try:
            return orig_save(self, stage, step, *a, **kw)
        finally:
            if stage == "finetune" and step is not None:  # mid-stage (step None: the stage's end)
                timers["save_mid"].append(time.perf_counter() - t)

    def evaluate(self, *a, **kw):
        t = time.perf_counter()
        try:
            return orig_eval(self, *a, **kw)
        finally:
            if self._stage == "finetune":
                timers["evaluate"].append(time.perf_counter() - t)

    runner.RunContext.save, runner.RunContext.evaluate = save, evaluate
    try:
        out.mkdir(parents=True)
        (summary,) = runner.execute(cfg, [cfg], out, [RunDir(out)], d_raw)
    finally:
        runner.RunContext.save, runner.RunContext.evaluate = orig_save, orig_eval
    ft = summary["stage_seconds"]["finetune"]
    buf = [p.stat().st_size for p in (out / "checkpoints").glob("finetune-step*/buffer.npz")]
    ck = [sum(f.stat().st_size for f in p.iterdir()) for p in (out / "checkpoints").glob("finetune-step*")]
    return {"finetune_s": ft, "eval_s": sum(timers["evaluate"]), "loop_s": ft - sum(timers["evaluate"]),
            "ckpt_times": timers["save_mid"], "buffer_bytes": max(buf, default=0), "ckpt_bytes": max(ck, default=0),
            "cfg": cfg}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="pointmaze-medium")
    p.add_argument("--steps", type=int, default=1000, help="online steps of runs A and B (after the warm-up)")
    p.add_argument("--every", type=int, default=250, help="run A's checkpoint interval (for the measurement)")
    p.add_argument("--json", default=None, help="also write the numbers here")
    args = p.parse_args(argv)
    from botorl.jaxsetup import setup_jax

    setup_jax()
    from botorl.configs.presets import make_preset

    preset = make_preset(args.task, "quick")
    every_default, warm = preset.checkpoint_every, preset.warmup.steps
    base = ["--task", args.task, "--profile", "quick", "--no-progress", "--no-tensorboard", "--offline.steps", "20",
            "--boto.boto_steps", "20", "--eval.episodes", "2", "--eval.num_envs", "2", "--eval.interval", "1000000000"]
    root = Path(tempfile.mkdtemp(prefix="botorl-ckpt-cost-"))
    print(f"compiling (a short run) in {root} ...", file=sys.stderr)
    _run(base + ["--online.steps", str(warm + 20), "--checkpoint_every", "10"], root / "compile")
    total = warm + args.steps
    print(f"A: {args.steps} online steps, a checkpoint every {args.every} ...", file=sys.stderr)
    a = _run(base + ["--online.steps", str(total), "--checkpoint_every", str(args.every)], root / "a")
    print(f"B: {args.steps} online steps, no mid-stage checkpoint ...", file=sys.stderr)
    b = _run(base + ["--online.steps", str(total), "--checkpoint_every", str(10**9)], root / "b")
    cfg = a.pop("cfg")
    b.pop("cfg")
    n = len(a["ckpt_times"])
    step_s = b["loop_s"] / args.steps
    ckpt_s = sum(a["ckpt_times"]) / max(n, 1)
    window = every_default * step_s
    row_bytes = a["buffer_bytes"] / max(warm + args.steps, 1)
    res = {
        "task": args.task, "profile": "quick", "checkpoint_every_default": every_default,
        "online_steps_measured": args.steps, "checkpoints_in_a": n, "step_s": step_s, "ckpt_s": ckpt_s,
        "ckpt_s_max": max(a["ckpt_times"], default=0.0),
        "ratio": ckpt_s / window,
        "ratio_ab": ((a["loop_s"] - b["loop_s"]) / max(n, 1)) / window,
        "loop_s_a": a["loop_s"], "loop_s_b": b["loop_s"], "ckpt_mb": a["ckpt_bytes"] / 2**20,
        "buffer_mb": a["buffer_bytes"] / 2**20,
        "buffer_mb_at_end": row_bytes * preset.online.steps / 2**20,
        "network": {"critics": cfg.online.sac.num_critics, "critic_hidden": list(cfg.online.sac.critic_hidden_dims),
                    "actor_hidden": list(cfg.online.sac.actor_hidden_dims), "utd": cfg.online.utd,
                    "batch": cfg.online.batch_size},
        "cpu_count": os.cpu_count(), "load_avg": os.getloadavg(),
    }
    print(json.dumps(res, indent=2))
    print(f"\n{args.task} quick: one checkpoint {ckpt_s:.3f} s (max {res['ckpt_s_max']:.3f} s, {res['ckpt_mb']:.1f} MB); "
          f"online loop {step_s * 1e3:.2f} ms/step -> {every_default} steps {window:.1f} s; checkpoints cost "
          f"{100 * res['ratio']:.2f} % of the online loop (A-B difference: {100 * res['ratio_ab']:.2f} %)")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Success of the pre-trained policy along offline pre-training: how many steps a task needs.

    python benchmarks/pretrain_success.py --task pointmaze-medium --steps 30000 --seed 1
    python benchmarks/pretrain_success.py --task pointmaze-large --steps 30000 --set cql_n_actions=5 --batch 256

Pre-trains the quick profile's agent for ``--pretrain`` (Cal-QL by default) on the task's data
and evaluates the deterministic policy (the run's evaluation: ``eval.episodes`` episodes from
the evaluation seeds) every ``--every`` steps, printing success, return, the mean Q on the
batch's data actions and the wall time per step (all of it, and the training alone: without the
evaluations and the first call, which compiles). This is how the quick profile's pre-training
budget on pointmaze was chosen (docs/results/pretraining.md). It uses the pipeline's own pieces (the
preset, the data, the agent, the population's batched calls) with a population of one, and the
pipeline's JAX settings (``setup_jax``: one CPU device per core, over which a population is
split): with ``--seeds``, the members' numbers are then the ones a ``botorl run`` of those seeds
computes, bit for bit. On another device count they are other draws from the same distribution
(the split changes XLA's float rounding, and training amplifies it; docs/results/pretraining.md, t6).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import jax
import numpy as np

from botorl.configs.presets import make_preset
from botorl.configs.resolve import resolve
from botorl.envs.registry import get_task
from botorl.agents import population as P
from botorl.pipeline.evaluation import make_eval_envs, run_episodes
from botorl.configs.members import parse_seeds
from botorl.jaxsetup import setup_jax
from botorl.pipeline.runner import load_offline, transform_dataset
from botorl.pipeline.stages import make_pretrain_agent


def _set(obj, path: str, value: str):
    """``obj`` with the field at dotted ``path`` set from the string ``value``, converted to the
    field's current type (a tuple from comma-separated ints, a bool from true/false)."""
    head, _, rest = path.partition(".")
    if rest:
        return replace(obj, **{head: _set(getattr(obj, head), rest, value)})
    old = getattr(obj, head)
    if isinstance(old, bool):
        new = value.lower() in ("1", "true", "yes")
    elif isinstance(old, tuple):
        new = tuple(int(v) for v in value.split(","))
    elif old is None:
        new = None if value.lower() == "none" else float(value)
    else:
        new = type(old)(value)
    return replace(obj, **{head: new})


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="pointmaze-medium")
    p.add_argument("--pretrain", default="calql", choices=["calql", "cql", "iql"])
    p.add_argument("--steps", type=int, default=30_000)
    p.add_argument("--every", type=int, default=5_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", default=None, metavar="A-B|A,B,..",
                   help="several seeds as one population, with the pipeline's batch streams ([seed, 1]), so the "
                        "policy at --steps is the one `botorl run` evaluates at online step 0")
    p.add_argument("--batch", type=int, default=None, help="offline batch size (default: the preset's)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="a CQLConfig field, e.g. cql_n_actions=5 or cql_weight=1.0, or a dotted RunConfig path, "
                        "e.g. network.critic_hidden_dims=128,128 (repeatable)")
    p.add_argument("--profile", default="quick", help="the preset the probe starts from")
    args = p.parse_args(argv)
    setup_jax()  # before the first array: the device split `botorl run` uses

    cfg = make_preset(args.task, args.profile, "wsrl", args.pretrain)
    for item in args.set:
        path, _, value = item.partition("=")
        cfg = _set(cfg, path if "." in path else f"offline.cql.{path}", value)
    offline = replace(cfg.offline, steps=args.steps, batch_size=args.batch or cfg.offline.batch_size)
    cfg = resolve(replace(cfg, seed=args.seed, offline=offline, progress=False))
    spec = get_task(args.task)
    d = transform_dataset(cfg, spec, load_offline(cfg, spec))
    if args.seeds is None:
        seeds = [args.seed]
        # batches from default_rng(seed), not the pipeline's stream ([seed, 1]): the first single-seed probe
        # table (git history) was measured so; the policy at a step is therefore not the one `botorl run` evaluates at 0
        rngs = [np.random.default_rng(args.seed)]
    else:
        seeds = parse_seeds(args.seeds)
        rngs = [np.random.default_rng([s, 1]) for s in seeds]
    agents = P.stack([make_pretrain_agent(cfg, d.obs_dim, d.action_dim, s) for s in seeds])
    envs = [make_eval_envs(spec, cfg.eval) for _ in seeds]
    print(f"{args.task} {args.pretrain} seeds {seeds}: {len(d.observations)} rows, batch {offline.batch_size}, "
          f"cql_n_actions {cfg.offline.cql.cql_n_actions}, {cfg.network.num_critics} critics "
          f"{cfg.network.critic_hidden_dims} LN {cfg.network.layer_norm}, lagrange {cfg.offline.cql.cql_lagrange}, "
          f"max-target {cfg.offline.cql.max_target_backup}", flush=True)
    K, step, t0 = 50, 0, time.perf_counter()
    eval_s = first_call_s = 0.0  # evaluations and the first call (XLA's compile), kept out of "train ms/step"
    while step < args.steps:
        agents, metrics = P.update_many(agents, d.sample_members(rngs, offline.batch_size, K))
        step += K
        if step == K:
            jax.block_until_ready(metrics)
            first_call_s = time.perf_counter() - t0
        if step % args.every == 0 or step >= args.steps:
            jax.block_until_ready(metrics)
            train_s = time.perf_counter() - t0
            t_eval = time.perf_counter()
            sts = run_episodes(lambda o: P.eval_actions(agents, o), envs, episodes=cfg.eval.episodes,
                               success_mode=spec.success_mode, seeds=[100_000 + 1000 * s for s in seeds],
                               max_steps=spec.max_episode_steps)
            succ = np.array([st.success for st in sts])
            q = float(np.mean(np.asarray(metrics["q_data"]))) if "q_data" in metrics else float("nan")
            per = " ".join(f"{x:.2f}" for x in succ) if len(seeds) > 1 else ""
            train_only = (train_s - eval_s - first_call_s) / max(step - K, 1)
            eval_s += time.perf_counter() - t_eval
            print(f"step {step:>7}  success {succ.mean():.2f}  {per}  return {np.mean([st.episode_return for st in sts]):7.2f}"
                  f"  q_data {q:8.1f}  {1000 * train_s / step:.2f} ms/step  (train {1000 * train_only:.2f} ms/step "
                  f"after the first call's {first_call_s:.0f} s; evaluations {eval_s:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

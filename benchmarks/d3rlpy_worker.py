"""Times d3rlpy updates; runs with the d3rlpy virtual environment's python, not botorl's.

d3rlpy 2.8 pins gymnasium 1.0 and needs PyTorch, neither of which botorl may depend on,
so ``against_d3rlpy.py`` runs this file as a subprocess in its own venv. This file imports nothing from botorl, and torch /
d3rlpy only inside the functions that need them, so botorl's tests can check its argument
parsing without either installed.

Two modes:

- one shot: ``python d3rlpy_worker.py --algo calql --n-critics 2 ...`` builds one algorithm,
  times it ``--repeats`` times and prints one JSON object on stdout;
- ``--serve``: reads one JSON request per line on stdin and answers one JSON line each, so
  the parent can interleave d3rlpy and botorl measurements without paying torch's import
  per measurement. Requests: ``{"cmd": "setup", "name": ..., "spec": {<the one-shot
  options as keys>}}``, ``{"cmd": "time", "name": ..., "min_time": s}``, ``{"cmd": "quit"}``.

What one "update" is here (the parent matches botorl's updates to these):

- ``calql``, ``cql``, ``sac``, ``iql``: ``impl.update(batch, step)``, d3rlpy's own training
  step (critic + actor + temperature [+ CQL alpha] + Polyak; IQL: Q + V + actor + Polyak),
  on a fixed ``TorchMiniBatch`` already on the CPU. ``algo.update(TransitionMiniBatch)``
  would add numpy->torch conversion and a Python loop over transitions for Cal-QL's
  returns-to-go, which botorl's jitted update does not pay either.
- ``sac_utd``: WSRL's online step composed from d3rlpy's parts (d3rlpy has no UTD option):
  ``utd`` x (``update_critic`` on its own batch + ``update_critic_target``), then one
  ``update_actor`` (which includes the temperature step) on the ``utd * batch`` rows.
- ``sac_critic``: ``update_critic`` + ``update_critic_target`` only. d3rlpy has no BOTO;
  this is the nearest step (a SAC critic step without the action noise and penalty).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

ALGOS = ("calql", "cql", "iql", "sac", "sac_utd", "sac_critic")


def _int_list(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}")
    if not values or min(values) <= 0:
        raise argparse.ArgumentTypeError(f"expected positive layer widths, got {text!r}")
    return values


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="d3rlpy_worker", description=__doc__.split("\n")[0])
    p.add_argument("--serve", action="store_true", help="answer JSON requests on stdin")
    p.add_argument("--algo", choices=ALGOS, default="sac")
    p.add_argument("--n-critics", type=int, default=2)
    p.add_argument("--critic-hidden", type=_int_list, default=[256, 256])
    p.add_argument("--actor-hidden", type=_int_list, default=[256, 256])
    p.add_argument("--value-hidden", type=_int_list, default=None, help="IQL V network (default: critic's)")
    p.add_argument("--layer-norm", type=int, choices=(0, 1), default=1, help="LayerNorm after hidden layers")
    p.add_argument("--obs-dim", type=int, default=29)
    p.add_argument("--action-dim", type=int, default=8)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--n-action-samples", type=int, default=10)
    p.add_argument("--utd", type=int, default=4)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: all cores)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--min-time", type=float, default=1.0, help="seconds per repeat")
    p.add_argument("--seed", type=int, default=0)
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    args = build_parser().parse_args(argv)
    for name in ("n_critics", "obs_dim", "action_dim", "batch", "utd", "repeats"):
        if getattr(args, name) <= 0:
            build_parser().error(f"--{name.replace('_', '-')} must be positive")
    if args.n_action_samples <= 0:
        build_parser().error("--n-action-samples must be positive")
    return args


def spec_to_argv(spec: dict[str, Any]) -> list[str]:
    """The one-shot command line for a spec dict (keys as the options, underscores)."""
    argv: list[str] = []
    for key, value in spec.items():
        if value is None:
            continue
        if isinstance(value, (list, tuple)):
            value = ",".join(str(v) for v in value)
        elif isinstance(value, bool):
            value = int(value)
        argv += [f"--{key.replace('_', '-')}", str(value)]
    return argv


# --------------------------------------------------------------------------- torch side


class Workload:
    """One d3rlpy algorithm built for fixed shapes, and a callable doing one update."""

    def __init__(self, args: argparse.Namespace):
        import numpy as np
        import torch
        import d3rlpy
        from d3rlpy.models.encoders import VectorEncoderFactory
        from d3rlpy.torch_utility import TorchMiniBatch

        if args.threads > 0:
            torch.set_num_threads(args.threads)
        torch.manual_seed(args.seed)
        self.args = args
        enc = lambda hidden: VectorEncoderFactory(hidden_units=list(hidden), use_layer_norm=bool(args.layer_norm))
        common = dict(
            batch_size=args.batch,
            actor_encoder_factory=enc(args.actor_hidden),
            critic_encoder_factory=enc(args.critic_hidden),
            n_critics=args.n_critics,
        )
        algo = args.algo
        if algo in ("calql", "cql"):
            cls = d3rlpy.algos.CalQLConfig if algo == "calql" else d3rlpy.algos.CQLConfig
            # Fixed CQL weight (no Lagrange step): the adroit/kitchen setting and botorl's default.
            config = cls(n_action_samples=args.n_action_samples, max_q_backup=True,
                         alpha_learning_rate=0.0, conservative_weight=1.0, **common)
        elif algo == "iql":
            config = d3rlpy.algos.IQLConfig(
                value_encoder_factory=enc(args.value_hidden or args.critic_hidden), **common)
        else:
            config = d3rlpy.algos.SACConfig(**common)
        self.algo = config.create(device="cpu:0")
        self.algo.create_impl((args.obs_dim,), args.action_dim)
        self.impl = self.algo.impl
        self.step = 0
        self.last_cpu_rate = float("nan")

        rng = np.random.default_rng(args.seed)

        def batch(rows: int) -> Any:
            t = lambda *shape: torch.as_tensor(rng.uniform(-1, 1, shape).astype(np.float32))
            return TorchMiniBatch(
                observations=t(rows, args.obs_dim), actions=t(rows, args.action_dim) * 0.99,
                rewards=t(rows, 1), next_observations=t(rows, args.obs_dim),
                next_actions=t(rows, args.action_dim) * 0.99, returns_to_go=t(rows, 1),
                terminals=torch.zeros(rows, 1), intervals=torch.ones(rows, 1), device="cpu:0")

        self.batches = [batch(args.batch) for _ in range(args.utd)]
        self.big_batch = batch(args.batch * args.utd)

    def update(self) -> None:
        impl, algo = self.impl, self.args.algo
        if algo == "sac_utd":
            impl.modules.set_train()
            for b in self.batches:
                impl.update_critic(b)
                impl.update_critic_target()
            impl.update_actor(self.big_batch)
        elif algo == "sac_critic":
            impl.modules.set_train()
            impl.update_critic(self.batches[0])
            impl.update_critic_target()
        else:
            impl.update(self.batches[0], self.step)
        self.step += 1

    def time(self, min_time: float) -> float:
        """Updates per second over at least ``min_time`` seconds (after warm-up calls).

        The first calls of a fresh model are slow (allocator, thread pool): warm up for
        a quarter of ``min_time`` and at least two calls before the clock starts.
        """
        t0, k = time.perf_counter(), 0
        while k < 2 or time.perf_counter() - t0 < min_time / 4:
            self.update()
            k += 1
        n, t0, c0 = 0, time.perf_counter(), time.process_time()
        while True:
            self.update()
            n += 1
            elapsed = time.perf_counter() - t0
            if elapsed >= min_time and n >= 2:
                self.last_cpu_rate = n / max(time.process_time() - c0, 1e-9)
                return n / elapsed


def _versions() -> dict[str, str]:
    import torch
    import d3rlpy

    return {"d3rlpy": d3rlpy.__version__, "torch": torch.__version__, "torch_threads": str(torch.get_num_threads())}


def serve(stdin: Any = None, stdout: Any = None) -> int:
    stdin, stdout = stdin or sys.stdin, stdout or sys.stdout
    workloads: dict[str, Workload] = {}

    def reply(obj: dict[str, Any]) -> None:
        stdout.write(json.dumps(obj) + "\n")
        stdout.flush()

    reply({"ready": True, **_versions()})
    for line in stdin:
        if not line.strip():
            continue
        try:
            req = json.loads(line)
            cmd = req.get("cmd")
            if cmd == "quit":
                reply({"ok": True})
                return 0
            if cmd == "setup":
                workloads[req["name"]] = Workload(parse_args(spec_to_argv(req["spec"])))
                reply({"ok": True, "name": req["name"]})
            elif cmd == "time":
                rate = workloads[req["name"]].time(float(req.get("min_time", 1.0)))
                reply({"ok": True, "name": req["name"], "updates_per_s": rate,
                       "updates_per_cpu_s": workloads[req["name"]].last_cpu_rate})
            else:
                reply({"ok": False, "error": f"unknown cmd {cmd!r}"})
        except SystemExit as err:  # argparse error inside a setup request
            reply({"ok": False, "error": f"bad spec ({err})"})
        except Exception as err:  # report, keep serving: the parent decides
            reply({"ok": False, "error": f"{type(err).__name__}: {err}"})
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.serve:
        return serve()
    w = Workload(args)
    rates = [w.time(args.min_time) for _ in range(args.repeats)]
    rates_sorted = sorted(rates)
    print(json.dumps({"algo": args.algo, "updates_per_s": rates,
                      "median": rates_sorted[len(rates) // 2], **_versions()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

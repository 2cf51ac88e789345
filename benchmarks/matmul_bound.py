"""How fast could each benchmarked update be if everything but its matmuls were free?

    python benchmarks/matmul_bound.py [--only calql sac10 ...] [--d3rlpy-json PATH] [--json out.json]

For each workload of ``botorl bench`` this traces one update, collects every ``dot_general``
of the traced program (forward and backward, a ``scan`` body counted ``length`` times), and
times each distinct matmul alone as a jitted function on this machine. Their sum is the
update's *matmul time*: a floor for any implementation that does the same matmuls with
XLA's CPU kernels, since everything else in the update (elementwise ops, reductions, Adam,
sampling) only adds to it. ``botorl % of bound`` says how close the whole update is to
that floor.

With ``--d3rlpy-json`` (a ``benchmarks/against_d3rlpy.py --json`` result from this
machine) it also prints the ratio to d3rlpy that the floor allows:
``bound ratio = ratio x (botorl ms / matmul ms)``, the botorl/d3rlpy ratio of an update
that spent no time outside its matmuls. Below 2, "2x d3rlpy" needs fewer FLOPs (or faster
matmul kernels than XLA's), not less overhead.
"""

from __future__ import annotations

import argparse
import collections
import json
import statistics
import sys
import time


def _dots(jaxpr, mult: int, out: collections.Counter) -> None:
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "dot_general":
            lhs, rhs = (v.aval for v in eqn.invars[:2])
            key = (tuple(lhs.shape), str(lhs.dtype), tuple(rhs.shape), str(rhs.dtype),
                   repr(eqn.params["dimension_numbers"]), repr(eqn.params.get("precision")),
                   repr(eqn.params.get("preferred_element_type")))
            out[key] += mult
            out_params = out.setdefault("_params", {})
            out_params[key] = eqn.params
        elif name == "scan":
            _dots(eqn.params["jaxpr"].jaxpr, mult * eqn.params["length"], out)
        elif name == "while":
            _dots(eqn.params["body_jaxpr"].jaxpr, mult, out)
        else:
            for value in eqn.params.values():
                for item in value if isinstance(value, (tuple, list)) else (value,):
                    if hasattr(item, "eqns"):
                        _dots(item, mult, out)
                    elif hasattr(item, "jaxpr") and hasattr(item.jaxpr, "eqns"):
                        _dots(item.jaxpr, mult, out)


def _time(fn, min_time: float = 0.2, rounds: int = 5) -> float:
    import jax

    jax.block_until_ready(fn())
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    n = max(1, int(min_time / max(time.perf_counter() - t0, 1e-6)))
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(n):
            out = fn()
        jax.block_until_ready(out)
        best = min(best, (time.perf_counter() - t0) / n)
    return best


def collect_dots(fn, *args) -> tuple[collections.Counter, dict]:
    """The distinct ``dot_general``s of one traced call and how often each runs."""
    import jax

    found: collections.Counter = collections.Counter()
    _dots(jax.make_jaxpr(fn)(*args).jaxpr, 1, found)
    params = found.pop("_params", {})
    return found, params


def matmul_seconds(flop_fn, flop_args) -> tuple[float, int]:
    """(seconds of one call's matmuls, each timed alone, best of rounds; distinct matmuls)."""
    import jax

    found, params = collect_dots(flop_fn, *flop_args)
    total = 0.0
    key = jax.random.PRNGKey(0)
    for k, count in found.items():
        lshape, ldt, rshape, rdt, *_ = k
        p = params[k]
        lhs = jax.random.normal(key, lshape).astype(ldt)
        rhs = jax.random.normal(jax.random.fold_in(key, 1), rshape).astype(rdt)
        dot = jax.jit(lambda a, b, p=p: jax.lax.dot_general(
            a, b, p["dimension_numbers"], precision=p.get("precision"),
            preferred_element_type=p.get("preferred_element_type")))
        total += count * _time(lambda: dot(lhs, rhs))
    return total, len(found)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--only", nargs="*", default=None, help="workload names (default: all)")
    p.add_argument("--d3rlpy-json", default=None, help="a `benchmarks/against_d3rlpy.py --json` result")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)

    from botorl.jaxsetup import setup_jax

    setup_jax()
    from botorl.benchmarks import workloads as wl
    from botorl.benchmarks.flops import matmul_peak_gflops

    d3 = {}
    if args.d3rlpy_json:
        with open(args.d3rlpy_json) as f:
            d3 = json.load(f).get("updates", {})
    names = args.only or list(wl.WORKLOADS)
    rows = {}
    peak = matmul_peak_gflops()
    print(f"matmul peak (1024^2): {peak:.0f} GFLOP/s", file=sys.stderr)
    for name in names:
        b = wl.build(wl.WORKLOADS[name])
        k = b.updates_per_call
        mm_s, distinct = matmul_seconds(b.flop_fn, b.flop_args)
        calls = max(1, int(1.0 / max(_time(lambda: b.step(1), 0.0, 1), 1e-6)))
        rates = []
        for _ in range(3):
            t0 = time.perf_counter()
            b.step(calls)
            rates.append(calls * k / (time.perf_counter() - t0))
        ups = statistics.median(rates)
        row = {"botorl_ms": 1e3 / ups, "matmul_ms": 1e3 * mm_s / k, "distinct_matmuls": distinct}
        row["botorl_fraction_of_bound"] = row["matmul_ms"] / row["botorl_ms"]
        ref = d3.get(name, {})
        if ref.get("ratio"):
            row["measured_ratio"] = ref["ratio"]
            row["bound_ratio"] = ref["ratio"] / row["botorl_fraction_of_bound"]
        rows[name] = row
        print(f"{name}: done", file=sys.stderr, flush=True)

    print(f"{'update':16s} {'botorl ms':>10s} {'matmul ms':>10s} {'% of bound':>10s} {'ratio':>6s} {'bound ratio':>11s}")
    for name, r in rows.items():
        ratio = f"{r['measured_ratio']:6.2f}" if "measured_ratio" in r else f"{'-':>6s}"
        bound = f"{r['bound_ratio']:11.2f}" if "bound_ratio" in r else f"{'-':>11s}"
        print(f"{name:16s} {r['botorl_ms']:10.2f} {r['matmul_ms']:10.2f} {100 * r['botorl_fraction_of_bound']:10.1f} {ratio} {bound}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"peak_gflops": peak, "d3rlpy_json": args.d3rlpy_json, "updates": rows}, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""FLOP counts of one call of a jitted function, and the fp32 matmul peak they are compared with.

``jaxpr_flops`` counts the traced program: ``dot_general`` costs ``2 * prod(batch) * M * N * K``,
an elementwise or reduction op one FLOP per element (transcendentals none, as XLA counts them
apart), a ``scan`` body ``length`` times, the dearer branch of a ``cond``; the backward pass is in
the trace. ``xla_flops`` (XLA's cost analysis) counts a ``while`` body once, so it undercounts
scans; the benchmark keeps it as a cross-check (docs/performance.md).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

# Elementwise arithmetic (one FLOP per output element).
_ELEMENTWISE = {
    "add", "sub", "mul", "div", "neg", "max", "min", "abs", "sign", "square", "rem",
    "integer_pow", "select_n", "clamp", "floor", "ceil", "round", "nextafter",
    "eq", "ne", "lt", "le", "gt", "ge", "and", "or", "not", "xor", "add_any",
}
_REDUCE = {"reduce_sum", "reduce_max", "reduce_min", "reduce_prod", "argmax", "argmin",
           "cumsum", "cummax", "cumlogsumexp", "reduce_and", "reduce_or"}


@dataclass
class FlopCount:
    flops: float = 0.0  # matmul + elementwise + reductions
    matmul_flops: float = 0.0


def _size(aval: Any) -> int:
    return math.prod(getattr(aval, "shape", None) or ())


def _dot_flops(eqn: Any) -> float:
    lhs, rhs = (v.aval for v in eqn.invars[:2])
    (lc, rc), (lb, _rb) = eqn.params["dimension_numbers"]
    batch = math.prod(lhs.shape[d] for d in lb)
    contract = math.prod(lhs.shape[d] for d in lc)
    m = math.prod(s for d, s in enumerate(lhs.shape) if d not in lc and d not in lb)
    n = math.prod(s for d, s in enumerate(rhs.shape) if d not in rc and d not in _rb)
    return 2.0 * batch * m * n * contract


def _count_jaxpr(jaxpr: Any) -> np.ndarray:
    """(FLOPs, matmul FLOPs) of a traced program."""
    total = np.zeros(2)
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "dot_general":
            total += _dot_flops(eqn)
        elif name == "scan":
            total += _count_jaxpr(eqn.params["jaxpr"].jaxpr) * eqn.params["length"]
        elif name == "cond":
            total += max((_count_jaxpr(b.jaxpr) for b in eqn.params["branches"]), key=lambda c: c[0])
        elif name in _ELEMENTWISE:
            total[0] += _size(eqn.outvars[0].aval)
        elif name in _REDUCE:
            total[0] += _size(eqn.invars[0].aval)
        else:  # a call (pjit, custom_jvp, remat, ...) counts its body, a while its body and cond
            # once (as XLA does: the trip count is unknown when tracing); any other primitive is free
            for value in eqn.params.values():
                for item in value if isinstance(value, (tuple, list)) else (value,):
                    sub = item if hasattr(item, "eqns") else getattr(item, "jaxpr", None)  # open or closed jaxpr
                    if hasattr(sub, "eqns"):
                        total += _count_jaxpr(sub)
    return total


def jaxpr_flops(fn: Callable, *args: Any, **kwargs: Any) -> FlopCount:
    """FLOPs of one call of ``fn(*args)`` counted on its traced program (see module doc)."""
    return FlopCount(*map(float, _count_jaxpr(jax.make_jaxpr(fn)(*args, **kwargs).jaxpr)))


def xla_flops(fn: Callable, *args: Any, **kwargs: Any) -> float:
    """FLOPs of one call as XLA's cost analysis of the compiled program gives them."""
    cost = jax.jit(fn).lower(*args, **kwargs).compile().cost_analysis()
    return float((cost or {}).get("flops", float("nan")))


def matmul_peak_gflops(n: int = 1024, repeats: int = 7, calls: int = 4) -> float:
    """Best-of-repeats fp32 GFLOP/s of a jitted ``(n, n) @ (n, n)`` on the default device, with
    the threads the updates use: an update's ``gflops / peak`` is its share of the machine's best."""
    key = jax.random.PRNGKey(0)
    a = jax.random.normal(key, (n, n), jnp.float32)
    b = jax.random.normal(jax.random.fold_in(key, 1), (n, n), jnp.float32)
    mm = jax.jit(lambda x, y: x @ y)
    mm(a, b).block_until_ready()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            out = mm(a, b)
        out.block_until_ready()
        best = min(best, (time.perf_counter() - t0) / calls)
    return 2.0 * n**3 / best / 1e9

"""The FLOP counter on programs whose count is known by hand."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from botorl.benchmarks.flops import jaxpr_flops, xla_flops


def test_matmul_count_is_2mnk():
    a = np.ones((64, 32), np.float32)
    b = np.ones((32, 16), np.float32)
    want = 2 * 64 * 32 * 16
    count = jaxpr_flops(lambda x, y: x @ y, a, b)
    assert count.flops == want and count.matmul_flops == want
    # XLA's own count of the same compiled matmul agrees exactly.
    assert xla_flops(lambda x, y: x @ y, a, b) == want


def test_batched_dot_and_scan_trip_count():
    # (E, B, K) x (E, K, N) batched over E: 2 E B K N; under a scan of length 3: three times.
    x = np.ones((4, 8, 16), np.float32)
    w = np.ones((4, 16, 5), np.float32)
    one = 2 * 4 * 8 * 16 * 5
    assert jaxpr_flops(lambda x, w: jnp.einsum("ebk,ekn->ebn", x, w), x, w).matmul_flops == one

    def scanned(x, w):
        def body(c, _):
            return c, jnp.einsum("ebk,ekn->ebn", c, w)
        return jax.lax.scan(body, x, None, length=3)[1]

    assert jaxpr_flops(scanned, x, w).matmul_flops == 3 * one


def test_gradient_of_a_dense_layer_counts_backward_pass():
    # y = x @ w, loss = sum(y): grad w.r.t. w is x^T @ ones -> one more (K, B) x (B, N) matmul.
    x = np.ones((8, 16), np.float32)
    w = np.ones((16, 4), np.float32)
    count = jaxpr_flops(jax.grad(lambda w, x: jnp.sum(x @ w)), w, x)
    assert count.matmul_flops == 2 * (2 * 8 * 16 * 4)


def test_matmul_bound_finds_every_matmul_of_a_scanned_gradient():
    # benchmarks/matmul_bound.py: grad of sum(x @ w) w.r.t. w has two matmuls (forward and
    # x^T @ ones); under a scan of length 3 each runs 3 times; their time alone is positive.
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "matmul_bound.py"
    spec = importlib.util.spec_from_file_location("matmul_bound", path)
    mb = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mb)
    x = np.ones((3, 8, 16), np.float32)
    w = np.ones((16, 4), np.float32)

    def scanned_grad(x, w):
        def body(acc, xi):
            return acc + jax.grad(lambda w: jnp.sum(xi @ w))(w), None
        return jax.lax.scan(body, jnp.zeros_like(w), x)[0]

    found, _ = mb.collect_dots(scanned_grad, x, w)
    assert sorted(found.values()) == [3, 3]
    # forward (8, 16) x (16, 4); backward contracts the 8 rows of the cotangent with x's
    assert {(k[0], k[2]) for k in found} == {((8, 16), (16, 4)), ((8, 4), (8, 16))}
    seconds, distinct = mb.matmul_seconds(scanned_grad, (x, w))
    assert distinct == 2 and seconds > 0

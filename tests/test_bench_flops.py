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

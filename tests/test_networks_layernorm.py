"""botorl's LayerNorm (matmul reductions, hand-written backward) against flax's."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from botorl.networks.common import MLP, LayerNorm, standardize


def _inputs(shift=0.0):
    x = jax.random.normal(jax.random.PRNGKey(0), (3, 37, 16)) * 2.0 + shift
    params = {"scale": jax.random.normal(jax.random.PRNGKey(1), (16,)), "bias": jax.random.normal(jax.random.PRNGKey(2), (16,))}
    w = jax.random.normal(jax.random.PRNGKey(3), (3, 37, 16))
    return x, params, w


def test_forward_and_gradients_match_flax():
    x, params, w = _inputs()

    def loss(module):
        def f(p, x):
            return jnp.sum(jnp.tanh(module.apply({"params": p}, x)) * w)
        return jax.value_and_grad(f, argnums=(0, 1))(params, x)

    (v_ours, (gp_ours, gx_ours)) = loss(LayerNorm())
    (v_ref, (gp_ref, gx_ref)) = loss(nn.LayerNorm())
    np.testing.assert_allclose(v_ours, v_ref, rtol=1e-5)
    np.testing.assert_allclose(gx_ours, gx_ref, atol=2e-5)
    for k in ("scale", "bias"):
        np.testing.assert_allclose(gp_ours[k], gp_ref[k], atol=2e-4)


def test_gradient_matches_finite_differences_in_float64():
    with jax.enable_x64(True):
        x = jax.random.normal(jax.random.PRNGKey(4), (5, 8), dtype=jnp.float64)
        w = jax.random.normal(jax.random.PRNGKey(5), (5, 8), dtype=jnp.float64)
        f = lambda x: jnp.sum(jnp.sin(standardize(x)) * w)  # noqa: E731
        g = jax.grad(f)(x)
        d = jax.random.normal(jax.random.PRNGKey(6), (5, 8), dtype=jnp.float64)
        h = 1e-6
        fd = (f(x + h * d) - f(x - h * d)) / (2 * h)
        np.testing.assert_allclose(jnp.sum(g * d), fd, rtol=1e-6)


def test_large_mean_stays_accurate():
    # Two-pass variance: a mean 1000x the spread does not cancel (flax's E[x^2] - E[x]^2 does).
    x, _, _ = _inputs(shift=1000.0)
    x64 = np.asarray(x, np.float64)
    want = (x64 - x64.mean(-1, keepdims=True)) / np.sqrt(x64.var(-1, keepdims=True) + 1e-6)
    assert np.max(np.abs(np.asarray(standardize(x)) - want)) < 1e-3


def test_parameter_tree_is_flaxs():
    # Checkpoints written with flax's LayerNorm load into the same tree.
    x = jnp.ones((2, 5))
    ours = MLP((8, 8), use_layer_norm=True).init(jax.random.PRNGKey(0), x)
    ref = jax.tree_util.tree_structure({"params": {"Dense_0": {"kernel": 0, "bias": 0}, "LayerNorm_0": {"scale": 0, "bias": 0},
                                                   "Dense_1": {"kernel": 0, "bias": 0}, "LayerNorm_1": {"scale": 0, "bias": 0}}})
    assert jax.tree_util.tree_structure(ours) == ref

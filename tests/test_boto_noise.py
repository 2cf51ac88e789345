"""Statistical tests of the BOTO noise samplers against their definition (paper B.1).

Sample sizes and thresholds: 200,000 rows; proportions are checked to 5 standard errors
(~0.0025 at p = 0.05), KS tests need p > 1e-3, and each test also shows that a plausible wrong
sampler fails the same check (so the thresholds have power).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from botorl.boto.noise import (
    gaussian_noise,
    hybrid_noise,
    make_noise_fn,
    resolve_weight_fn,
)
from botorl.errors import ConfigError

N = 200_000


def expected_uniform_share(log_sigma: float, weight_fn="linear", n: int = 200_001) -> float:
    """E[w(t)] = (1 / |log sigma|) * integral_{log sigma}^0 w(e^lambda) d lambda: closed form for
    "linear" ((1 - sigma) / |log sigma|) and a constant p, Simpson's rule on ``n`` points for a callable."""
    if weight_fn == "linear":
        return float(-math.expm1(log_sigma) / -log_sigma)
    if isinstance(weight_fn, (int, float)):
        return float(weight_fn)
    from scipy.integrate import simpson

    lam = np.linspace(log_sigma, 0.0, n)
    vals = np.asarray(weight_fn(jnp.exp(jnp.asarray(lam))), dtype=np.float64)
    return float(simpson(vals, x=lam) / -log_sigma)


def _draw(log_sigma, weight_fn="linear", act_dim=2, clip=True, seed=0):
    actions = jnp.zeros((N, act_dim), jnp.float32)
    a_bar, info = jax.jit(lambda k: hybrid_noise(k, actions, log_sigma, weight_fn, clip=clip))(
        jax.random.PRNGKey(seed)
    )
    return np.asarray(a_bar), np.asarray(info["uniform"]), np.asarray(info["t"])


def _prop_ok(share, p):
    return abs(share - p) < 5 * np.sqrt(p * (1 - p) / N)


@pytest.mark.parametrize("log_sigma", [-20.0, -2.0])
def test_uniform_share_and_log_t_distribution(log_sigma):
    a_bar, uniform, t = _draw(log_sigma)
    expected = expected_uniform_share(log_sigma, "linear")
    # closed form (1 - sigma) / |log sigma| against quadrature of the same integral
    assert expected == pytest.approx(expected_uniform_share(log_sigma, lambda t: t), rel=1e-6)
    assert _prop_ok(uniform.mean(), expected), (uniform.mean(), expected)
    # log t ~ U(log sigma, 0)
    ks = stats.kstest(np.log(t), "uniform", args=(log_sigma, -log_sigma))
    assert ks.pvalue > 1e-3
    # power: t ~ U(sigma, 1) (uniform in t instead of in log t) is rejected
    wrong_t = np.random.default_rng(0).uniform(np.exp(log_sigma), 1.0, N)
    assert stats.kstest(np.log(wrong_t), "uniform", args=(log_sigma, -log_sigma)).pvalue < 1e-6
    # power: that wrong sampler's uniform share (w = t with t uniform) fails the share check too
    wrong_uniform = np.random.default_rng(1).uniform(size=N) < wrong_t
    assert not _prop_ok(wrong_uniform.mean(), expected)
    assert np.all(np.abs(a_bar) <= 1.0)


def test_uniform_probability_given_t_is_w_of_t():
    # P(uniform | t) = w(t) = t: checked per decile of t (log sigma = -2 gives t in [0.14, 1])
    _, uniform, t = _draw(-2.0, seed=1)
    edges = np.quantile(t, np.linspace(0, 1, 11))
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (t >= lo) & (t < hi)
        p = t[sel].mean()
        assert abs(uniform[sel].mean() - p) < 5 * np.sqrt(p * (1 - p) / sel.sum()) + 0.005
    # power: ignoring t (same overall share, drawn independently) is caught in the extreme deciles
    shuffled = np.random.default_rng(0).permutation(uniform)
    sel = t < edges[1]
    assert abs(shuffled[sel].mean() - t[sel].mean()) > 0.1


def test_component_shapes():
    # unclipped, centre 0: uniform rows are U(-1, 1) per coordinate; Gaussian rows are N(0, t^2)
    a_bar, uniform, t = _draw(-2.0, clip=False, seed=2)
    assert stats.kstest(a_bar[uniform, 0], "uniform", args=(-1.0, 2.0)).pvalue > 1e-3
    z = a_bar[~uniform] / t[~uniform, None]
    assert stats.kstest(z[:, 0], "norm").pvalue > 1e-3
    assert stats.kstest(z[:, 1], "norm").pvalue > 1e-3
    # one t per row shared by both dimensions: the two coordinates' |z| are independent, so the
    # ratio of the two standardised coordinates is standard Cauchy
    assert stats.kstest(z[:, 0] / z[:, 1], "cauchy").pvalue > 1e-3
    # power: standardising with a wrong scale (2 t) is rejected
    assert stats.kstest(z[:, 0] / 2, "norm").pvalue < 1e-6


def test_constant_weight_and_gaussian():
    _, uniform, _ = _draw(-20.0, weight_fn=0.2, seed=3)
    assert _prop_ok(uniform.mean(), 0.2)
    assert expected_uniform_share(-20.0, 0.2) == 0.2
    actions = jnp.full((N, 1), 0.5, jnp.float32)
    a_bar, info = gaussian_noise(jax.random.PRNGKey(4), actions, 0.25, clip=False)
    assert stats.kstest((np.asarray(a_bar)[:, 0] - 0.5) / 0.25, "norm").pvalue > 1e-3
    assert not np.asarray(info["uniform"]).any()
    a_bar, _ = gaussian_noise(jax.random.PRNGKey(4), actions, 0.25)
    assert float(a_bar.max()) == 1.0 and np.mean(np.asarray(a_bar) == 1.0) == pytest.approx(
        stats.norm.sf(2.0), abs=0.003
    )


def test_bad_settings_raise_config_error():
    with pytest.raises(ConfigError):
        resolve_weight_fn("quadratic")
    with pytest.raises(ConfigError):
        resolve_weight_fn(1.5)
    with pytest.raises(ConfigError):
        make_noise_fn("hybrid", log_sigma=0.5)
    with pytest.raises(ConfigError):
        make_noise_fn("laplace")
    with pytest.raises(ConfigError):
        make_noise_fn("gaussian", sigma=0.0)

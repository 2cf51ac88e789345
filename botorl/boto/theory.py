"""The exact alpha-NAMDP solution of a one-step problem and its Theorem 2 bounds (NumPy).

In a bandit (gamma = 0) with dataset rows (a_i, r_i), each of weight 1/N in p_D, and a noise
density q(a_bar | a), the minimiser of the BOTO loss is (paper Theorem 1, eq. 8)

    Q*(a_bar) = sum_i q(a_bar|a_i) (r_i - alpha ||a_i - a_bar||^2) / sum_i q(a_bar|a_i)

and Theorem 2 bounds it by

    min(0, -alpha) Rbar(a_bar) + min_i r_i  <=  Q*(a_bar)  <=  max(0, -alpha) Rbar(a_bar) + max_i r_i,
    Rbar(a_bar) = sum_i q(a_bar|a_i) ||a_i - a_bar||^2 / sum_i q(a_bar|a_i).

(the inf/sup over the support of p_D become min/max over the rows). Posterior weights are
computed in log space so that points far from the data do not underflow.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.special import softmax


def gaussian_log_density(sigma: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``(a_bar (M, A), a (N, A)) -> log q(a_bar_m | a_n)`` of shape (M, N) for N(a, sigma^2 I)."""

    def logq(a_bar: np.ndarray, a: np.ndarray) -> np.ndarray:
        d2 = ((a_bar[:, None, :] - a[None, :, :]) ** 2).sum(-1)
        dim = a.shape[-1]
        return -0.5 * d2 / sigma**2 - dim * (np.log(sigma) + 0.5 * np.log(2 * np.pi))

    return logq


@dataclass
class ExactSolution:
    """Q* and the Theorem 2 bounds on a set of query actions."""

    q: np.ndarray
    lower: np.ndarray
    upper: np.ndarray


def namdp_exact(query: np.ndarray, actions: np.ndarray, rewards: np.ndarray, alpha: float,
                log_density: Callable[[np.ndarray, np.ndarray], np.ndarray], chunk: int = 512) -> ExactSolution:
    """Q*(a_bar) and its bounds at ``query`` (M, A) for the dataset (``actions`` (N, A), ``rewards`` (N,))."""
    query = np.atleast_2d(np.asarray(query, np.float64))
    actions = np.asarray(actions, np.float64).reshape(len(rewards), -1)
    rewards = np.asarray(rewards, np.float64)
    r_lo, r_hi = rewards.min(), rewards.max()
    rbar, rmean = [], []
    for start in range(0, len(query), chunk):
        qb = query[start : start + chunk]
        post = softmax(log_density(qb, actions), axis=-1)  # (m, N): log p_D(a_i) q(a_bar|a_i) + const, normalised
        d2 = ((qb[:, None, :] - actions[None, :, :]) ** 2).sum(-1)
        rbar.append((post * d2).sum(-1))
        rmean.append(post @ rewards)
    rbar_a, rmean_a = np.concatenate(rbar), np.concatenate(rmean)
    return ExactSolution(
        q=rmean_a - alpha * rbar_a,
        lower=min(0.0, -alpha) * rbar_a + r_lo,
        upper=max(0.0, -alpha) * rbar_a + r_hi,
    )

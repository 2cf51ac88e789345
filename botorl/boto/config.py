"""``BOTOConfig``: the settings of the BOTO phase (stage 2b of the pipeline). The bias
controller ``alpha`` is not one of them but each run's (``RunConfig.alpha``), so one phase trains
a population whose members have their own alphas. Fields left at ``None`` are taken from the
pre-trained agent's config, so BOTO bootstraps exactly like the agent it continues.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from botorl.agents.common import check_fields
from botorl.boto.noise import NOISE_KINDS, resolve_weight_fn
from botorl.errors import ConfigError


def check_alpha(alpha: Any, what: str = "alpha") -> None:
    """Raise ConfigError unless ``alpha`` is a number in [-1, 1] (or an array of them): the one
    check of BOTO's alpha, wherever it comes from (--alpha, --alphas, a sweep, BOTOConfig)."""
    try:
        arr = np.asarray(alpha, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} = {alpha!r} is not a number; give BOTO's alpha in [-1, 1], e.g. --alpha -0.5.") from None
    if arr.size == 0 or np.isnan(arr).any() or (arr < -1.0).any() or (arr > 1.0).any():
        raise ConfigError(
            f"{what} = {alpha!r} is outside [-1, 1]. alpha is BOTO's bias controller (paper section 4): > 0 "
            "conservative, < 0 optimistic, 1 is the NAMDP of Oh & Lee (2025); the paper's grid is [-1, 1] in steps "
            "of 0.1. Pass e.g. --alpha -0.5."
        )


@dataclass(frozen=True)
class BOTOConfig:
    """Settings of BOTO training; defaults are the paper's (Table 2, B.1) where it gives them.

    boto_steps: critic gradient steps (paper: 100k, 250k on kitchen). noise: "hybrid" (paper
    B.1), "gaussian" (``sigma``, the bandit figure 3) or "none" (a_bar = a: the re-fit control of
    the ablation study, BOTO's compute without its bound). log_sigma: the hybrid noise's lower end
    of log t (paper: -20; -30 on antmaze-large-diverse). weight_fn: the hybrid mixing weight
    (botorl.boto.noise). batch_size: rows per step from D_BOTO = D_offline u D_warmup. steps_per_call:
    steps fused into one jitted ``lax.scan`` (also ``run_boto``'s logging and callback period).
    num_min_critics, subsample_replace, discount, tau (Polyak rate): None -> the agent's own (an
    agent without a subset setting, IQL, uses all its critics). backup_entropy: subtract
    ``temperature * log pi(a~|s')`` in the target (the SAC sign); IQL has none.
    train_actor: also step the actor and temperature after every critic step (SAC family only;
    default False: Theorem 1 is stated for a fixed policy).
    """

    boto_steps: int = 100_000
    noise: str = "hybrid"
    log_sigma: float = -20.0
    sigma: float = 0.25
    weight_fn: str | float = "linear"
    clip: bool = True
    batch_size: int = 256
    steps_per_call: int = 1_000
    num_min_critics: int | None = None
    subsample_replace: bool | None = None
    backup_entropy: bool = True
    discount: float | None = None
    tau: float | None = None
    train_actor: bool = False

    def validate(self) -> None:
        check_fields(self, BOTO_CHECKS)
        resolve_weight_fn(self.weight_fn)


BOTO_CHECKS = (
    ("boto_steps", lambda c: c.boto_steps >= 0, "must be >= 0"),
    ("noise", lambda c: c.noise in NOISE_KINDS,
     'use "hybrid" (paper B.1), "gaussian", or "none" (the re-fit control: a_bar = a, no bound)'),
    ("log_sigma", lambda c: c.log_sigma < 0 and not math.isinf(c.log_sigma),
     "must be a finite negative number (paper: -20, or -30 on antmaze-large-diverse)"),
    ("sigma", lambda c: c.sigma > 0, "the Gaussian noise scale must be positive, e.g. 0.25"),
    ("batch_size", lambda c: c.batch_size >= 1, "must be >= 1"),
    ("steps_per_call", lambda c: c.steps_per_call >= 1, "must be >= 1"),
    ("num_min_critics", lambda c: c.num_min_critics is None or c.num_min_critics >= 1,
     "must be >= 1 or None (use the agent's setting)"),
    ("discount", lambda c: c.discount is None or 0.0 <= c.discount <= 1.0, "must be in [0, 1] or None"),
    ("tau", lambda c: c.tau is None or 0.0 < c.tau <= 1.0, "the Polyak rate must be in (0, 1] or None"),
)

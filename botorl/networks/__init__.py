"""Network building blocks shared by every agent (flax linen): the MLP, Q ensembles and V
(``common``), the tanh-Gaussian actor and its sampling helpers (``actor``), and the SAC entropy
``Temperature`` (NOT BOTO's ``alpha``), which CQL's ``LagrangeMultiplier`` is too."""

from __future__ import annotations

from botorl.networks.common import CriticEnsemble, LagrangeMultiplier, Temperature, ValueNetwork
from botorl.networks.actor import (
    TanhGaussianActor, sample_tanh_gaussian, tanh_gaussian_from_noise, tanh_gaussian_log_prob,
)

__all__ = [
    "CriticEnsemble", "ValueNetwork", "Temperature", "LagrangeMultiplier", "TanhGaussianActor", "sample_tanh_gaussian",
    "tanh_gaussian_from_noise", "tanh_gaussian_log_prob",
]

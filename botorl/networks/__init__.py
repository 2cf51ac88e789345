"""Network building blocks shared by every agent (flax linen, pure functions).

- ``MLP``: Dense layers, optional dropout and LayerNorm after each hidden layer (RLPD/WSRL
  put LayerNorm after every hidden layer of actor and critic; docs/methods.md).
- ``QNetwork`` / ``CriticEnsemble``: Q(s, a); the ensemble is an ``nn.vmap`` over N members,
  so every parameter has leading axis N and the output is (N, B).
- ``ValueNetwork``: V(s) for IQL.
- ``TanhGaussianActor``: returns ``(mean, log_std)`` of the pre-tanh Gaussian; the helpers
  ``sample_tanh_gaussian`` / ``tanh_gaussian_log_prob`` / ``tanh_gaussian_mode`` turn them into
  actions and log-probs with the tanh change-of-variables correction.
- ``Temperature``: the SAC entropy temperature ``exp(log_temp)``. It is NOT BOTO's ``alpha``.
"""

from __future__ import annotations

from botorl.networks.common import (
    MLP,
    CriticEnsemble,
    QNetwork,
    Temperature,
    ValueNetwork,
    default_init,
    subsample_ensemble,
)
from botorl.networks.actor import (
    TanhGaussianActor,
    sample_tanh_gaussian,
    tanh_gaussian_from_noise,
    tanh_gaussian_log_prob,
    tanh_gaussian_mode,
)

__all__ = [
    "MLP",
    "QNetwork",
    "CriticEnsemble",
    "ValueNetwork",
    "Temperature",
    "TanhGaussianActor",
    "sample_tanh_gaussian",
    "tanh_gaussian_from_noise",
    "tanh_gaussian_log_prob",
    "tanh_gaussian_mode",
    "default_init",
    "subsample_ensemble",
]

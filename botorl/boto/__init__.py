"""BOTO: bounding Q-function estimates before online fine-tuning (paper section 4).

- ``noise``: the hybrid and Gaussian action-noise samplers q_sigma(a_bar | a).
- ``objective``: the BOTO critic update on a SAC-family or IQL agent.
- ``phase``: ``BOTOConfig`` and ``run_boto`` (the stage between pre-training and fine-tuning).
- ``theory``: the exact alpha-NAMDP Q* of a one-step problem and the Theorem 2 bounds.
- ``bandit``: ``botorl bandit``, the paper's figures 2 and 3.
"""

from botorl.boto.config import BOTOConfig
from botorl.boto.noise import gaussian_noise, hybrid_noise
from botorl.boto.objective import boto_update, boto_update_many
from botorl.boto.phase import run_boto

__all__ = ["BOTOConfig", "run_boto", "boto_update", "boto_update_many", "hybrid_noise", "gaussian_noise"]

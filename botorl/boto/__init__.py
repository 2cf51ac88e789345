"""BOTO: bounding Q-function estimates before online fine-tuning (paper section 4): the action
noise, the critic update, the phase between pre-training and fine-tuning, the exact solution of
a one-step problem (``theory``) and ``botorl bandit`` (the paper's figures 2 and 3)."""

from botorl.boto.config import BOTOConfig
from botorl.boto.noise import gaussian_noise, hybrid_noise
from botorl.boto.objective import boto_update, boto_update_many
from botorl.boto.phase import run_boto

__all__ = ["BOTOConfig", "run_boto", "boto_update", "boto_update_many", "hybrid_noise", "gaussian_noise"]

"""botorl: offline-to-online reinforcement learning with BOTO, in JAX."""

__version__ = "0.1.0"

from botorl.errors import BotorlError  # noqa: E402,F401

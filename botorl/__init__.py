"""botorl: offline-to-online reinforcement learning with BOTO, in JAX.

The Python API (``register_task``, ``run``, ``resume``, ``load_policy``, ``load_agent``,
``export_policy``) lives in ``botorl/api.py`` and is imported on first use of one of its names,
so ``import botorl`` stays light (no JAX).
"""

__version__ = "0.1.0"

from importlib import import_module as _import_module  # noqa: E402 (private: dir(botorl) lists the API)

from botorl.errors import BotorlError  # noqa: E402,F401

_API = ("register_task", "run", "resume", "load_policy", "load_agent", "export_policy")
__all__ = ["BotorlError", "__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        return getattr(_import_module("botorl.api"), name)
    raise AttributeError(f"module 'botorl' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_API))

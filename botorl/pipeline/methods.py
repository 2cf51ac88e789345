"""Moved to ``botorl.configs.methods`` (which stages a method runs is configuration); kept
so that existing importers of ``botorl.pipeline.methods`` keep working."""

from botorl.configs.methods import METHODS, PRETRAIN_ALGOS, Method, get_method, resolve_pretrain  # noqa: F401

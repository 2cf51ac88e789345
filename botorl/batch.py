"""The batch every update reads (docs/CONTRACTS.md, "Batch"), and the one list of its keys.

A plain dict, so a user's own dict is a batch and jax flattens it by key; ``Batch`` names the
keys and their order, and every module takes them from here.
"""

from typing import Any, TypedDict


class Batch(TypedDict):
    observations: Any  # (B, O) float32, numpy or jax; several batches stack ahead: (K, B, ...)
    actions: Any  # (B, A)
    rewards: Any  # (B,)
    next_observations: Any  # (B, O)
    dones: Any  # (B,) 1.0 = a true terminal, no bootstrap (a time-limit truncation is not done)
    mc_returns: Any  # (B,) Monte-Carlo return-to-go; zeros where unknown (online rows)


BATCH_KEYS = tuple(Batch.__annotations__)
TRANSITION_KEYS = BATCH_KEYS[:-1]  # what BOTO's critic step reads: it needs no return-to-go

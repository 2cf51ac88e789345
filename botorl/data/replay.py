"""Online replay buffer (fixed-capacity ring) and mixed sampling from several sources.

``sample_mixed`` draws one batch whose rows come from several sources (replay buffers and/or
``Dataset``s) in fixed proportions, e.g. RLPD's and the Cal-QL/CQL/IQL fine-tuning baselines'
50/50 offline/online batches. Counts are exact: ``ratios=(0.5, 0.5)`` with ``batch_size=256``
gives exactly 128 rows from each source (largest-remainder rounding otherwise).

Finished episodes: the buffer knows which rows belong to the episode still running (the
newest ``open_rows``; ``end_episode()`` closes it). Cal-QL online needs each row's
Monte-Carlo return-to-go, known only once its episode ends, so it samples
``buffer.finished()``, a view of the closed rows only -- as WSRL does for Cal-QL, which
samples finished trajectories and waits one episode before its first update.
"""

from __future__ import annotations

from typing import Sequence, Union

import numpy as np

from botorl.data.dataset import BATCH_KEYS, Dataset
from botorl.errors import BotorlError, DataFormatError

_FIELDS = ("observations", "actions", "rewards", "next_observations", "dones", "mc_returns")


class ReplayBuffer:
    """Ring buffer of float32 transitions; the oldest rows are overwritten once full.

    ``insert`` is O(1); ``insert_batch`` writes many rows with at most two slice copies.
    ``state_dict()`` / ``load_state_dict()`` give plain numpy arrays for checkpoints.
    """

    def __init__(self, capacity: int, obs_dim: int, action_dim: int):
        if capacity <= 0:
            raise ValueError(f"capacity must be positive, got {capacity}")
        self.capacity = int(capacity)
        self.obs_dim = int(obs_dim)
        self.action_dim = int(action_dim)
        self.observations = np.zeros((capacity, obs_dim), np.float32)
        self.actions = np.zeros((capacity, action_dim), np.float32)
        self.rewards = np.zeros((capacity,), np.float32)
        self.next_observations = np.zeros((capacity, obs_dim), np.float32)
        self.dones = np.zeros((capacity,), np.float32)
        self.mc_returns = np.zeros((capacity,), np.float32)
        self.size = 0
        self.insert_index = 0
        self.total_inserted = 0
        self.open_rows = 0  # rows of the episode still running: the newest ones

    def __len__(self) -> int:
        return self.size

    def insert(self, observation, action, reward, next_observation, done, mc_return: float = 0.0) -> None:
        """Add one transition. ``done`` = true terminal only (a time-limit truncation is not done)."""
        i = self.insert_index
        self.observations[i] = observation
        self.actions[i] = action
        self.rewards[i] = reward
        self.next_observations[i] = next_observation
        self.dones[i] = float(done)
        self.mc_returns[i] = mc_return
        self.insert_index = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self.total_inserted += 1
        self.open_rows = min(self.open_rows + 1, self.capacity)

    def end_episode(self) -> None:
        """The running episode has ended: its rows become finished (sampleable by ``finished()``)."""
        self.open_rows = 0

    def finished(self) -> "FinishedRows":
        """A view of the rows whose episode has ended (for ``sample_mixed``/``sample``)."""
        return FinishedRows(self)

    def insert_batch(self, observations, actions, rewards, next_observations, dones, mc_returns=None) -> None:
        """Add n transitions of finished episodes at once (in order; if n > capacity only the last
        ``capacity`` stay)."""
        data = {
            "observations": np.asarray(observations, np.float32).reshape(-1, self.obs_dim),
            "actions": np.asarray(actions, np.float32).reshape(-1, self.action_dim),
            "rewards": np.asarray(rewards, np.float32).reshape(-1),
            "next_observations": np.asarray(next_observations, np.float32).reshape(-1, self.obs_dim),
            "dones": np.asarray(dones, np.float32).reshape(-1),
        }
        n = data["rewards"].shape[0]
        data["mc_returns"] = (
            np.zeros(n, np.float32) if mc_returns is None else np.asarray(mc_returns, np.float32).reshape(-1)
        )
        if any(v.shape[0] != n for v in data.values()):
            raise DataFormatError(
                "ReplayBuffer.insert_batch: fields have different lengths "
                f"{ {k: v.shape[0] for k, v in data.items()} }."
            )
        skipped = max(0, n - self.capacity)
        if skipped:
            data = {k: v[skipped:] for k, v in data.items()}
        m = n - skipped
        start = (self.insert_index + skipped) % self.capacity
        first = min(m, self.capacity - start)
        for k, v in data.items():
            buf = getattr(self, k)
            buf[start : start + first] = v[:first]
            buf[: m - first] = v[first:]
        self.insert_index = (start + m) % self.capacity
        self.size = min(self.size + n, self.capacity)
        self.total_inserted += n
        self.open_rows = 0

    def insert_dataset(self, dataset: Dataset) -> None:
        """Copy all rows of a ``Dataset`` (with its MC returns if it has them)."""
        if dataset.obs_dim != self.obs_dim or dataset.action_dim != self.action_dim:
            raise DataFormatError(
                f"cannot insert {dataset!r} into a buffer for obs_dim={self.obs_dim}, "
                f"action_dim={self.action_dim}."
            )
        self.insert_batch(
            dataset.observations,
            dataset.actions,
            dataset.rewards,
            dataset.next_observations,
            dataset.terminals,
            dataset.mc_returns,
        )

    def batch_at(self, idx: np.ndarray) -> dict:
        return {k: getattr(self, k)[idx] for k in BATCH_KEYS}

    def sample(self, rng: np.random.Generator, batch_size: int, num_batches: int | None = None) -> dict:
        """Uniform rows with replacement: (B, ...) or, with ``num_batches=K``, (K, B, ...)."""
        if self.size == 0:
            raise BotorlError("cannot sample from an empty replay buffer; insert transitions first.")
        shape = (batch_size,) if num_batches is None else (num_batches, batch_size)
        return self.batch_at(rng.integers(0, self.size, size=shape))

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, np.ndarray]:
        """Filled rows plus counters, as numpy arrays (np.savez-able)."""
        n = self.size
        state = {k: getattr(self, k)[:n].copy() for k in _FIELDS}
        state.update(
            capacity=np.asarray(self.capacity),
            obs_dim=np.asarray(self.obs_dim),
            action_dim=np.asarray(self.action_dim),
            size=np.asarray(self.size),
            insert_index=np.asarray(self.insert_index),
            total_inserted=np.asarray(self.total_inserted),
            open_rows=np.asarray(self.open_rows),
        )
        return state

    def load_state_dict(self, state: dict) -> "ReplayBuffer":
        """Restore from ``state_dict()`` output (in place; returns self)."""
        for k in ("capacity", "obs_dim", "action_dim"):
            if int(state[k]) != getattr(self, k):
                raise DataFormatError(
                    f"replay buffer checkpoint has {k}={int(state[k])}, this buffer has "
                    f"{getattr(self, k)}; build the buffer with the checkpoint's sizes."
                )
        n = int(state["size"])
        for k in _FIELDS:
            arr = np.asarray(state[k])
            if arr.shape[0] != n:
                raise DataFormatError(f"replay buffer checkpoint: field {k!r} has {arr.shape[0]} rows, expected {n}.")
            getattr(self, k)[:n] = arr
        self.size = n
        self.insert_index = int(state["insert_index"])
        self.total_inserted = int(state["total_inserted"])
        self.open_rows = int(state.get("open_rows", 0))
        return self

    @classmethod
    def from_state_dict(cls, state: dict) -> "ReplayBuffer":
        return cls(int(state["capacity"]), int(state["obs_dim"]), int(state["action_dim"])).load_state_dict(state)

    sample_mixed = staticmethod(lambda *a, **k: sample_mixed(*a, **k))


class FinishedRows:
    """The rows of a ``ReplayBuffer`` whose episode has ended, oldest first (a live view)."""

    def __init__(self, buffer: ReplayBuffer):
        self.buffer = buffer

    def __len__(self) -> int:
        return self.buffer.size - self.buffer.open_rows

    def batch_at(self, idx: np.ndarray) -> dict:
        b = self.buffer
        oldest = b.insert_index if b.size == b.capacity else 0
        return b.batch_at((oldest + np.asarray(idx)) % b.capacity)

    def sample(self, rng: np.random.Generator, batch_size: int, num_batches: int | None = None) -> dict:
        if len(self) == 0:
            raise BotorlError("no finished episode in the replay buffer yet; wait for one to end before sampling.")
        shape = (batch_size,) if num_batches is None else (num_batches, batch_size)
        return self.batch_at(rng.integers(0, len(self), size=shape))


Source = Union[ReplayBuffer, Dataset, FinishedRows]


def split_counts(ratios: Sequence[float], batch_size: int) -> list[int]:
    """Integer counts summing to ``batch_size`` in the given proportions (largest remainder)."""
    r = np.asarray(ratios, dtype=np.float64)
    if r.ndim != 1 or len(r) == 0 or (r < 0).any() or r.sum() <= 0:
        raise ValueError(f"ratios must be non-negative with a positive sum, got {list(ratios)}")
    exact = r / r.sum() * batch_size
    counts = np.floor(exact).astype(int)
    rest = batch_size - counts.sum()
    # Ties go to the earlier source, so the split is deterministic.
    order = np.argsort(-(exact - counts), kind="stable")
    counts[order[:rest]] += 1
    return counts.tolist()


def sample_mixed(
    sources: Sequence[Source],
    ratios: Sequence[float],
    rng: np.random.Generator,
    batch_size: int,
    num_batches: int | None = None,
) -> dict:
    """One Batch whose rows come from ``sources`` in proportion ``ratios``.

    Rows are grouped by source in the order given (source 0's rows first); each source is
    sampled uniformly with replacement. An empty source's share goes to the non-empty ones
    (in proportion to their ratios), so RLPD-style mixing works before the first online
    step; if all are empty this raises. With ``num_batches=K`` the result is (K, B, ...).
    """
    if len(sources) != len(ratios):
        raise ValueError(f"{len(sources)} sources but {len(ratios)} ratios")
    ratios = [float(r) if len(s) > 0 else 0.0 for s, r in zip(sources, ratios)]
    if sum(ratios) <= 0:
        raise BotorlError("sample_mixed: every source with a positive ratio is empty; nothing to sample.")
    counts = split_counts(ratios, batch_size)
    parts = []
    for src, c in zip(sources, counts):
        if c == 0:
            continue
        n = len(src)
        shape = (c,) if num_batches is None else (num_batches, c)
        parts.append(src.batch_at(rng.integers(0, n, size=shape)))
    axis = 0 if num_batches is None else 1
    return {k: np.concatenate([p[k] for p in parts], axis=axis) for k in BATCH_KEYS}

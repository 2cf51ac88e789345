"""Online replay buffer (fixed-capacity ring), with a member axis for populations (CONTRACTS.md,
"Data"). ``sample_members`` draws each member's batch with the member's own generator exactly as
that member's own buffer would, offline/online counts exact (``split_counts``).

Cal-QL online needs each row's Monte-Carlo return-to-go, known only once its episode ends, so it
samples finished rows only (``finished=True``; the running episode's rows are the newest
``open_rows``) -- as WSRL does for Cal-QL, which waits one episode before its first update.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from botorl.batch import BATCH_KEYS, Batch
from botorl.data.dataset import Dataset
from botorl.errors import BotorlError, DataFormatError

_EMPTY = "cannot sample from an empty replay buffer; insert transitions first."


class ReplayBuffer:
    """Ring buffer(s) of float32 transitions; the oldest rows are overwritten once full.
    ``members=N``: fields (N, capacity, ...), ``size``, ``insert_index`` and ``total_inserted``
    shared, the rows of the running episode per member."""

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, members: int | None = None):
        if capacity <= 0:
            raise ValueError(f"capacity must be positive, got {capacity}")
        self.capacity, self.obs_dim, self.action_dim = int(capacity), int(obs_dim), int(action_dim)
        self.members = None if members is None else int(members)
        m = 1 if members is None else self.members
        tails = {"observations": (obs_dim,), "actions": (action_dim,), "next_observations": (obs_dim,)}
        self._arrays = {k: np.zeros((m, capacity) + tails.get(k, ()), np.float32) for k in BATCH_KEYS}
        for k, arr in self._arrays.items():  # the public fields: views without the axis for one buffer
            setattr(self, k, arr[0] if members is None else arr)
        self.size = 0
        self.insert_index = 0
        self.total_inserted = 0
        self._open = np.zeros(m, np.int64)  # rows of each member's running episode: the newest ones

    @property
    def n(self) -> int:
        return self._open.shape[0]

    def __len__(self) -> int:
        return self.size

    # ------------------------------------------------------------------ inserting
    def insert(self, observation, action, reward, next_observation, done, mc_return=0.0) -> None:
        """One transition (per member, stacked (N, ...), for a member buffer). ``done`` = true
        terminal only (a time-limit truncation is not done)."""
        i = self.insert_index
        for k, v in zip(BATCH_KEYS, (observation, action, reward, next_observation, done, mc_return)):
            self._arrays[k][:, i] = v
        self.insert_index = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self.total_inserted += 1
        self._open = np.minimum(self._open + 1, self.capacity)

    def end_episode(self, member: int = 0) -> None:
        """The member's running episode has ended: its rows become finished."""
        self._open[member] = 0

    def finished_len(self, member: int = 0) -> int:
        return int(self.size - self._open[member])

    def insert_batch(self, observations, actions, rewards, next_observations, dones, mc_returns=None) -> None:
        """Add n transitions of finished episodes at once, in order (if n > capacity only the last
        ``capacity`` stay); a member buffer takes (N, n, ...) arrays."""
        values = (observations, actions, rewards, next_observations, dones, mc_returns)
        data = {k: None if v is None else np.asarray(v, np.float32).reshape((self.n, -1) + self._arrays[k].shape[2:])
                for k, v in zip(BATCH_KEYS, values)}
        n = data["rewards"].shape[1]
        if data["mc_returns"] is None:
            data["mc_returns"] = np.zeros((self.n, n), np.float32)
        if any(v.shape[1] != n for v in data.values()):
            raise DataFormatError("ReplayBuffer.insert_batch: fields have different lengths "
                                  f"{ {k: v.shape[1] for k, v in data.items()} }.")
        skipped = max(0, n - self.capacity)
        m = n - skipped
        start = (self.insert_index + skipped) % self.capacity
        first = min(m, self.capacity - start)
        for k, v in data.items():
            buf = self._arrays[k]
            buf[:, start:start + first] = v[:, skipped:skipped + first]
            buf[:, :m - first] = v[:, skipped + first:]
        self.insert_index = (start + m) % self.capacity
        self.size = min(self.size + n, self.capacity)
        self.total_inserted += n
        self._open[:] = 0

    def insert_dataset(self, dataset: Dataset | Sequence[Dataset]) -> None:
        """Copy all rows of a ``Dataset`` (with its MC returns if it has them); a member buffer
        takes one dataset per member, all of one length (each member's D_warmup)."""
        datasets = [dataset] if isinstance(dataset, Dataset) else list(dataset)
        if len(datasets) != self.n or len({len(d) for d in datasets}) != 1:
            raise ValueError(f"insert_dataset needs {self.n} dataset(s) of one length, got {len(datasets)}")
        for d in datasets:
            if d.obs_dim != self.obs_dim or d.action_dim != self.action_dim:
                raise DataFormatError(f"cannot insert {d!r} into a buffer for obs_dim={self.obs_dim}, "
                                      f"action_dim={self.action_dim}.")
        batches = [d.batch_at(np.arange(len(d))) for d in datasets]  # dones as floats, mc_returns 0 if absent
        self.insert_batch(*(np.stack([b[k] for b in batches]) for k in BATCH_KEYS))

    def set_mc_returns(self, rows: Sequence[int], mc_returns: Callable[[Dataset], np.ndarray], member: int = 0) -> None:
        """Fill the Monte-Carlo returns of one finished episode's ``rows`` (of ``member``) with
        ``mc_returns(episode)`` (the offline data's rule, applied to the episode as a Dataset)."""
        if not len(rows):
            return
        idx = (member, np.asarray(rows))
        ep = Dataset.of_batch({k: a[idx] for k, a in self._arrays.items()}, metadata={"source": "online episode"})
        self._arrays["mc_returns"][idx] = mc_returns(ep)

    # ------------------------------------------------------------------ sampling
    def batch_at(self, idx: np.ndarray) -> Batch:
        """Rows ``idx`` of a single buffer."""
        return {k: getattr(self, k)[idx] for k in BATCH_KEYS}

    def sample(self, rng: np.random.Generator, batch_size: int, num_batches: int | None = None) -> Batch:
        """Uniform rows with replacement: (B, ...) or, with ``num_batches=K``, (K, B, ...)."""
        if self.size == 0:
            raise BotorlError(_EMPTY)
        shape = (batch_size,) if num_batches is None else (num_batches, batch_size)
        return self.batch_at(rng.integers(0, self.size, size=shape))

    def _take(self, members: np.ndarray, idx: np.ndarray) -> Batch:
        """Rows ``idx`` (M, ...) of ``members`` (M,), one flat ``np.take`` per field: numpy's
        two-array fancy index (``arr[m, idx]``) is 4-10x slower, and with 8 members it was a
        fifth of a fine-tuning step's host time."""
        flat = (members.reshape(members.shape + (1,) * (idx.ndim - 1)) * self.capacity + idx).ravel()
        return {k: np.take(a.reshape((-1,) + a.shape[2:]), flat, axis=0).reshape(idx.shape + a.shape[2:])
                for k, a in self._arrays.items()}

    def _row_index(self, i: int, rng: np.random.Generator, shape, finished: bool) -> np.ndarray:
        """Member i's row indices: all rows, or (``finished``) those of closed episodes, oldest first."""
        if not finished:
            return rng.integers(0, self.size, size=shape)
        oldest = self.insert_index if self.size == self.capacity else 0
        return (oldest + rng.integers(0, self.finished_len(i), size=shape)) % self.capacity

    def sample_members(self, rngs: Sequence[np.random.Generator], batch_size: int, num_batches: int | None = None,
                       *, active: Sequence[bool] | None = None, finished: bool = False, offline: Dataset | None = None,
                       offline_ratio: float = 0.0) -> Batch:
        """One batch per member, drawn with ``rngs[i]`` as member i's own buffer would: offline rows
        first (``offline_ratio`` of the batch), then its buffer's (or its finished rows). Members not
        ``active`` draw nothing (their generator is not advanced) and get zeros. Stacked (N, [K,] B, ...)."""
        active = [True] * self.n if active is None else active
        lead = () if num_batches is None else (num_batches,)
        out = {k: np.zeros((self.n,) + lead + (batch_size,) + v.shape[2:], np.float32) for k, v in self._arrays.items()}
        r_idx, members, off_idx = [], [], []
        counts = None
        for i, (rng, on) in enumerate(zip(rngs, active)):
            if not on:
                continue
            n_rows = self.finished_len(i) if finished else self.size
            if offline is not None:
                ratios = [offline_ratio if len(offline) > 0 else 0.0, (1.0 - offline_ratio) if n_rows > 0 else 0.0]
                if sum(ratios) <= 0:
                    raise BotorlError("ReplayBuffer.sample_members: every source with a positive ratio (the "
                                      "offline data, the buffer) is empty; nothing to sample.")
                c_off, c_on = split_counts(ratios, batch_size)
            else:
                if n_rows == 0:
                    raise BotorlError(_EMPTY)
                c_off, c_on = 0, batch_size
            if counts is not None and counts != (c_off, c_on):
                raise AssertionError("members of one population drew batches of different compositions")
            counts = (c_off, c_on)
            # the offline rows first, then the buffer's, in every member's batch
            off_idx.append(rng.integers(0, len(offline), size=lead + (c_off,)) if c_off else None)
            r_idx.append(self._row_index(i, rng, lead + (c_on,), finished) if c_on else None)
            members.append(i)
        if not members:
            return out
        c_off, c_on = counts
        parts = []
        if c_off:
            parts.append(offline.batch_at(np.stack(off_idx)))
        if c_on:
            parts.append(self._take(np.asarray(members), np.stack(r_idx)))
        axis = len(lead) + 1
        for k in BATCH_KEYS:
            out[k][np.asarray(members)] = np.concatenate([p[k] for p in parts], axis=axis)
        return out

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, np.ndarray]:
        """Filled rows plus counters, as numpy arrays (np.savez-able); a member buffer's also
        ``num_members`` and one ``open_rows`` per member."""
        lead = 0 if self.members is None else slice(None)  # a single buffer's fields have no member axis
        state = {k: self._arrays[k][lead, :self.size].copy() for k in BATCH_KEYS}
        if self.members is not None:
            state["num_members"] = np.asarray(self.members)
        state.update(capacity=np.asarray(self.capacity), obs_dim=np.asarray(self.obs_dim),
                     action_dim=np.asarray(self.action_dim), size=np.asarray(self.size),
                     insert_index=np.asarray(self.insert_index), total_inserted=np.asarray(self.total_inserted),
                     open_rows=np.array(self._open[lead]))
        return state

    @classmethod
    def from_state_dict(cls, state: dict) -> "ReplayBuffer":
        """A buffer from either form's ``state_dict()`` output."""
        members = int(state["num_members"]) if "num_members" in state else None
        buf = cls(int(state["capacity"]), int(state["obs_dim"]), int(state["action_dim"]), members)
        n = int(state["size"])
        for k in BATCH_KEYS:
            arr = np.asarray(state[k])
            arr = arr[None] if members is None else arr
            if arr.shape[:2] != (buf.n, n):
                raise DataFormatError(f"replay buffer checkpoint: field {k!r} has shape {arr.shape}, expected "
                                      f"{buf.n} member(s) x {n} rows.")
            buf._arrays[k][:, :n] = arr
        buf.size = n
        buf.insert_index = int(state["insert_index"])
        buf.total_inserted = int(state["total_inserted"])
        buf._open[:] = np.asarray(state.get("open_rows", 0), np.int64)
        return buf


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

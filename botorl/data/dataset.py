"""The one offline dataset type every algorithm uses, and the one reward transform.

``episode_ends[i]`` marks the last row of an episode (terminal or truncated), ``terminals[i]`` a
true terminal (no bootstrapping): Cal-QL's adroit data have several terminal rows inside one
trajectory, and a truncated episode ends without one. Batches: ``botorl.batch.Batch``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from botorl.batch import BATCH_KEYS, Batch
from botorl.errors import DataFormatError

# The per-row arrays of a Dataset, named here only, in the order of its constructor's arguments:
# a transition's five, then where episodes end and their Monte-Carlo returns (None: unknown).
TRANSITION_FIELDS = ("observations", "actions", "rewards", "next_observations", "terminals")
FIELDS = TRANSITION_FIELDS + ("episode_ends", "mc_returns")

# Actions are kept strictly inside the open box so that atanh (tanh-squashed policies'
# log-probabilities of dataset actions) stays finite; 1e-5 as in jaxrl/IQL/Cal-QL.
ACTION_CLIP = 1.0 - 1e-5


@dataclass(frozen=True)
class RewardTransform:
    """``r' = scale * r + bias``, applied to the offline data and to every online reward alike,
    so the two can never drift apart. Evaluation returns are never transformed."""

    scale: float = 1.0
    bias: float = 0.0

    @classmethod
    def of(cls, spec) -> "RewardTransform":
        """The transform of a task (``TaskSpec.reward_scale``, ``reward_bias``)."""
        return cls(spec.reward_scale, spec.reward_bias)

    def __call__(self, rewards):
        return self.scale * rewards + self.bias


def segments(last_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, stops) of the row ranges that end at the marked rows."""
    stops = np.flatnonzero(last_rows) + 1
    return np.concatenate([[0], stops[:-1]]).astype(stops.dtype), stops


def _source(metadata: dict | None) -> str:
    return str((metadata or {}).get("source", "<in-memory dataset>"))


def numeric(x, field: str, source: str) -> np.ndarray:
    """``x`` as an array of booleans, integers or reals; DataFormatError naming the field for any
    other dtype (byte strings or text parse as numbers, complex numbers lose their imaginary part,
    objects are no data)."""
    a = np.asarray(x)
    if a.dtype.kind not in "biuf":
        raise DataFormatError(f"{source}: {field} has dtype {a.dtype}, which cannot be read as numbers; the data must "
                              f"be booleans, integers or floats. Save {field} as a numeric array.")
    return a


class Dataset:
    """Flat offline transitions (see the module docstring).

    Actions are clipped to ``±ACTION_CLIP``; their largest raw magnitude is kept in
    ``raw_action_max`` so that ``validate`` can still reject data far outside the box.
    ``episode_ends`` defaults to the terminal rows; the last row is always an episode end.
    ``metadata["source"]`` names where the data came from (in error messages).
    """

    def __init__(self, observations, actions, rewards, next_observations, terminals, episode_ends=None, mc_returns=None,
                 infos: dict[str, np.ndarray] | None = None, metadata: dict[str, Any] | None = None, *,
                 raw_action_max: float | None = None):
        src = _source(metadata)
        obs = numeric(observations, "observations", src).astype(np.float32, copy=False)
        nobs = numeric(next_observations, "next_observations", src).astype(np.float32, copy=False)
        act = numeric(actions, "actions", src).astype(np.float32, copy=False)
        rew = numeric(rewards, "rewards", src).astype(np.float32, copy=False)
        term = numeric(terminals, "terminals", src).astype(bool)
        obs, nobs, act = (x[:, None] if x.ndim == 1 else x for x in (obs, nobs, act))
        rew, term = (x.reshape(-1) if x.ndim == 2 and x.shape[1] == 1 else x for x in (rew, term))
        n = obs.shape[0]
        shapes = {"observations": obs.shape, "actions": act.shape, "rewards": rew.shape,
                  "next_observations": nobs.shape, "terminals": term.shape}
        if obs.ndim != 2 or nobs.ndim != 2 or act.ndim != 2 or rew.ndim != 1 or term.ndim != 1:
            raise DataFormatError(f"{src}: arrays have the wrong number of dimensions ({shapes}); expected "
                                  "observations/next_observations (N, O), actions (N, A), rewards and terminals (N,). "
                                  "Flatten observations before building a Dataset.")
        lengths = {k: s[0] for k, s in shapes.items()}
        if len(set(lengths.values())) != 1 or nobs.shape[1] != obs.shape[1]:
            raise DataFormatError(f"{src}: mismatched array lengths/shapes {shapes}. Every field needs one row per "
                                  "transition and next_observations must have the same width as observations; the "
                                  "file is truncated or was written inconsistently.")
        if n == 0:
            raise DataFormatError(f"{src}: the dataset has no transitions.")
        ends = term.copy() if episode_ends is None else numeric(episode_ends, "episode_ends", src).astype(bool).reshape(-1)
        if mc_returns is not None:
            mc_returns = numeric(mc_returns, "mc_returns", src).astype(np.float32).reshape(-1)
        for name, v in (("episode_ends", ends), ("mc_returns", mc_returns)):
            if v is not None and v.shape != (n,):
                raise DataFormatError(f"{src}: {name} has shape {v.shape}, expected ({n},).")
        ends[-1] = True
        infos = {k: np.asarray(v) for k, v in (infos or {}).items()}
        for k, v in infos.items():
            if v.shape[:1] != (n,):
                raise DataFormatError(f"{src}: info field {k!r} has {v.shape[:1]} rows, expected {n}.")
        if raw_action_max is None:
            # inf counts (validate reports it); NaN is left to the finiteness check.
            mags = np.abs(act[~np.isnan(act)])
            raw_action_max = float(mags.max()) if mags.size else 0.0
        self.raw_action_max = float(raw_action_max)
        # NaN actions stay NaN (validate reports them); everything else is clipped.
        self.observations = obs
        self.actions = np.clip(act, -ACTION_CLIP, ACTION_CLIP)
        self.rewards = rew
        self.next_observations = nobs
        self.terminals = term
        self.episode_ends = ends
        self.mc_returns = mc_returns
        self.infos = infos
        self.metadata = dict(metadata or {})

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.rewards.shape[0])

    def __repr__(self) -> str:
        return (
            f"Dataset(n={len(self)}, obs_dim={self.obs_dim}, action_dim={self.action_dim}, "
            f"episodes={self.num_episodes}, source={_source(self.metadata)!r})"
        )

    @property
    def obs_dim(self) -> int:
        return int(self.observations.shape[1])

    @property
    def action_dim(self) -> int:
        return int(self.actions.shape[1])

    @property
    def num_episodes(self) -> int:
        return int(self.episode_ends.sum())

    def _replace(self, **changes) -> "Dataset":
        fields = {k: getattr(self, k) for k in FIELDS + ("infos", "raw_action_max")}
        fields["metadata"] = copy.deepcopy(self.metadata)
        return Dataset(**{**fields, **changes})

    def arrays(self) -> dict[str, np.ndarray]:
        """Its per-row arrays by name (``FIELDS``; mc_returns where known): ``Dataset(**arrays)`` again."""
        return {k: getattr(self, k) for k in FIELDS if getattr(self, k) is not None}

    @classmethod
    def of_batch(cls, rows: Batch, **kw) -> "Dataset":
        """The transitions of a Batch's rows (``dones`` as terminals; its mc_returns not kept)."""
        return cls(*(rows[k] for k in BATCH_KEYS[:4]), rows["dones"] > 0.5, **kw)

    def episode_slices(self) -> list[slice]:
        """Row ranges of the episodes, in order."""
        return [slice(int(s), int(e)) for s, e in zip(*segments(self.episode_ends))]

    def episodes(self) -> Iterator[dict[str, np.ndarray]]:
        """Yield each episode as a dict of its rows (views, not copies)."""
        for sl in self.episode_slices():
            ep = {k: getattr(self, k)[sl] for k in TRANSITION_FIELDS}
            if self.mc_returns is not None:
                ep["mc_returns"] = self.mc_returns[sl]
            for k, v in self.infos.items():
                ep[f"infos/{k}"] = v[sl]
            yield ep

    # ------------------------------------------------------------------ transforms
    def with_reward_transform(self, scale: float | RewardTransform = 1.0, bias: float = 0.0) -> "Dataset":
        """A copy with ``r' = scale * r + bias``; MC returns are recomputed from the new rewards
        with the same settings, because the return of transformed rewards is not an affine map
        of the old return."""
        tf = scale if isinstance(scale, RewardTransform) else RewardTransform(float(scale), float(bias))
        meta = copy.deepcopy(self.metadata)
        meta.setdefault("reward_transforms", []).append({"scale": tf.scale, "bias": tf.bias})
        out = self._replace(rewards=tf(self.rewards).astype(np.float32), mc_returns=None, metadata=meta)
        mc = self.metadata.get("mc_returns")
        if self.mc_returns is not None and mc is not None:
            r_neg = mc["sparse_negative_reward"]
            out = out.with_mc_returns(mc["gamma"], sparse_negative_reward=None if r_neg is None else float(tf(r_neg)),
                                      infinite_horizon=mc["infinite_horizon"])
        return out

    def with_mc_returns(self, gamma: float, *, sparse_negative_reward: float | None = None,
                        infinite_horizon: bool = False) -> "Dataset":
        """A copy with Monte-Carlo returns-to-go, as Cal-QL computes them (nakamotoo/Cal-QL
        JaxCQL/replay_buffer.py ``calc_return_to_go``).

        Per episode, backwards: ``G_t = r_t + gamma * (1 - terminal_t) * G_{t+1}``, ``G = 0``
        after the last row (``r_last / (1 - gamma)`` with ``infinite_horizon``, Cal-QL's kitchen
        choice). An episode whose rewards all equal ``sparse_negative_reward`` (in the units of
        the current rewards) gets ``r_neg / (1 - gamma)`` at every row: it fails forever.
        """
        if not 0.0 <= gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {gamma}")
        # lazy: scipy.signal takes ~1 s to import, and botorl.api imports this module; only MC returns need it
        from scipy.signal import lfilter

        out = np.empty(len(self), dtype=np.float64)
        rew = self.rewards.astype(np.float64)
        # Segments end at episode ends and at terminals; inside a segment the recursion has
        # the constant coefficient gamma, so a reversed IIR filter computes it exactly.
        for s, e in zip(*segments(self.episode_ends | self.terminals)):
            r = rew[s:e]
            g = lfilter([1.0], [1.0, -gamma], r[::-1])[::-1]
            if infinite_horizon and not self.terminals[e - 1]:
                tail = r[-1] / (1.0 - gamma)
                g = g + tail * gamma ** np.arange(e - s, 0, -1)
            out[s:e] = g
        if sparse_negative_reward is not None:
            r_neg = float(sparse_negative_reward)
            for sl in self.episode_slices():
                if np.all(np.isclose(rew[sl], r_neg, rtol=0.0, atol=1e-6)):
                    out[sl] = r_neg / (1.0 - gamma)
        meta = copy.deepcopy(self.metadata)
        meta["mc_returns"] = {"gamma": float(gamma), "sparse_negative_reward": sparse_negative_reward,
                              "infinite_horizon": bool(infinite_horizon)}
        return self._replace(mc_returns=out.astype(np.float32), metadata=meta)

    def concat(self, other: "Dataset") -> "Dataset":
        """Rows of ``self`` then ``other``; MC returns only if both have them, infos only the keys both have."""
        if other.obs_dim != self.obs_dim or other.action_dim != self.action_dim:
            raise DataFormatError(f"cannot concatenate {_source(self.metadata)} (obs {self.obs_dim}, action "
                                  f"{self.action_dim}) with {_source(other.metadata)} (obs {other.obs_dim}, action "
                                  f"{other.action_dim}): the dimensions differ.")
        both_mc = self.mc_returns is not None and other.mc_returns is not None
        mc = np.concatenate([self.mc_returns, other.mc_returns]) if both_mc else None
        keys = sorted(set(self.infos) & set(other.infos))
        meta = copy.deepcopy(self.metadata)
        meta["source"] = f"{_source(self.metadata)} + {_source(other.metadata)}"
        if self.metadata.get("mc_returns") != other.metadata.get("mc_returns"):
            meta.pop("mc_returns", None)
        return Dataset(
            *(np.concatenate([getattr(self, k), getattr(other, k)]) for k in TRANSITION_FIELDS + ("episode_ends",)),
            mc,
            {k: np.concatenate([self.infos[k], other.infos[k]]) for k in keys},
            meta,
            raw_action_max=max(self.raw_action_max, other.raw_action_max),
        )

    # ------------------------------------------------------------------ sampling
    def batch_at(self, idx: np.ndarray) -> Batch:
        """The Batch of the given row indices (any index shape: (B,) or (K, B))."""
        batch = {k: getattr(self, k)[idx] for k in BATCH_KEYS[:4]}
        batch["dones"] = self.terminals[idx].astype(np.float32)
        batch["mc_returns"] = self.mc_returns[idx] if self.mc_returns is not None else np.zeros(idx.shape, np.float32)
        return batch

    def sample(self, rng: np.random.Generator, batch_size: int, num_batches: int | None = None) -> Batch:
        """Uniform rows with replacement: a Batch of (B, ...) or, with ``num_batches=K``, (K, B, ...)."""
        shape = (batch_size,) if num_batches is None else (num_batches, batch_size)
        return self.batch_at(rng.integers(0, len(self), size=shape))

    def sample_members(self, rngs, batch_size: int, num_batches: int | None = None) -> Batch:
        """One batch per member, drawn with ``rngs[i]`` exactly as ``sample(rngs[i], ...)`` would,
        gathered at once: (N, [K,] B, ...)."""
        shape = (batch_size,) if num_batches is None else (num_batches, batch_size)
        return self.batch_at(np.stack([r.integers(0, len(self), size=shape) for r in rngs]))

    def to_device(self) -> Batch:
        """The Batch fields of all rows as a pytree of ``jnp`` arrays (for ``sample_batches``)."""
        import jax.numpy as jnp  # lazy: JAX; botorl.api imports this module (`import botorl` stays without JAX)

        return {k: jnp.asarray(v) for k, v in self.batch_at(np.arange(len(self))).items()}

    # ------------------------------------------------------------------ stats
    def stats(self, success_key: str = "success") -> dict[str, Any]:
        """Size, episodes, per-episode returns and success rate (an episode's success: the max of
        ``infos[success_key]`` over its rows; None without it)."""
        slices = self.episode_slices()
        csum = np.concatenate([[0.0], np.cumsum(self.rewards, dtype=np.float64)])
        rets = np.array([csum[s.stop] - csum[s.start] for s in slices])
        lens = np.array([s.stop - s.start for s in slices])
        success_rate = None
        if success_key in self.infos:
            succ = np.asarray(self.infos[success_key], dtype=np.float64)
            success_rate = float(np.mean([succ[s].max() for s in slices]))
        return {"transitions": len(self), "episodes": len(slices), "obs_dim": self.obs_dim,
                "action_dim": self.action_dim, "terminals": int(self.terminals.sum()),
                "episode_length_mean": float(lens.mean()), "return_mean": float(rets.mean()),
                "return_std": float(rets.std()), "return_min": float(rets.min()), "return_max": float(rets.max()),
                "reward_min": float(self.rewards.min()), "reward_max": float(self.rewards.max()),
                "success_rate": success_rate}


def validate(dataset: Dataset, obs_dim: int | None = None, action_dim: int | None = None,
             action_tolerance: float = 1e-3) -> Dataset:
    """The dataset unchanged, after checking finite values, the widths (when given) and the raw
    actions within ``1 + action_tolerance``; a ``DataFormatError`` naming the file and problem."""
    src = _source(dataset.metadata)
    for name in ("observations", "actions", "rewards", "next_observations"):
        arr = getattr(dataset, name)
        bad = ~np.isfinite(arr)
        if bad.any():
            rows = np.flatnonzero(bad.reshape(len(arr), -1).any(axis=1))
            raise DataFormatError(f"{src}: field {name!r} has {int(bad.sum())} NaN/inf values (first at row "
                                  f"{int(rows[0])}, {len(rows)} rows affected). Clean or drop those transitions "
                                  "before loading; botorl does not train on non-finite data.")
    if dataset.mc_returns is not None and not np.isfinite(dataset.mc_returns).all():
        raise DataFormatError(f"{src}: mc_returns contain NaN/inf values.")
    if obs_dim is not None and dataset.obs_dim != obs_dim:
        raise DataFormatError(f"{src}: observations have {dataset.obs_dim} dimensions but the task expects "
                              f"{obs_dim}. The file belongs to a different task or version (or its dict "
                              "observations were flattened in another order/subset); load the matching dataset.")
    if action_dim is not None and dataset.action_dim != action_dim:
        raise DataFormatError(f"{src}: actions have {dataset.action_dim} dimensions but the task expects "
                              f"{action_dim}. The file belongs to a different task; load the matching dataset.")
    if dataset.raw_action_max > 1.0 + action_tolerance:
        raise DataFormatError(f"{src}: actions reach magnitude {dataset.raw_action_max:.6g}, outside [-1, 1] by more "
                              f"than the tolerance {action_tolerance:g}. botorl expects actions normalised to "
                              "[-1, 1]; rescale the actions, or pass a larger action_tolerance if clipping them "
                              "is acceptable.")
    return dataset

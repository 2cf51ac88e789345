"""Fidelity to WSRL's protocol: the bugs a review against WSRL's code found, each pinned.

- an N-critic ensemble is N trained critics (tiling fewer pre-trained ones left copies that
  stay identical forever: same batches, same targets);
- fine-tuning starts from the pre-trained optimiser state (WSRL restores the whole agent);
- Cal-QL online samples finished episodes only (their MC returns are known) and waits for
  the first one before updating.
"""

from __future__ import annotations

import csv
import itertools

import jax
import numpy as np
import pytest

from botorl.agents.sac import SACAgent
from botorl.cli import main as botorl_main
from botorl.configs.presets import make_preset
from botorl.configs.resolve import resolve
from botorl.data.dataset import Dataset
from botorl.data.replay import ReplayBuffer
from botorl.errors import ConfigError
from botorl.pipeline.stages import make_pretrain_agent
from helpers import FinishedRows, sample_mixed

O, A, B = 4, 2, 32


def _batch(rng, k=None):
    shape = (B,) if k is None else (k, B)
    return {
        "observations": rng.normal(size=shape + (O,)).astype(np.float32),
        "actions": rng.uniform(-0.9, 0.9, size=shape + (A,)).astype(np.float32),
        "rewards": rng.normal(size=shape).astype(np.float32),
        "next_observations": rng.normal(size=shape + (O,)).astype(np.float32),
        "dones": np.zeros(shape, np.float32),
        "mc_returns": rng.normal(size=shape).astype(np.float32),
    }


@pytest.fixture(scope="module", params=["calql", "iql"])
def warm_started(request):
    """The quick profile's BOTO config (4 critics), pre-trained a few steps, then warm-started."""
    cfg = resolve(make_preset("pointmaze-umaze", "quick", "boto", pretrain=request.param))
    rng = np.random.default_rng(0)
    pre = make_pretrain_agent(cfg, O, A, seed=0)
    pre, _ = pre.update_many(_batch(rng, 3))
    online = SACAgent.from_pretrained(pre, cfg.online.sac, seed=1)
    return cfg, pre, online


def test_every_critic_of_the_ensemble_is_distinct(warm_started):
    cfg, pre, online = warm_started
    assert cfg.network.num_critics == 4 and cfg.online.sac.num_critics == 4
    rng = np.random.default_rng(1)
    for _ in range(3):
        # an online update: utd critic minibatches, (utd, B, ...)
        online, _ = online.update({k: np.stack([v] * cfg.online.utd) for k, v in _batch(rng).items()})
    kernel = np.asarray(online.critic.params["members"]["MLP_0"]["Dense_0"]["kernel"])  # (N, in, H)
    for i, j in itertools.combinations(range(kernel.shape[0]), 2):
        assert np.abs(kernel[i] - kernel[j]).max() > 1e-3, f"critics {i} and {j} are copies"


def test_finetuning_starts_from_the_pretrained_optimiser_state(warm_started):
    _, pre, online = warm_started
    for name in ("actor", "critic"):
        got, want = getattr(online, name), getattr(pre, name)
        assert int(got.step) == int(want.step) == 3
        got_leaves = jax.tree_util.tree_leaves(got.opt_state)
        want_leaves = jax.tree_util.tree_leaves(want.opt_state)
        assert any(np.abs(np.asarray(w)).max() > 0 for w in want_leaves)  # Adam moments after 3 steps
        for g, w in zip(got_leaves, want_leaves):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    if hasattr(pre, "temp"):
        np.testing.assert_array_equal(
            np.asarray(jax.tree_util.tree_leaves(online.temp.opt_state)[1]),
            np.asarray(jax.tree_util.tree_leaves(pre.temp.opt_state)[1]))


def test_an_ensemble_is_never_filled_with_copies(warm_started):
    from dataclasses import replace

    cfg, pre, _ = warm_started
    with pytest.raises(ConfigError, match="Pre-train with the fine-tuning ensemble size"):
        SACAgent.from_pretrained(pre, replace(cfg.online.sac, num_critics=8))


# ----------------------------------------------------------------------------- Cal-QL online
def _insert(buf, values, done_last):
    for i, v in enumerate(values):
        buf.insert(np.full(O, v), np.zeros(A), 0.0, np.zeros(O), done_last and i == len(values) - 1)


def test_finished_rows_exclude_the_running_episode():
    buf = ReplayBuffer(8, O, A)
    _insert(buf, [1, 2, 3], done_last=True)
    buf.end_episode()
    _insert(buf, [4, 5], done_last=False)  # still running
    fin = FinishedRows(buf)
    assert len(buf) == 5 and len(fin) == 3
    seen = set(fin.sample(np.random.default_rng(0), 200)["observations"][:, 0])
    assert seen == {1.0, 2.0, 3.0}
    # in a 50/50 batch with the offline data, the online half holds finished rows only
    off = Dataset(np.full((10, O), -1.0, np.float32), np.zeros((10, A), np.float32), np.zeros(10, np.float32),
                  np.zeros((10, O), np.float32), np.zeros(10, bool))
    mixed = sample_mixed([off, fin], [0.5, 0.5], np.random.default_rng(1), 64)
    assert set(mixed["observations"][32:, 0]) <= {1.0, 2.0, 3.0}
    # the ring wraps: the oldest rows are overwritten, the running episode stays excluded
    buf.end_episode()
    _insert(buf, [6, 7, 8, 9, 10], done_last=False)
    assert len(buf) == 8 and len(FinishedRows(buf)) == 3
    assert set(FinishedRows(buf).sample(np.random.default_rng(2), 200)["observations"][:, 0]) == {3.0, 4.0, 5.0}
    # and the count survives a checkpoint
    again = ReplayBuffer.from_state_dict(buf.state_dict())
    assert len(FinishedRows(again)) == 3


def test_calql_online_waits_for_a_finished_episode(tmp_path):
    # pointmaze episodes outlast the smoke run's 40 online steps: no row has its MC return
    # yet, so Cal-QL continued online must not update (before: it did, with returns of 0)
    out = tmp_path / "calql"
    args = ["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--method", "calql", "--no-progress",
            "--no-tensorboard", "--out", str(out)]
    assert botorl_main(args) == 0
    with open(out / "metrics" / "finetune.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(int(r["episodes"]) == 0 for r in rows)
    assert all(not r.get("critic_loss") for r in rows), "Cal-QL updated on rows without an MC return"

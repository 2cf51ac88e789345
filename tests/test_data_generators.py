"""Bandit generators and their ground truth (botorl.envs.bandit); the cache and the `botorl data` CLI."""

from __future__ import annotations

import numpy as np
import pytest

from botorl.data.generators import GENERATORS, get_generator
from botorl.data.generators import bandit
from botorl.envs import bandit as truth
from botorl.errors import ConfigError


def test_pinwheel_density_normalised_and_matches_samples():
    g = np.linspace(-1, 1, 401)
    xx, yy = np.meshgrid(g, g)
    dens = truth.pinwheel_density(np.stack([xx, yy], -1))
    mass = dens.sum() * (g[1] - g[0]) ** 2
    assert mass == pytest.approx(1.0, abs=0.01)  # all mass inside [-1, 1]^2
    acts, arm = truth.sample_pinwheel(np.random.default_rng(0), 20000)
    assert np.abs(acts).max() < 1.0
    # Sampled points sit where the density is high: mean density at samples >> uniform's 1/4.
    assert truth.pinwheel_density(acts).mean() > 1.0
    # The arm with the largest density at a sample is (almost always) the arm it came from.
    assert (truth.pinwheel_arm(acts) == arm).mean() > 0.95
    r = truth.pinwheel_reward(acts)
    for k in range(truth.PINWHEEL_ARMS):
        sel = truth.pinwheel_arm(acts) == k
        assert r[sel].min() >= k / 5 - 1e-6 and r[sel].max() < (k + 1) / 5


def test_bandit_datasets_one_step_and_deterministic():
    a = bandit.generate_pinwheel(300, seed=3)
    b = bandit.generate_pinwheel(300, seed=3)
    np.testing.assert_array_equal(a.actions, b.actions)
    assert a.terminals.all() and a.episode_ends.all() and a.obs_dim == 1 and a.action_dim == 2
    np.testing.assert_allclose(a.rewards, truth.pinwheel_reward(a.actions), atol=1e-5)
    d = bandit.generate_1d(500, seed=0)
    sup, rew, probs = truth.bandit_1d_support()
    assert d.action_dim == 1 and probs.sum() == pytest.approx(1.0)
    assert set(np.round(d.actions[:, 0], 5)) <= set(np.round(sup[:, 0], 5))
    np.testing.assert_array_equal(d.rewards, truth.bandit_1d_reward(d.actions))
    assert len(set(rew.tolist())) == len(truth.BANDIT_1D_CLUSTERS)  # distinct cluster rewards


def test_registry_errors():
    assert {"pointmaze-large", "door-binary-local", "bandit-pinwheel", "bandit-1d"} <= set(GENERATORS)
    assert get_generator("bandit-1d") is bandit.generate_1d
    with pytest.raises(ConfigError, match="cannot generate"):
        get_generator("antmaze-large-diverse-v2")


def test_every_generator_in_the_table_exists():
    for task in GENERATORS:
        assert callable(get_generator(task)), task


def test_ensure_dataset_caches_and_cli(tmp_path, monkeypatch, capsys):
    from botorl.cli import main as botorl_main
    from botorl.data.generate import cache_path, cached_datasets, ensure_dataset

    monkeypatch.setenv("BOTORL_DATA_DIR", str(tmp_path))
    ds = ensure_dataset("bandit-1d", 50, 1, progress=False)
    assert cached_datasets("bandit-1d") == [cache_path("bandit-1d", 50, 1)]
    again = ensure_dataset("bandit-1d", 50, 1)
    np.testing.assert_array_equal(again.actions, ds.actions)
    assert again.metadata["botorl"]["seed"] == 1
    assert botorl_main(["data", "generate", "bandit-1d", "--steps", "50", "--seed", "1"]) == 0
    assert "found cached" in capsys.readouterr().out
    assert botorl_main(["data", "info", "bandit-1d", "--json"]) == 0
    out = capsys.readouterr().out
    assert '"transitions": 50' in out and '"episodes": 50' in out
    assert botorl_main(["data", "info", "bandit-pinwheel"]) == 2
    assert "botorl data generate bandit-pinwheel" in capsys.readouterr().err
    assert botorl_main(["data", "generate", "nope-task"]) == 2
    assert botorl_main(["data", "info", str(cache_path("bandit-1d", 50, 1))]) == 0
    assert "transitions" in capsys.readouterr().out

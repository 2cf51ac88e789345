"""The maze2d-style pointmaze generator: determinism, agreement with the env, labels."""

from __future__ import annotations

import numpy as np
import pytest

from botorl.data.generators.pointmaze import generate, generate_large
from botorl.envs.pointmaze import MAZES, SUCCESS_RADIUS, cell_to_xy
from botorl.envs.registry import get_task


@pytest.fixture(scope="module")
def umaze():
    return generate("umaze", 20_000, seed=0, progress=False)


def test_deterministic_for_a_seed():
    a = generate_large(2_000, seed=7, progress=False)
    b = generate_large(2_000, seed=7, progress=False)
    c = generate_large(2_000, seed=8, progress=False)
    for key in ("observations", "actions", "rewards", "next_observations", "terminals", "episode_ends"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    assert not np.array_equal(a.actions, c.actions)


def test_replaying_actions_in_the_env_gives_the_same_next_observations():
    ds = generate("medium", 1_000, seed=3, progress=False)
    env = get_task("pointmaze-medium").make_env(seed=0)
    env.reset()
    task = env.env
    start = 100
    o = ds.observations[start].astype(np.float64)
    task.set_state(o[:2], o[2:])
    worst = 0.0
    for t in range(start, start + 300):
        obs, *_ = env.step(ds.actions[t])
        worst = max(worst, float(np.abs(obs - ds.next_observations[t]).max()))
    # float32 storage of the start state and of the (1e-5-clipped) actions: errors ~1e-4
    assert worst < 1e-3, worst


def test_rewards_and_terminals_are_those_of_the_evaluation_goal(umaze):
    ds = umaze
    spec = MAZES["umaze"]
    goal = cell_to_xy(spec.maze_map, spec.goal_cell)
    near = np.linalg.norm(ds.next_observations[:, :2] - goal, axis=1) <= SUCCESS_RADIUS
    np.testing.assert_array_equal(ds.rewards == 1.0, near)
    np.testing.assert_array_equal(ds.terminals, near)
    assert near.sum() > 10  # the planner visits the evaluation goal
    assert np.all(ds.episode_ends[ds.terminals])
    assert set(np.unique(ds.rewards)) <= {0.0, 1.0}


def test_one_continuous_trajectory_with_bounded_actions(umaze):
    ds = umaze
    np.testing.assert_array_equal(ds.observations[1:], ds.next_observations[:-1])
    assert np.abs(ds.actions).max() <= 1.0
    assert ds.obs_dim == 4 and ds.action_dim == 2
    n_ends = int(ds.episode_ends.sum())
    assert n_ends > ds.terminals.sum()  # planner goal switches end episodes too (timeouts)
    # the point moves around the maze: it visits every free cell of the U
    cells = {(int(np.floor(2.5 - y)), int(np.floor(x + 2.5))) for x, y in ds.observations[:, :2]}
    assert {(1, 1), (1, 3), (3, 1), (3, 3), (2, 3)} <= cells

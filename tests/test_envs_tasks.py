"""Task registry and env wrappers: shapes, success/termination semantics, errors."""

from __future__ import annotations

import numpy as np
import pytest

from botorl.envs import compat
from botorl.envs.registry import get_task, list_tasks
from botorl.errors import ConfigError

PAPER = {
    "antmaze-large-diverse-v2": (-1.0, 100_000, -30.0),
    "antmaze-large-play-v2": (-0.7, 100_000, -20.0),
    "kitchen-partial-v0": (0.8, 250_000, -20.0),
    "kitchen-mixed-v0": (1.0, 250_000, -20.0),
    "door-binary-v0": (0.0, 100_000, -20.0),
    "pen-binary-v0": (-0.9, 100_000, -20.0),
}


def _bandit_available() -> bool:
    try:
        import botorl.data.generators.bandit  # noqa: F401
    except ImportError:
        return False
    return True


def _env_tasks():
    names = [t.name for t in list_tasks() if not t.name.startswith("bandit") or _bandit_available()]
    return names


@pytest.mark.parametrize("name", _env_tasks())
def test_env_resets_and_steps_with_contract_shapes(name):
    spec = get_task(name)
    env = spec.make_env(seed=0)
    assert env.observation_space.shape == (spec.obs_dim,)
    assert env.action_space.shape == (spec.action_dim,)
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    obs, info = env.reset()
    assert obs.shape == (spec.obs_dim,) and obs.dtype == np.float32
    assert 0.0 <= info["success"] <= 1.0
    for _ in range(3):
        obs, r, term, trunc, info = env.step(env.action_space.sample())
        assert obs.shape == (spec.obs_dim,) and obs.dtype == np.float32
        assert np.isfinite(r) and 0.0 <= info["success"] <= 1.0
        if term or trunc:
            obs, info = env.reset()
    env.close()


def test_seeded_env_is_reproducible():
    spec = get_task("pointmaze-umaze")
    a, b = spec.make_env(seed=3), spec.make_env(seed=3)
    oa, _ = a.reset()
    ob, _ = b.reset()
    np.testing.assert_array_equal(oa, ob)
    for _ in range(5):
        act = np.array([0.3, -0.2], np.float32)
        np.testing.assert_array_equal(a.step(act)[0], b.step(act)[0])


def test_registry_settings():
    assert len(list_tasks()) == len({t.name for t in list_tasks()})
    for name, (alpha, steps, log_sigma) in PAPER.items():
        spec = get_task(name)
        assert (spec.paper.alpha, spec.paper.boto_steps, spec.paper.log_sigma) == (alpha, steps, log_sigma)
        assert not spec.generated
    assert (get_task("antmaze-large-play-v2").reward_scale, get_task("antmaze-large-play-v2").reward_bias) == (10, -5)
    assert (get_task("pen-binary-v0").reward_scale, get_task("pen-binary-v0").reward_bias) == (10, 5)
    assert (get_task("kitchen-mixed-v0").reward_scale, get_task("kitchen-mixed-v0").reward_bias) == (1, -4)
    assert get_task("antmaze-large-diverse-v2").networks.critic == (256,) * 4
    assert get_task("kitchen-partial-v0").networks.actor == (512,) * 3
    assert get_task("door-binary-v0").networks.critic == (512,) * 3
    assert [get_task(n).max_episode_steps for n in ("pen-binary-v0", "door-binary-v0", "kitchen-partial-v0")] == [100, 200, 280]
    assert get_task("kitchen-partial-v0").success_mode == "last"
    assert get_task("pointmaze-large").generated and get_task("pointmaze-large").paper is None


def test_unknown_task_names_the_valid_ones_and_a_close_match():
    with pytest.raises(ConfigError) as err:
        get_task("antmaze-large-divers-v2")
    msg = str(err.value)
    assert "antmaze-large-diverse-v2" in msg and "Did you mean" in msg and "pointmaze-large" in msg


def test_antmaze_terminates_with_reward_one_at_the_goal():
    env = get_task("antmaze-large-diverse-v2").make_env(seed=0)
    env.reset()
    inner = env.unwrapped
    qpos = inner.ant_env.data.qpos.copy()
    qpos[:2] = inner.goal
    inner.ant_env.set_state(qpos, np.zeros_like(inner.ant_env.data.qvel))
    obs, r, term, trunc, info = env.step(np.zeros(8, np.float32))
    assert (r, term, info["success"]) == (1.0, True, 1.0)
    np.testing.assert_allclose(obs[:2], inner.goal, atol=0.1)  # obs starts with (x, y)


def test_antmaze_uses_d4rl_start_and_goal_cells():
    env = get_task("antmaze-large-play-v2").make_env(seed=1)
    obs, _ = env.reset()
    inner = env.unwrapped
    start = inner.maze.cell_rowcol_to_xy(np.array([1, 1]))
    goal = inner.maze.cell_rowcol_to_xy(np.array([7, 9]))
    assert np.all(np.abs(obs[:2] - start) <= 1.0 + 1e-6)  # +-0.25 cells of noise, cells are 4 wide
    assert np.all(np.abs(inner.goal - goal) <= 1.0 + 1e-6)


def test_door_terminates_at_first_success():
    env = get_task("door-binary-v0").make_env(seed=0)
    env.reset()
    inner = env.unwrapped
    obs, r, term, _, info = env.step(np.zeros(28, np.float32))
    assert (r, term, info["success"]) == (-1.0, False, 0.0)
    qpos, qvel = inner.data.qpos.copy(), np.zeros_like(inner.data.qvel)
    qpos[inner.door_hinge_addrs] = 1.5
    inner.set_state(qpos, qvel)
    obs, r, term, _, info = env.step(np.zeros(28, np.float32))
    assert obs[28] >= 1.35
    assert (r, term, info["success"]) == (0.0, True, 1.0)


def test_pen_binary_reward_from_goal_achieved():
    from botorl.envs.adroit import AdroitBinaryTask

    import gymnasium as gym

    class Stub(gym.Env):
        observation_space = gym.spaces.Box(-np.inf, np.inf, (45,))
        action_space = gym.spaces.Box(-1.0, 1.0, (24,), dtype=np.float32)
        t = 0

        def reset(self, *, seed=None, options=None):
            self.t = 0
            return np.zeros(45), {}

        def step(self, a):
            self.t += 1
            return np.zeros(45), 10.0, False, False, {"success": self.t == 2}

    env = AdroitBinaryTask(Stub(), 45)
    env.reset()
    assert env.step(np.zeros(24))[1:3] == (-1.0, False)
    _, r, term, _, info = env.step(np.zeros(24))
    assert (r, term, info["success"]) == (0.0, True, 1.0)
    pen = get_task("pen-binary-v0").make_env(0)
    assert pen.observation_space.shape == (45,) and pen._max_episode_steps == 100


def test_kitchen_reward_counts_target_subtasks_and_terminates_at_four():
    from botorl.envs.kitchen import PARTIAL_TASKS

    env = get_task("kitchen-partial-v0").make_env(seed=0)
    env.reset()
    inner = env.unwrapped
    data = inner.data
    zero = np.zeros(9, np.float32)

    def put(**targets):
        qpos = data.qpos.copy()
        for idx, val in targets.values():
            qpos[idx] = val
        inner.robot_env.set_state(qpos, np.zeros_like(data.qvel))

    goals = {
        "microwave": ([22], [-0.75]),
        "slide": ([19], [0.37]),
        "light": ([17, 18], [-0.69, -0.05]),
        "kettle": (list(range(23, 30)), [-0.23, 0.75, 1.62, 0.99, 0.0, 0.0, -0.06]),
        "burner": ([11, 12], [-0.88, -0.01]),  # not a target of kitchen-partial
    }
    put(microwave=goals["microwave"], burner=goals["burner"])
    _, r, term, _, info = env.step(zero)
    assert (r, term, info["success"]) == (1.0, False, 0.25)
    # remove_task_when_completed=False: the done sub-task keeps counting on later steps
    _, r, term, _, _ = env.step(zero)
    assert (r, term) == (1.0, False)
    put(slide=goals["slide"], light=goals["light"], kettle=goals["kettle"])
    _, r, term, _, info = env.step(zero)
    assert (r, term, info["success"]) == (4.0, True, 1.0)
    assert len(PARTIAL_TASKS) == 4


def test_kitchen_mixed_targets_are_d4rl():
    env = get_task("kitchen-mixed-v0").make_env(seed=0)
    assert set(env.unwrapped.goal) == {"microwave", "kettle", "bottom burner", "light switch"}


def test_pointmaze_goal_is_fixed_and_terminal():
    from botorl.envs.pointmaze import MAZES, cell_to_xy

    env = get_task("pointmaze-medium").make_env(seed=0)
    obs, _ = env.reset()
    spec = MAZES["medium"]
    goal = cell_to_xy(spec.maze_map, spec.goal_cell)
    np.testing.assert_allclose(env.unwrapped.goal, goal)
    assert np.all(np.abs(obs[:2] - cell_to_xy(spec.maze_map, spec.start_cell)) <= 0.25 + 1e-6)
    task = env.env  # TimeLimit -> PointMazeTask
    task.set_state(goal + 0.1, [0.0, 0.0])
    obs, r, term, _, info = env.step(np.zeros(2, np.float32))
    assert (r, term, info["success"]) == (1.0, True, 1.0)


def test_kitchen_compat_patch_is_needed_and_applied():
    import mujoco

    from gymnasium_robotics.utils import mujoco_utils

    compat.apply()
    if compat.needs_patch():
        assert mujoco_utils.get_joint_qpos is compat.get_joint_qpos
    model = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint name='h' type='hinge'/><geom size='.1'/></body>"
        "<body pos='1 0 0'><freejoint name='f'/><geom size='.1'/></body></worldbody></mujoco>"
    )
    data = mujoco.MjData(model)
    assert compat.get_joint_qpos(model, data, "h").shape == (1,)
    assert compat.get_joint_qpos(model, data, "f").shape == (7,)
    assert compat.get_joint_qvel(model, data, "f").shape == (6,)


def test_generated_task_loads_through_ensure_dataset():
    # conftest points BOTORL_DATA_DIR at a temp folder: generated, cached, then read back
    from botorl.data.tasks import data_status, load_task_data

    spec = get_task("pointmaze-umaze")
    ds = load_task_data(spec, steps=2_000, seed=1, progress=False)
    assert (ds.obs_dim, ds.action_dim) == (spec.obs_dim, spec.action_dim)
    assert data_status(spec)[0] == "generated-cached"
    again = load_task_data(spec, steps=2_000, seed=1, progress=False)
    np.testing.assert_allclose(again.observations, ds.observations)


def test_calql_task_without_a_path_says_how_to_get_the_data():
    from botorl.data.tasks import load_task_data
    from botorl.errors import DatasetNotFoundError

    with pytest.raises(DatasetNotFoundError, match="Cal-QL"):
        load_task_data(get_task("pen-binary-v0"))

"""The loop every stage runs (``stages.stage_loop``; pre-training and the BOTO stage here), on a
``Stage`` whose update counts, of two members: its calls, checks, logs and checkpoints against the points
worked out by hand for 10 steps in calls of 3, logs every 4 and checkpoints every 6."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from botorl.configs.methods import get_method
from botorl.configs.schema import OnlineConfig
from botorl.data.dataset import RewardTransform
from botorl.data.replay import ReplayBuffer
from botorl.pipeline.online import OnlineState
from botorl.pipeline.stages import Schedule, Stage, stage_loop


def _run(start: int = 0, check_every_call: bool = False):
    seen: dict[str, list] = {"calls": [], "checks": [], "logs": [], "saves": []}

    class Probe(Stage):
        """Two members; member i's metric "x" is step + i * k, a 2-d metric is not a scalar and is left out."""

        name = "probe"

        def chunk(self, step):
            return min(3, 10 - step)

        def update(self, agents, step, k):
            seen["calls"].append((step, k))
            return agents + k, {"x": np.array([step, step + k], np.float32), "m": np.zeros((2, 3))}

        def check(self, step, ms):
            seen["checks"].append((step, ms))

        def log(self, step, ms):
            seen["logs"].append((step, ms))

        def save(self, step, agents, interrupted):
            seen["saves"].append((step, agents, interrupted))

    probe = Probe(SimpleNamespace(cfg=SimpleNamespace(progress=True), member_cfgs=[None, None]), Schedule(10, 4, 6))
    probe.check_every_call = check_every_call
    agents = stage_loop(probe, start, start, "probe")
    return agents, probe.bar.n, seen


def test_stage_loop_points_and_window_means():
    agents, n, seen = _run()
    assert agents == 10 and n == 10
    assert seen["calls"] == [(0, 3), (3, 3), (6, 3), (9, 1)]
    # steps 3, 6, 9, 10: logs where step // 4 passes a multiple and at the end, a checkpoint at 6
    # (the end's is the runner's); a log point's row is the mean over the calls since the last
    assert seen["checks"] == seen["logs"] == [(6, [{"x": 1.5}, {"x": 4.5}]), (9, [{"x": 6.0}, {"x": 9.0}]),
                                             (10, [{"x": 9.0}, {"x": 10.0}])]
    assert seen["saves"] == [(6, 6, False)]


def test_stage_loop_checks_every_call_and_resumes_on_the_same_points():
    _, _, seen = _run(check_every_call=True)
    assert [s for s, _ in seen["checks"]] == [3, 6, 9, 10]
    assert seen["logs"][0] == (6, [{"x": 3.0}, {"x": 6.0}])  # the log point's own call
    agents, n, resumed = _run(start=6)
    assert agents == 10 and n == 10
    assert resumed["calls"] == [(6, 3), (9, 1)] and resumed["logs"] == seen["logs"][1:] and resumed["saves"] == []


class _ThreeStepEnv:
    """Episodes of 3 steps (time limit) whose info["success"] is 1, 1, 0: "any" says 1, "last" 0."""

    def reset(self, seed=None):
        self.t = 0
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.t += 1
        return np.full(2, self.t, np.float32), 1.0, False, self.t == 3, {"success": float(self.t < 3)}

    def close(self):
        pass


@pytest.mark.parametrize("mode, success", [("any", 1.0), ("last", 0.0)])
def test_the_online_loop_counts_success_by_the_tasks_rule_and_records_the_warmups_episode_ends(mode, success):
    """The warm-up is the online loop's first steps: its episodes' success follows the task's
    rule (kitchen's "last" too, where the old warm-up always took the maximum), its rows go into
    the buffer with transformed rewards, and while ``ended`` is a list the episode ends land in it."""
    state = OnlineState([_ThreeStepEnv()], ReplayBuffer(16, 2, 1, members=1), [np.random.default_rng(0)],
                        OnlineConfig(), get_method("wsrl"), RewardTransform(2.0, -1.0), mc_returns=None,
                        success_mode=mode)
    state.reset([0])
    state.ended = [[]]
    for _ in range(7):
        state.act(np.zeros((1, 1), np.float32))
    assert state.recent_success == [[success, success]] and state.episodes == [2]
    assert state.ended == [[2, 5]] and state.ep_rows == [[6]]
    assert len(state.buffer) == 7 and np.all(state.buffer.state_dict()["rewards"] == 1.0)  # 2 * 1 - 1

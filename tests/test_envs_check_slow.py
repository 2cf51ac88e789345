"""`botorl tasks check` passes for every task (1,000 random-action steps each; slow)."""

from __future__ import annotations

import pytest

from botorl.envs.cli import check_task, main
from botorl.envs.registry import get_task, list_tasks


@pytest.mark.slow
@pytest.mark.parametrize("name", [t.name for t in list_tasks()])
def test_tasks_check_passes(name):
    r = check_task(get_task(name), steps=1000, seed=0)
    assert r["problems"] == []
    assert r["steps_per_s"] > 0


def test_cli_check_and_list(capsys):
    assert main(["check", "pointmaze-umaze", "--steps", "50"]) == 0
    assert "ok" in capsys.readouterr().out
    assert main([]) == 0
    out = capsys.readouterr().out
    assert "antmaze-large-diverse-v2" in out and "bandit-1d" in out

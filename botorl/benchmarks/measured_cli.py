"""One process that ``botorl bench --paper`` measures (its wall time and peak resident size by
``wait4``; botorl/benchmarks/paper.py): ``python -m botorl.benchmarks.measured_cli STATS ARGS``.

``ARGS`` is a botorl command line (``run ...``), run as ``botorl`` would, or ``--time-eval OUT
MEMBERS EPISODES`` (``paper.time_evaluation``: a run's evaluation, timed as the run evaluates).
``STATS`` receives, as JSON, the evaluation's figures and the device's peak memory at the
process's end (``paper.device_memory``; None on a CPU).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from botorl.benchmarks.paper import device_memory, time_evaluation
from botorl.cli import main as botorl_main
from botorl.io import atomic_write_bytes


def main(argv: list[str]) -> int:
    stats, rest = Path(argv[0]), argv[1:]
    result, code = {}, 0
    if rest[:1] == ["--time-eval"]:
        result = time_evaluation(Path(rest[1]), int(rest[2]), int(rest[3]))
    else:
        code = botorl_main(rest)
    atomic_write_bytes(stats, json.dumps({**result, **device_memory()}).encode())
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""The sweep's trial launcher: ``python -m botorl.experiments.child --parent PID [--cpus 0,1] -- CMD...``.

Sets up the trial process, then execs CMD (same pid): it dies with the sweep (PR_SET_PDEATHSIG;
it does not start if the sweep is gone) and stays on its cores. Not a ``preexec_fn``: Python
between fork and exec in the sweep, which may hold JAX's threads, can deadlock on their locks.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1


def launcher(cmd: list[str], parent_pid: int, cpus=None) -> list[str]:
    """The command line that runs ``cmd`` under this launcher."""
    head = [sys.executable, "-m", "botorl.experiments.child", "--parent", str(parent_pid)]
    if cpus:
        head += ["--cpus", ",".join(str(c) for c in cpus)]
    return head + ["--", *cmd]


def main(argv: list[str]) -> int:
    if "--" not in argv:
        print("usage: python -m botorl.experiments.child --parent PID [--cpus 0,1] -- CMD...", file=sys.stderr)
        return 2
    i = argv.index("--")
    opts, cmd = argv[:i], argv[i + 1:]
    args = dict(zip(opts[0::2], opts[1::2]))
    with contextlib.suppress(Exception):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if "--parent" in args and os.getppid() != int(args["--parent"]):  # the sweep died before prctl
        return 1
    if args.get("--cpus"):
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, {int(c) for c in args["--cpus"].split(",")})
    os.execvp(cmd[0], cmd)
    return 127  # not reached: execvp raises OSError when it cannot run cmd


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""The sweep's local backends, ``local`` (``--workers`` trial processes, each pinned to its own
block of the cores) and ``sequential`` (one trial at a time, the machine's full thread pools),
and what every backend shares (a trial's environment, pid files, stopping what a sweep recorded)."""

from __future__ import annotations

import contextlib
import functools
import os
import re
import secrets
import signal
import socket
import subprocess
import time
from pathlib import Path
from typing import Any

from botorl.experiments.child import launcher
from botorl.io import atomic_write_json, open_regular, read_json_object
from botorl.jaxsetup import usable_cores

ABORT_WAIT_S = 60.0  # a stopped trial's last update chunk and checkpoint; SLURM's default KillWait is 30 s
TRIAL_PID = ".sweep-trial.json"  # pid/host of the attempt now running (orphan detection)

# A sweep signals only processes it started: each carries this variable with the sweep's secret
# token in its environment (inherited by Ray's daemons, the trials and their children), which
# /proc/PID/environ shows to this user only. A pid and start time in a file name a process; they
# do not prove that a sweep started it (anyone can read both from /proc). The token names the sweep
# folder by its identity (device, inode): a file can copy a token, but a copy of the folder (another
# inode) names none of the original sweep's processes, even those that do carry its token.
TOKEN_ENV = "BOTORL_SWEEP_TOKEN"
_TOKEN_FORM = re.compile(r"[0-9a-f]{32}-[0-9a-f]+-[0-9a-f]+")


@functools.cache
def _secret() -> str:
    return secrets.token_hex(16)  # this process's, made once (128 random bits)


def folder_identity(path: str | os.PathLike) -> str | None:
    """``DEVICE-INODE`` of the folder ``path`` (None if it is gone): what a move keeps and a copy does not."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return f"{st.st_dev:x}-{st.st_ino:x}"


def sweep_token(out: str | os.PathLike) -> str:
    """This process's token for its sweep of the folder ``out``: the secret and the folder's identity."""
    return f"{_secret()}-{folder_identity(out)}"


def own_token(token: Any, out: str | os.PathLike) -> bool:
    """Whether ``token`` (read back from a file) is one a sweep made for the folder ``out`` as it is now."""
    ident = folder_identity(out)
    return (ident is not None and isinstance(token, str) and _TOKEN_FORM.fullmatch(token) is not None
            and token.endswith(f"-{ident}"))


def carries_token(pid: int, token: Any) -> bool:
    """Whether process ``pid`` has ``TOKEN_ENV=token`` in its environment (False when it cannot be
    read: another user's process, or gone)."""
    if not isinstance(token, str) or not _TOKEN_FORM.fullmatch(token):
        return False
    try:
        with open(f"/proc/{int(pid)}/environ", "rb") as f:
            env = f.read(1 << 22)
    except (OSError, ValueError):
        return False
    return f"{TOKEN_ENV}={token}".encode() in env.split(b"\0")

# BLAS/OpenMP limited to one thread for a trial pinned to one core, where more only add context
# switches. XLA needs no flag: its CPU thread pools are sized from the affinity mask, and any
# XLA_FLAGS value is part of the persistent compile cache's key (pinned trials would recompile
# what unpinned runs cached). Extra flags for pinned trials: $BOTORL_SWEEP_XLA_FLAGS.
SINGLE_THREAD_ENV = dict.fromkeys(("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                   "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS", "TF_NUM_INTRAOP_THREADS",
                                   "TF_NUM_INTEROP_THREADS"), "1")


def trial_env(token: str, single_thread: bool) -> dict[str, str]:
    """A trial's environment: this process's with the sweep's ``token`` (which lets a later sweep
    stop the trial if orphaned) and, for a trial on one core, SINGLE_THREAD_ENV."""
    env = {**os.environ, TOKEN_ENV: token}
    if single_thread:
        env.update(SINGLE_THREAD_ENV)
        if extra := env.get("BOTORL_SWEEP_XLA_FLAGS", "").strip():
            env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {extra}".strip()
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def isolated(env: dict[str, str]) -> dict[str, str]:
    """``env`` for a trial that imports nothing from the folders it runs in (a sweep folder may hold
    anything, e.g. a planted numpy.py): PYTHONSAFEPATH, so Python puts neither the working directory
    (``-m``) nor a script's folder on sys.path, in the trial and in any Python it starts; and only
    PYTHONPATH's absolute entries, as an empty or relative one names the working directory."""
    entries = [e for e in env.get("PYTHONPATH", "").split(os.pathsep) if os.path.isabs(e)]
    out = {k: v for k, v in env.items() if k != "PYTHONPATH"}
    return {**out, "PYTHONSAFEPATH": "1", **({"PYTHONPATH": os.pathsep.join(entries)} if entries else {})}


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _stat_fields(pid: int) -> list[bytes] | None:
    """The fields of /proc/PID/stat after the command name (field 3 onwards)."""
    try:
        raw = Path(f"/proc/{int(pid)}/stat").read_bytes()
        return raw[raw.rindex(b")") + 2:].split()
    except (OSError, ValueError):
        return None


def start_time(pid: int) -> int | None:
    """When ``pid`` started (clock ticks since boot, field 22 of /proc/PID/stat). A pid is
    reused; the pair (pid, start time) names one process for good."""
    f = _stat_fields(pid)
    try:
        return int(f[19]) if f and f[0] != b"Z" else None  # a zombie has ended (its parent has not reaped it)
    except (ValueError, IndexError):
        return None


def process_record(pid: int, token: str) -> dict[str, Any] | None:
    """What a sweep writes down to stop a process of its own later: its pid, start time and the
    token the sweep put in its environment."""
    start = start_time(pid)
    return None if start is None else {"pid": int(pid), "start": start, "token": token}


def recorded_alive(record: Any, out: str | os.PathLike) -> int | None:
    """The pid of ``record`` (``process_record``, as read back from a file) if that very process
    still runs, is this user's and carries the record's token in its environment, a token made for
    the sweep folder ``out``, else None: a record names a process, never a pattern, and the token
    proves that a sweep of this folder started it."""
    if not isinstance(record, dict) or not own_token(record.get("token"), out):
        return None
    pid, start = record.get("pid"), record.get("start")
    if type(pid) is not int or type(start) is not int or pid <= 1 or pid == os.getpid():
        return None
    try:
        mine = Path(f"/proc/{pid}").stat().st_uid == os.getuid()
    except OSError:
        return None
    return pid if mine and start_time(pid) == start and carries_token(pid, record.get("token")) else None


def descendants(pids: list[int]) -> list[int]:
    """Every live descendant of ``pids`` (children, their children, ...)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            f = _stat_fields(int(entry.name))
            if f and len(f) > 1 and f[1].isdigit():
                children.setdefault(int(f[1]), []).append(int(entry.name))
    out, todo = [], list(pids)
    while todo:
        for c in children.get(todo.pop(), []):
            if c not in out and c not in pids:
                out.append(c)
                todo.append(c)
    return out


def stop_recorded(records: Any, out: str | os.PathLike, timeout: float = 10.0) -> int:
    """SIGTERM (then SIGKILL) the processes ``records`` name that still run (same pid, same
    start time, this user's, a token of the sweep folder ``out``), with their descendants of the
    same token; nothing else. The number stopped."""
    victims: list[dict[str, Any]] = []
    for rec in records if isinstance(records, list) else []:
        root = recorded_alive(rec, out)
        if root is None:
            continue
        token = rec["token"]  # a descendant is stopped only if it carries the same token
        victims += [r for p in [root] + descendants([root]) if carries_token(p, token)
                    and (r := process_record(p, token)) is not None and r not in victims]
    for r in victims:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(r["pid"], signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(recorded_alive(r, out) for r in victims):
        time.sleep(0.1)
    for r in victims:
        if recorded_alive(r, out):
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(r["pid"], signal.SIGKILL)
    return len(victims)


def stop_orphan(run_dir: Path, out: Path, timeout: float = 15.0) -> bool:
    """Stop a trial process left from an earlier sweep of the folder ``out`` (same host only): the
    process the trial's pid file records (pid, start time and token), if it still runs, carries a
    token of this very folder and still works on this directory."""
    info = read_json_object(Path(run_dir) / TRIAL_PID)
    if info is None or info.get("host") != socket.gethostname():
        return False
    pid = recorded_alive(info, out)
    if pid is None or str(Path(run_dir).resolve()) not in cmdline(pid):
        return False
    stop_recorded([info], out, timeout)
    return True


def spawn(cmd: list[str], log, run_dir, env: dict, block=None, **record) -> subprocess.Popen:
    """``cmd`` started under the launcher (child.py) on the cores ``block``, in ``run_dir`` with an
    ``isolated`` module path, its output appended to ``log``, and its pid file (``TRIAL_PID``: pid,
    start time, host and ``record``) written."""
    with os.fdopen(open_regular(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT), "ab") as logf:
        proc = subprocess.Popen(launcher(cmd, os.getpid(), block), stdout=logf, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=isolated(env), cwd=run_dir)
    atomic_write_json(Path(run_dir) / TRIAL_PID, {"pid": proc.pid, "start": start_time(proc.pid),
                                                  "host": socket.gethostname(), "token": env.get(TOKEN_ENV),
                                                  **record})
    return proc


class LocalBackend:
    """Trials as child processes of the sweep (``sweep`` is the ``sweep.Sweep``)."""

    def __init__(self, sweep):
        self.sweep = sweep
        self.pinned = sweep.opt.backend == "local"

    def start(self, pending: int) -> int:
        """The number of trials to run at once."""
        opt = self.sweep.opt
        self.workers = 1 if not self.pinned else (max(1, int(opt.workers)) if opt.workers else len(usable_cores()))
        return min(self.workers, max(1, pending))

    def core_block(self, slot: int) -> list[int]:
        """The cores of worker slot ``slot``: the sweep's cores split into one contiguous block
        per worker, so W workers on C cores get C // W cores each (one when W >= C)."""
        cores = usable_cores()
        w = min(self.workers, len(cores))
        k = slot % w
        return cores[k * len(cores) // w:(k + 1) * len(cores) // w]

    def launch(self, trial, slot: int | None) -> subprocess.Popen:
        sweep = self.sweep
        run_dir, cmd, log = sweep.prepare(trial)
        block = self.core_block(slot) if (slot is not None and self.pinned) else None
        # "cpu": the one core of a single-core block (the manifest's field before blocks), else None
        cpu = block[0] if block and len(block) == 1 else None
        proc = spawn(cmd, log, run_dir, trial_env(sweep_token(sweep.out), cpu is not None), block, cpu=cpu, cpus=block)
        sweep.entry(trial).update(pid=proc.pid, cpu=cpu, cpus=block)
        return proc

    def poll(self, running: dict) -> list[tuple[int, int]]:
        """(key, exit code) of every finished trial."""
        return [(key, code) for key, (_, proc) in running.items() if (code := proc.poll()) is not None]

    def abort(self, running: dict, signum: int = signal.SIGTERM) -> None:
        """Forward ``signum`` (the signal that stopped the sweep): each trial checkpoints and exits
        (pipeline/preempt.py); one still running after ``ABORT_WAIT_S`` is killed."""
        for _, proc in running.values():
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signum)
        deadline = time.monotonic() + ABORT_WAIT_S
        for _, proc in running.values():
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def close(self) -> Any:
        return None

"""The ``botorl`` command line.

Each sub-command lives next to the code it drives and exposes ``main(argv) -> int``; this
module only dispatches, so ``botorl --help`` stays fast (no JAX import) and a user error
(``BotorlError``) becomes a one-paragraph message with exit code 2.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import re
import signal
import sys

from botorl import __version__
from botorl.errors import BotorlError, Interrupted
from botorl.io import IO_FAULTS
from botorl.pipeline.preempt import handling

# name -> (module:function, one-line help). Imported lazily.
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("botorl.pipeline.cli:run_main", "run one method on one task, offline to online"),
    "resume": ("botorl.pipeline.cli:resume_main", "continue a run directory from its last checkpoint"),
    "eval": ("botorl.pipeline.cli:eval_main", "evaluate the last checkpoint of a run directory"),
    "export": ("botorl.pipeline.cli:export_main", "export a run's policy to ONNX, with its contract"),
    "data": ("botorl.data.cli:main", "generate datasets and show their statistics"),
    "tasks": ("botorl.envs.cli:main", "list the tasks, or check one's environment"),
    "train-ant": ("botorl.experts.ant_train:main", "train the goal-reaching ant behind the antmaze data"),
    "bandit": ("botorl.boto.bandit:main", "reproduce the paper's bandit figures 2 and 3"),
    "bench": ("botorl.benchmarks.suite:main", "measure update speed, or what a paper run costs"),
    "sweep": ("botorl.experiments.cli:sweep_main", "run a grid of tasks x methods x seeds x alphas"),
    "report": ("botorl.experiments.cli:report_main", "Table 1 and Figure 5 from finished runs"),
    "study": ("botorl.experiments.study_cli:main", "run a pre-registered study file, resumably, and report it"),
}


PREEMPTIBLE = ("run", "resume", "sweep", "study")


def _usage() -> str:
    width = max(len(n) for n in COMMANDS)
    lines = ["usage: botorl <command> [options]", "", "commands:"]
    lines += [f"  {name.ljust(width)}  {help_}" for name, (_, help_) in COMMANDS.items()]
    lines += ["", "`botorl <command> --help` shows the options of a command.", "",
              "Start here (README):",
              "  pip install -e . && botorl run                      # a whole BOTO run on pointmaze-umaze",
              '  pip install -e ".[test]" && python3 -m pytest -q    # the tests']
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        # a bare `botorl` trains nothing: it says what there is (the main job is `botorl run`)
        print(_usage())
        return 0
    if argv[0] in ("-V", "--version"):
        print(__version__)
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"botorl: unknown command {name!r}.\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name, func_name = COMMANDS[name][0].split(":")
    try:
        # the commands that train stop at a step with a checkpoint on SIGTERM / SIGINT
        # (botorl/pipeline/preempt.py); the others keep Python's defaults
        with handling() if name in PREEMPTIBLE else contextlib.nullcontext():
            func = getattr(importlib.import_module(module_name), func_name)
            code = func(rest)
    except BotorlError as err:
        print(f"botorl {name}: error: {err}", file=sys.stderr)
        return err.exit_code
    except Interrupted as err:
        what = signal.Signals(err.signum).name
        if err.how:
            at = f"; checkpoint {err.checkpoint}" if err.checkpoint else ""
            print(f"botorl {name}: stopped by {what}{at}. Continue with: {err.how}", file=sys.stderr)
        else:
            print(f"botorl {name}: stopped by {what} before any work was saved; nothing to resume.", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print(f"botorl {name}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # stdout was closed early (`botorl run --help | head`): no traceback, and none at exit
        # when Python flushes stdout again.
        _silence_stdout()
        return 2
    except OSError as err:
        m = re.search(r"errno = (\d+)", str(err))  # h5py's OSErrors carry their errno in the text only
        code = err.errno if err.errno is not None else (int(m.group(1)) if m else None)
        if code not in IO_FAULTS:
            raise
        where = f" {err.filename}" if err.filename else ""
        print(f"botorl {name}: error: cannot write{where}: {IO_FAULTS[code]} ({err.strerror or os.strerror(code)}). "
              f"Free space, or write somewhere writable (--out).", file=sys.stderr)
        return 2
    except SystemExit as err:
        # argparse / tyro exit after printing help or a usage error; flush here so that a
        # closed pipe surfaces now, not as a traceback at interpreter exit
        if not _flushed():
            return 2
        raise err
    return int(code or 0) if _flushed() else 2


def _flushed() -> bool:
    """Flush stdout; False (and stdout silenced) when it was closed early (`botorl run --help | head`)."""
    try:
        sys.stdout.flush()
        return True
    except BrokenPipeError:
        _silence_stdout()
        return False


def _silence_stdout() -> None:
    with contextlib.suppress(OSError, ValueError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def console_main() -> None:
    """The `botorl` command: ``main``, then a Ctrl-C during Python's shutdown (atexit handlers;
    JAX's, Ray's and W&B's threads) exits 130 without a traceback. Not in ``main``, which tests
    and `botorl.run` call in-process. Output piped into a reader that stops early (`| head`)
    ends quietly, as other commands do: stdout goes to /dev/null so the exit's flush cannot
    raise again."""
    try:
        code = main()
        sys.stdout.flush()
    except BrokenPipeError:
        _silence_stdout()
        sys.exit(1)

    def exit_130(signum, frame):
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):  # a closed pipe must not stop the exit
                stream.flush()
        os._exit(130)

    signal.signal(signal.SIGINT, exit_130)
    sys.exit(code)


if __name__ == "__main__":
    console_main()

"""The one exception type for problems a user can fix (docs/CONTRACTS.md, "Errors and the CLI"):
the CLI prints the message and exits 2; bugs in botorl stay ordinary exceptions, with a traceback.
A command's number flags carry their range (``Range``), checked in one place (``check_ranges``).
"""

from __future__ import annotations

import dataclasses
import sys
import typing


class BotorlError(Exception):
    """A problem with the user's input, data or configuration (CLI exit code 2)."""

    exit_code = 2


class DatasetNotFoundError(BotorlError):
    """A dataset botorl needs is not on this machine."""


class DataFormatError(BotorlError):
    """A file is not in the format it claims, or its contents are invalid."""


class ConfigError(BotorlError):
    """A configuration value is invalid."""


class TrainingDivergedError(BotorlError):
    """A loss became NaN or inf; the last good checkpoint is kept."""


def warn(message: str) -> None:
    """What botorl tells the user and goes on (stderr; stdout holds a command's result)."""
    print(f"botorl: warning: {message}", file=sys.stderr)


class Interrupted(KeyboardInterrupt):
    """SIGTERM or SIGINT stopped the work (botorl/pipeline/preempt.py); the CLI exits
    128 + ``signum``. A KeyboardInterrupt, so what cleans up after Ctrl-C cleans up after it.
    ``how``: the command that continues the work (if any); ``checkpoint``: where it starts."""

    def __init__(self, signum: int):
        super().__init__(f"signal {signum}")
        self.signum = int(signum)
        self.how: str | None = None
        self.checkpoint: str | None = None

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


@dataclasses.dataclass(frozen=True)
class Range:
    """A number flag's range, inclusive, as ``Annotated[int, Range(1, 1024)]`` metadata of a
    command's dataclass field (tyro ignores it): ``check_ranges`` refuses a value outside it,
    NaN too. ``why``: what the bound protects, for the message."""

    lo: float
    hi: float
    why: str = ""


def check_ranges(args) -> None:
    """ConfigError naming the flag for the first field of the dataclass ``args`` (a command's
    parsed flags) that lies outside its ``Range``; None values (a flag left to its default) pass."""
    hints = typing.get_type_hints(type(args), include_extras=True)
    for f in dataclasses.fields(args):
        bound = next((m for m in getattr(hints[f.name], "__metadata__", ()) if isinstance(m, Range)), None)
        v = getattr(args, f.name)
        if bound is None or v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not bound.lo <= v <= bound.hi:
            flag = "--" + f.name.rstrip("_").replace("_", "-")
            raise ConfigError(f"{flag} {v!r} is out of range: give a number from {bound.lo:,} to {bound.hi:,}"
                              f"{f' ({bound.why})' if bound.why else ''}.")

"""The one exception type for problems a user can fix (docs/CONTRACTS.md, "Errors and the CLI"):
the CLI prints the message and exits 2; bugs in botorl stay ordinary exceptions, with a traceback.
"""

from __future__ import annotations


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

"""The one exception type for problems a user can fix.

Everything that is the user's doing (a file in the wrong format, a missing dataset, a bad
config value) raises ``BotorlError`` with a one-paragraph message that names the thing and
says how to fix it. The CLI prints that message and exits with code 2, never a traceback.
Bugs in botorl itself stay ordinary exceptions so that they do show a traceback.
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
    128 + ``signum``. A KeyboardInterrupt, so code that cleans up after Ctrl-C cleans up after
    it too. ``how``: the command that continues the work, once there is work to continue
    (``botorl resume DIR``); ``checkpoint``: the checkpoint that resume starts from."""

    def __init__(self, signum: int):
        super().__init__(f"signal {signum}")
        self.signum = int(signum)
        self.how: str | None = None
        self.checkpoint: str | None = None

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

"""``python -m botorl.benchmarks``: the same as ``botorl bench --against ...``."""

import sys

from botorl.benchmarks.suite import main
from botorl.errors import BotorlError

if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1:]))
    except BotorlError as err:  # as the CLI does: one paragraph, exit code 2
        print(f"botorl bench: error: {err}", file=sys.stderr)
        sys.exit(err.exit_code)

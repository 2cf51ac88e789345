import sys

from botorl.benchmarks.suite import main

if __name__ == "__main__":
    from botorl.cli import main as cli_main  # noqa: F401  (same error handling as the CLI)
    from botorl.errors import BotorlError

    try:
        sys.exit(main(sys.argv[1:]))
    except BotorlError as err:
        print(f"botorl bench: error: {err}", file=sys.stderr)
        sys.exit(err.exit_code)

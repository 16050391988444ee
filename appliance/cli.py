"""Command-line entry point `extensometer`."""

import sys


def main(argv: list[str] | None = None) -> int:
    """Run the `extensometer` command line; returns the process exit status."""
    del argv
    print("extensometer: no command yet", file=sys.stderr)
    return 2

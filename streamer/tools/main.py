"""The ``ttl`` entry point: every subcommand's options, and the one module that runs it.

Builds the parser of :mod:`ttlcore.cli.main` (the science commands) with the operations
commands of :mod:`streamer.tools.parsers` added, neither of which imports any science, bus or
cluster code; the command's own module (``handler``) is imported only after its arguments
have parsed.  ``ttl --help`` and argument errors thus answer in a fraction of a second
(they took 3-6 s when the entry point imported the whole stack), and ``ttl info`` does not
load Zenoh or Dask.  The conventions every command follows: ``docs/cli.md``.
"""

from __future__ import annotations

import sys

from ttlcore.cli.main import main as _main

from .parsers import register


def main(argv=None) -> int:
    """Run ``ttl`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    return _main(argv, registrars=(register,))


if __name__ == "__main__":
    sys.exit(main())

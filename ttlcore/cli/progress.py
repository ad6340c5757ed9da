"""Progress of long command-line steps, in place on a terminal (tqdm).

The library reports progress as short messages through a ``progress`` callable
(``diagnose(..., progress=say)``, ``run_scenarios(..., progress=...)``); the commands turn
them into one status line that updates in place when standard error is a terminal, and into
plain lines otherwise (logs, pipes).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from tqdm import tqdm


@contextmanager
def status_line(prefix: str, quiet: bool = False, stream=None) -> Iterator[Callable[[str], None]]:
    """A ``say(message)`` callable for the duration of a command step.

    Parameters
    ----------
    prefix : str
        Shown before every message (``"ttl diagnose"``).
    quiet : bool
        Show nothing.
    stream : file, optional
        Default standard error.
    """
    stream = stream or sys.stderr
    start = time.monotonic()
    if quiet:
        yield lambda msg: None
        return
    if not (hasattr(stream, "isatty") and stream.isatty()):
        yield lambda msg: print(f"{prefix}: {msg} ({time.monotonic() - start:.1f} s)", file=stream, flush=True)
        return
    with tqdm(total=None, file=stream, leave=False, bar_format="{desc} [{elapsed}]", dynamic_ncols=True) as bar:
        yield lambda msg: bar.set_description_str(f"{prefix}: {msg}")


@contextmanager
def progress_bar(label: str, quiet: bool = False, stream=None) -> Iterator[Callable[[int, int], None]]:
    """A ``progress(done, total)`` callable for a step of known size (``simulate_to_file``).

    A tqdm bar in place when ``stream`` (default standard error) is a terminal; otherwise a
    plain line at every tenth of the work, so that logs stay readable.
    """
    stream = stream or sys.stderr
    if quiet:
        yield lambda done, total: None
        return
    if not (hasattr(stream, "isatty") and stream.isatty()):
        start, last = time.monotonic(), [-1]

        def line(done: int, total: int) -> None:
            tenth = int(10 * done / total) if total > 0 else 10
            if tenth > last[0]:
                last[0] = tenth
                print(f"{label}: {10 * tenth}% ({time.monotonic() - start:.1f} s)", file=stream, flush=True)

        yield line
        return
    with tqdm(total=1, file=stream, desc=label, leave=True, dynamic_ncols=True) as bar:

        def update(done: int, total: int) -> None:
            bar.total = max(int(total), 1)
            bar.n = min(int(done), bar.total)
            bar.refresh()

        yield update

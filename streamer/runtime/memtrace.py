"""Memory of a stage process, segment by segment: for finding what grows in a long run.

Off by default.  With the environment variable :data:`ENV` (``TTL_MEMTRACE``) set to a
positive integer ``N`` (``ttl run`` passes its environment to the stages;
``bench/soak.py --memtrace N`` sets it), every pipeline stage
(:class:`streamer.runtime.pipeline_stage.PipelineStage`) starts :mod:`tracemalloc` and, after every
segment it handles, logs one line (INFO, on the stage's logger)::

    memory after segment 17: rss 412.3 MB, traced 180.2 MB (peak 260.1 MB)

and every ``N`` segments the ten source lines whose traced memory grew most since the
previous such report, with their size and count of live blocks.  An allocation is charged
to the innermost line of the project (``ttlcore``, ``streamer``, ``stages``) on its stack,
so that an array that numpy or scipy allocated for a stage names the stage's line; one
with no project line on its stack (a library's own thread) to its innermost line.

``rss`` is the resident set size of the process (``/proc/self/statm``; None where there is
no ``/proc``); ``traced`` is what Python and numpy allocated and still hold (numpy reports
its buffers to tracemalloc), so ``rss - traced`` is the interpreter, the extension
modules' own heaps (Zenoh, Rerun, BLAS) and the allocator's free pages.  Tracing costs
time and memory (a traced soak ran 2-3 times slower per segment, under load): a diagnosis
tool, not for production runs, and not for measuring the slopes themselves
(``docs/operations.md``, Measuring).
"""

from __future__ import annotations

import ctypes
import logging
import os
import tracemalloc
from pathlib import Path

log = logging.getLogger(__name__)

#: Environment variable switching the trace on: report every N segments (0 or unset: off).
ENV = "TTL_MEMTRACE"
#: Source lines listed in a growth report.
TOP_LINES = 10
#: Frames kept per traced allocation: enough to find, below numpy's and scipy's own frames,
#: the line of the project that asked for the memory.
FRAMES = 16
#: Where the project's packages are: an allocation is charged to the innermost frame there.
PACKAGES = tuple(str(Path(__file__).resolve().parents[2] / name) + os.sep for name in ("ttlcore", "streamer", "stages"))


def release_free_memory() -> bool:
    """Give the allocator's free pages back to the system (glibc ``malloc_trim(0)``): after
    a large temporary computation (a window refit, a diagnosis) its freed arrays otherwise
    stay in the process' heap and add to the next one's peak.  False where there is no
    glibc (the call is then a no-op)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return bool(libc.malloc_trim(0))


def rss_mb() -> float | None:
    """Resident set size of this process [MB] (from ``/proc/self/statm``), None without ``/proc``."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def every_from_env(environ=None) -> int:
    """The report period ``N`` of :data:`ENV` (0: off).

    Raises
    ------
    ValueError
        If the variable is set to something other than a non-negative integer.
    """
    raw = (os.environ if environ is None else environ).get(ENV, "").strip()
    if not raw:
        return 0
    try:
        every = int(raw)
    except ValueError:
        raise ValueError(
            f"environment variable {ENV}={raw!r}: expected a non-negative integer "
            "(report every N segments; 0 or unset: off)"
        ) from None
    if every < 0:
        raise ValueError(f"environment variable {ENV}={raw!r}: expected a non-negative integer")
    return every


class MemoryTrace:
    """Per-segment memory lines and periodic growth reports (module docstring).

    Parameters
    ----------
    every : int
        Growth report every ``every`` segments; 0: the trace is off and :meth:`segment`
        does nothing.
    logger : logging.Logger or LoggerAdapter, optional
        Where the lines go (default this module's logger).
    """

    def __init__(self, every: int, logger=None):
        self.every = int(every)
        self.log = logger or log
        self.count = 0
        self._snapshot: dict = {}  # the last snapshot (:meth:`_take`), when on
        if self.every > 0:
            if not tracemalloc.is_tracing():
                tracemalloc.start(FRAMES)
            self._snapshot = self._take()

    @classmethod
    def from_env(cls, logger=None) -> MemoryTrace:
        return cls(every_from_env(), logger)

    @property
    def on(self) -> bool:
        return self.every > 0

    @staticmethod
    def _take() -> dict:
        """Live traced memory per charged line (module docstring): ``{(file, line): [bytes, blocks]}``."""
        out: dict = {}
        for trace in tracemalloc.take_snapshot().traces:
            frames = trace.traceback  # oldest first
            if any(f.filename in (__file__, tracemalloc.__file__) for f in frames):
                continue  # the trace's own bookkeeping
            frame = next((f for f in reversed(frames) if f.filename.startswith(PACKAGES)), frames[-1])
            entry = out.setdefault((frame.filename, frame.lineno), [0, 0])
            entry[0] += trace.size
            entry[1] += 1
        return out

    def segment(self, index: int | None) -> dict | None:
        """After a handled segment: log the memory line (and the growth report when due);
        returns ``{"rss_mb", "traced_mb", "peak_mb"}``, None when off."""
        if not self.on:
            return None
        self.count += 1
        current, peak = tracemalloc.get_traced_memory()
        out = {"rss_mb": rss_mb(), "traced_mb": current / 2**20, "peak_mb": peak / 2**20}
        rss = f"{out['rss_mb']:.1f} MB" if out["rss_mb"] is not None else "unknown"
        self.log.info(
            "memory after segment %s: rss %s, traced %.1f MB (peak %.1f MB)",
            index,
            rss,
            out["traced_mb"],
            out["peak_mb"],
        )
        if self.count % self.every == 0:
            snap, before = self._take(), self._snapshot
            growth = sorted(
                ((size - before.get(where, (0, 0))[0], where, size, blocks) for where, (size, blocks) in snap.items()),
                reverse=True,
            )[:TOP_LINES]
            self._snapshot = snap
            for diff, (filename, lineno), size, blocks in growth:
                self.log.info(
                    "memory growth over the last %d segments: %s:%d %+.2f MB (now %.2f MB in %d blocks)",
                    self.every,
                    filename,
                    lineno,
                    diff / 2**20,
                    size / 2**20,
                    blocks,
                )
        return out

"""Progress of the stages of a run: one bookkeeping object for the stages and the launcher.

After handling segment ``i`` (output published, or given up), a pipeline stage
(:class:`streamer.runtime.pipeline_stage.PipelineStage`) publishes its cumulative progress as JSON on
``ttl/<run>/control/progress/<stage>`` with an advanced publisher caching the latest message
(late joiners get it from the cache)::

    {"run", "stage", "pid", "time",
     "index":          last handled index,
     "done":           [[first, last], ...]  indices whose output was published,
     "failed":         [[first, last], ...]  indices given up (error reported),
     "gaps":           [[first, last], ...]  of those, the ones with no data upstream (a gap in
                                             the data, reported, not a failure of the run),
     "segments_total": N or null (from the telemetry meta, passed down the pipeline),
     "complete":       true once the last index is handled and nothing is pending,
     "<name>_ranges":  [[first, last], ...]  stage extras (the fitter's "fits_ranges": the
                                             indices that produced a fit)}

``done`` and ``failed`` cover what *one process* handled; a restarted stage starts afresh, so
consumers (the launcher, the replayer) keep the union over everything they received: a
:class:`Progress` per stage, fed with :meth:`Progress.update`.  The launcher republishes
what it believed of each stage, in the same format, on ``ttl/<run>/control/board/<stage>``
(:meth:`Progress.message`); the stages of a launched run follow that board instead of each
other's own messages.  Who uses it: the replayer for flow control (at most ``window``
segments ahead of the slowest stage), the subtractor to know that the fitter has passed a
segment, the monitor to know what it still waits for, the launcher to show progress and
detect completion.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field

from ..bus.keys import KeyExprError, parse_progress_key
from .plan import MAX_SEGMENTS
from .rangeset import RangeSet

#: Default number of segments the replayer may run ahead of the slowest stage.
REPLAY_WINDOW = 4


@dataclass
class Progress:
    """What is known of one stage's progress: the union over all its messages (and processes).

    A pipeline stage keeps its own progress in one too (:attr:`done`, :attr:`failed`,
    :attr:`gaps` of this process) and publishes :meth:`message`.  Index sets are
    :class:`streamer.runtime.rangeset.RangeSet` (memory by ranges, not by index: a run's progress is a
    few ranges however long the run); sets given to the constructor are converted.

    Attributes
    ----------
    stage : str
        Stage name.
    done, failed, gaps : RangeSet
        Segment indices whose output was published, given up, given up for lack of data.
    segments_total : int or None
        Segments of the run, once known.
    complete : bool
        The stage said it handled its last segment with nothing pending.
    extra : dict
        Name -> RangeSet of indices, the stage's extras (``"fits"``: indices that produced a fit).
    last : dict
        The last message taken.
    pids : set of int
        Processes that reported.
    updated : float
        ``time.monotonic()`` of the last message.
    """

    stage: str
    done: RangeSet = field(default_factory=RangeSet)
    failed: RangeSet = field(default_factory=RangeSet)
    segments_total: int | None = None
    gaps: RangeSet = field(default_factory=RangeSet)
    complete: bool = False
    last: dict = field(default_factory=dict)
    pids: set = field(default_factory=set)
    extra: dict = field(default_factory=dict)
    updated: float = 0.0

    def __post_init__(self):
        for name in ("done", "failed", "gaps"):
            value = getattr(self, name)
            if not isinstance(value, RangeSet):
                setattr(self, name, RangeSet(value))
        self.extra = {n: v if isinstance(v, RangeSet) else RangeSet(v) for n, v in self.extra.items()}

    @property
    def handled(self) -> RangeSet:
        return self.done | self.failed

    @property
    def highest(self) -> int:
        """Highest handled index (-1 when none)."""
        return max(self.done.max(), self.failed.max())

    def covers(self, total: int | None = None) -> bool:
        """True when every index ``0 .. total-1`` was handled."""
        total = self.segments_total if total is None else total
        return total is not None and self.handled.issuperset(range(total))

    def update(self, msg: dict, limit: int | None = None) -> None:
        """Add a progress message (see the module docstring): index sets are united, clipped
        to ``[0, limit)`` (default: the segments total, once known)."""
        if isinstance(msg.get("segments_total"), int) and 0 < msg["segments_total"] <= MAX_SEGMENTS:
            self.segments_total = msg["segments_total"]
        limit = limit or self.segments_total or MAX_SEGMENTS
        self.done |= RangeSet.from_ranges(msg.get("done"), limit)
        self.failed |= RangeSet.from_ranges(msg.get("failed"), limit)
        self.gaps |= RangeSet.from_ranges(msg.get("gaps"), limit)
        self.complete = self.complete or bool(msg.get("complete"))
        if msg.get("pid") is not None:
            self.pids.add(msg["pid"])
        for name, value in msg.items():
            if name.endswith("_ranges"):
                self.extra.setdefault(name[: -len("_ranges")], RangeSet()).update(RangeSet.from_ranges(value, limit))
        self.last = msg
        self.updated = time.monotonic()

    def message(self, run: str, **fields) -> dict:
        """This progress as a message (module docstring); ``fields`` (``pid``, ``index``) added."""
        return {
            "run": run,
            "stage": self.stage,
            "time": time.time(),
            **fields,
            "done": self.done.ranges(),
            "failed": self.failed.ranges(),
            "gaps": self.gaps.ranges(),
            "segments_total": self.segments_total,
            "complete": self.complete,
            **{f"{name}_ranges": _ranges(v) for name, v in self.extra.items()},
        }

    def copy(self) -> Progress:
        """A copy that shares no set with this one."""
        return Progress(
            self.stage,
            self.done.copy(),
            self.failed.copy(),
            self.segments_total,
            self.gaps.copy(),
            self.complete,
            dict(self.last),
            set(self.pids),
            {n: RangeSet(s) if not isinstance(s, RangeSet) else s.copy() for n, s in self.extra.items()},
            self.updated,
        )


def _ranges(indices) -> list[list[int]]:
    """``[[first, last], ...]`` of a RangeSet or of any iterable of indices."""
    return indices.ranges() if isinstance(indices, RangeSet) else RangeSet(indices).ranges()


def parse_progress(payload) -> dict | None:
    """A progress message as a dict (None when it is not one)."""
    raw = payload.to_bytes() if hasattr(payload, "to_bytes") else bytes(payload or b"")
    try:
        msg = json.loads(raw)
    except (ValueError, RecursionError):  # RecursionError: nested too deep for the parser
        return None
    if not isinstance(msg, dict) or not isinstance(msg.get("stage"), str):
        return None
    return msg


def key_stage(key: str) -> str | None:
    """The stage a progress (or board) key names, None when ``key`` is not one."""
    try:
        return parse_progress_key(str(key))[1]
    except KeyExprError:
        return None


def progress_consistent(msg: dict, key: str, run: str | None, total: int | None) -> bool:
    """A progress message is believable: its stage is the key's last chunk, its run the
    run's, its ``segments_total`` the plan's (when known).  (Who may publish it at all is the
    access control's business; what it claims against what was published is the launcher's.)"""
    if key_stage(key) != msg.get("stage"):
        return False
    if run is not None and msg.get("run") != run:
        return False
    t = msg.get("segments_total")
    if total is not None and t is not None and t != total:
        return False
    return True


class ProgressBoard:
    """Progress of the stages of a run, fed from the progress messages (thread-safe)."""

    def __init__(self):
        self._lock = threading.Lock()
        self.stages: dict[str, Progress] = {}
        self.changed = threading.Event()

    def feed(self, sample, run: str | None = None, total: int | None = None) -> None:
        """Zenoh callback of the progress subscriber: messages of another run, of a stage
        other than the key's, or claiming more segments than the plan are dropped."""
        msg = parse_progress(sample.payload)
        if msg is None or not progress_consistent(msg, str(sample.key_expr), run, total):
            return
        with self._lock:
            self.stages.setdefault(msg["stage"], Progress(msg["stage"])).update(msg)
        self.changed.set()

    def get(self, stage: str | None) -> Progress | None:
        """The latest progress of ``stage`` (None: none heard, or no stage named)."""
        if stage is None:
            return None
        with self._lock:
            return self.stages.get(stage)

    def snapshot(self) -> dict[str, Progress]:
        with self._lock:
            return {k: v.copy() for k, v in self.stages.items()}

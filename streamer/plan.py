"""The plan of a run, and what every message must fit to change a stage's state.

The replayer knows the plan of a run before the first segment goes out: how many segments,
the sampling rate, where each segment starts and how many samples it holds (a file's last
segment may be shorter; several files leave gaps in time).  ``ttl run`` asks it
(``stages.replayer --check --plan-out``) and gives the plan to every stage in its
configuration (``StageConfig.plan``).  :class:`Validator` checks each decoded message against
it before the stage hands the message on (``docs/operations.md`` lists the rules):

* producer: the stage that owns the topic (``telemetry`` <- replayer, ``tdi`` <-
  tdi_builder, ``fit`` <- fitter, ``residual`` <- subtractor, ``monitor`` <- monitor);
* index: within ``0 .. segments_total - 1`` and within ``window`` of the highest index
  accepted so far on any input topic (a stray index far ahead cannot move the stream);
* fs equal to the plan's, t0 equal to the planned start of that index (half a sample);
* length: the last axis of every time-series array equals the planned samples of that
  index (``TIME_ARRAYS``);
* content: a time series with no finite sample at all is refused (an all-NaN TDI
  segment is no data; a NaN stretch is data with a gap and goes through);
* duplicates by content: a copy identical to the accepted one (producer, t0, fs and the
  payload checksum) is ignored; a different one is refused and the conflict recorded,
  and so is any later copy of that index.  What the accepted copies were is remembered
  within the index window only (memory bounded whatever the run's length): a copy more than
  ``window`` segments behind the highest accepted index is refused as too late, identical
  or not, without comparing it.  The first copy is kept out too when it has not
  been used yet: every accepted message waits in a :class:`Holdback` for ``hold`` seconds
  before the stage uses it, and a conflict withdraws it from there (or from the stage's own
  reorder buffer); the stage then treats the index as missing.

Without a plan (a stage run on its own), the first accepted message of a topic fixes its
producer, fs and the samples per segment (trust on first use), ``segments_total`` comes from the
messages' meta and the index window still applies.

Index bookkeeping is in ranges (:class:`RangeSet`), never per index: an index of 2^40
costs one range, not 2^40 entries.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from .topology import PRODUCERS

#: Arrays whose last axis is time (one sample per telemetry sample), per topic.
TIME_ARRAYS = {
    "telemetry": ("eta", "dws_phi", "dws_eta", "ltt"),
    "tdi": ("data", "regressors"),
    "residual": ("residual", "ttl_model"),
}
#: Arrays that must have at least one finite sample, per topic (others may be all NaN).
FINITE_SOMEWHERE = {"telemetry": ("eta",), "tdi": ("data",), "residual": ("residual",)}
#: Arrays that must be finite everywhere, per topic.
FINITE_EVERYWHERE = {"telemetry": ("ltt",)}
#: Default index window: how far beyond the highest accepted index a message may be.
DEFAULT_WINDOW = 64
#: Largest number of segments a plan may declare.
MAX_SEGMENTS = 10_000_000


class RangeSet:
    """A set of non-negative integers kept as sorted disjoint ``[first, last]`` ranges.

    Memory is O(number of ranges), whatever the indices: adding 2^40 costs one range.
    """

    def __init__(self, items: Iterable[int] = ()):
        self._starts: list[int] = []
        self._ends: list[int] = []
        for i in items:
            self.add(i)

    @classmethod
    def from_ranges(cls, ranges, limit: int | None = None) -> RangeSet:
        """From ``[[first, last], ...]``, malformed entries ignored, clipped to ``[0, limit)``."""
        out = cls()
        for r in ranges or ():
            try:
                a, b = int(r[0]), int(r[1])
            except (TypeError, ValueError, IndexError, OverflowError):
                continue
            if limit is not None:
                b = min(b, limit - 1)
            a = max(a, 0)
            if a <= b:
                out.add_range(a, b)
        return out

    def add(self, i: int) -> None:
        self.add_range(i, i)

    def add_range(self, a: int, b: int) -> None:
        """Add ``a .. b`` (inclusive)."""
        k = bisect.bisect_left(self._ends, a - 1)  # first range that ends at or after a - 1
        j = k
        while j < len(self._starts) and self._starts[j] <= b + 1:
            a, b = min(a, self._starts[j]), max(b, self._ends[j])
            j += 1
        self._starts[k:j] = [a]
        self._ends[k:j] = [b]

    def discard(self, i: int) -> None:
        k = bisect.bisect_right(self._starts, i) - 1
        if k < 0 or self._ends[k] < i:
            return
        a, b = self._starts[k], self._ends[k]
        new = [(x, y) for x, y in ((a, i - 1), (i + 1, b)) if x <= y]
        self._starts[k : k + 1] = [x for x, _ in new]
        self._ends[k : k + 1] = [y for _, y in new]

    def __contains__(self, i) -> bool:
        k = bisect.bisect_right(self._starts, i) - 1
        return k >= 0 and self._ends[k] >= i

    def __len__(self) -> int:
        return sum(b - a + 1 for a, b in zip(self._starts, self._ends))

    def __bool__(self) -> bool:
        return bool(self._starts)

    def __iter__(self):
        for a, b in zip(self._starts, self._ends):
            yield from range(a, b + 1)

    def ranges(self) -> list[list[int]]:
        return [[a, b] for a, b in zip(self._starts, self._ends)]

    @property
    def n_ranges(self) -> int:
        return len(self._starts)

    def max(self, default: int = -1) -> int:
        return self._ends[-1] if self._ends else default

    def covers(self, a: int, b: int) -> bool:
        """True when every index ``a .. b`` is in the set."""
        k = bisect.bisect_right(self._starts, a) - 1
        return k >= 0 and self._ends[k] >= b

    def missing(self, a: int, b: int) -> list[list[int]]:
        """The ranges of ``a .. b`` not in the set."""
        out, pos = [], a
        k = max(0, bisect.bisect_right(self._starts, a) - 1)
        for s, e in zip(self._starts[k:], self._ends[k:]):
            if s > b:
                break
            if e < pos:
                continue
            if s > pos:
                out.append([pos, s - 1])
            pos = e + 1
        if pos <= b:
            out.append([pos, b])
        return out

    def update(self, items: Iterable[int]) -> None:
        """Add every index of ``items`` (a :class:`RangeSet` range by range)."""
        if isinstance(items, RangeSet):
            for a, b in zip(items._starts, items._ends):
                self.add_range(a, b)
        else:
            for i in items:
                self.add(i)

    def copy(self) -> RangeSet:
        out = RangeSet()
        out._starts, out._ends = list(self._starts), list(self._ends)
        return out

    def __or__(self, other) -> RangeSet:
        out = self.copy()
        out.update(other)
        return out

    __ror__ = __or__

    def __ior__(self, other) -> RangeSet:
        self.update(other)
        return self

    def __sub__(self, other) -> RangeSet:
        """The indices of this set not in ``other`` (a RangeSet or any container)."""
        if isinstance(other, RangeSet):
            out = RangeSet()
            for a, b in zip(self._starts, self._ends):
                for x, y in other.missing(a, b):
                    out.add_range(x, y)
            return out
        out = self.copy()
        for i in other:
            out.discard(i)
        return out

    def __rsub__(self, other) -> set:
        """``other - self`` for a plain set (or any iterable): a set."""
        return {i for i in other if i not in self}

    def issuperset(self, items) -> bool:
        """True when every index of ``items`` is in the set (a ``range`` of step 1: in one look-up)."""
        if isinstance(items, range) and items.step == 1:
            return len(items) == 0 or self.covers(items.start, items.stop - 1)
        if isinstance(items, RangeSet):
            return all(self.covers(a, b) for a, b in zip(items._starts, items._ends))
        return all(i in self for i in items)

    def __eq__(self, other) -> bool:
        if isinstance(other, RangeSet):
            return self._starts == other._starts and self._ends == other._ends
        if isinstance(other, (set, frozenset)):
            return len(self) == len(other) and all(i in self for i in other)
        return NotImplemented

    __hash__ = None

    def __repr__(self) -> str:
        return f"RangeSet({self.ranges()})"


@dataclass(frozen=True)
class Plan:
    """What the run's segments are (made by the replayer from its source).

    Attributes
    ----------
    segments_total : int
    fs : float
        Sampling rate of every segment [Hz].
    t0 : float
        Start of segment 0 [s].
    samples : int
        Samples of a full segment.
    samples_total : int
        Samples of the whole run (the last segment holds the rest), for a regular plan.
    table : tuple of (t0, n), optional
        Start [s] and samples of every segment, when they are not regular (several files).
    producers : dict
        Topic -> the stage that publishes it.
    window : int
        How far beyond the highest accepted index a message may be.
    """

    segments_total: int
    fs: float
    t0: float
    samples: int
    samples_total: int
    table: tuple | None = None
    producers: dict = field(default_factory=lambda: dict(PRODUCERS))
    window: int = DEFAULT_WINDOW

    def segment(self, index: int) -> tuple[float, int]:
        """``(t0 [s], samples)`` of segment ``index``."""
        if self.table is not None:
            t0, n = self.table[index]
            return float(t0), int(n)
        return self.t0 + index * self.samples / self.fs, min(self.samples, self.samples_total - index * self.samples)

    def to_dict(self) -> dict:
        return {
            "segments_total": self.segments_total,
            "fs": self.fs,
            "t0": self.t0,
            "samples": self.samples,
            "samples_total": self.samples_total,
            "table": None if self.table is None else [list(r) for r in self.table],
            "producers": dict(self.producers),
            "window": self.window,
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> Plan:
        """From :meth:`to_dict` output; raises ValueError naming the field at fault."""
        d = dict(d)
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"plan: unknown field {sorted(unknown)[0]!r}")
        try:
            total, fs = int(d["segments_total"]), float(d["fs"])
            t0, samples, samples_total = float(d["t0"]), int(d["samples"]), int(d["samples_total"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"plan: {exc}") from None
        if not 0 < total <= MAX_SEGMENTS:
            raise ValueError(f"plan: segments_total {total} outside 1..{MAX_SEGMENTS}")
        if not (math.isfinite(fs) and fs > 0 and math.isfinite(t0) and samples > 0):
            raise ValueError("plan: fs, t0 must be finite, fs and samples > 0")
        table = d.get("table")
        if table is not None:
            table = tuple((float(a), int(b)) for a, b in table)
            if len(table) != total:
                raise ValueError(f"plan: table has {len(table)} rows for {total} segments")
        producers = {**PRODUCERS, **dict(d.get("producers") or {})}
        return cls(total, fs, t0, samples, samples_total, table, producers, int(d.get("window") or DEFAULT_WINDOW))


class Rejected(ValueError):
    """A message does not fit the plan (``field`` names what is wrong)."""

    def __init__(self, kind: str, field: str, what: str):
        self.kind = kind
        self.field = field
        self.what = what
        super().__init__(f"field {field!r}: {what}")


def _last_axis(header, name: str) -> int | None:
    for spec in header.arrays:
        if spec.name == name:
            return spec.shape[-1] if spec.shape else None
    return None


def content_digest(header) -> tuple:
    """What makes two copies of a segment the same message."""
    return (header.producer, header.t0, header.fs, header.checksum, header.payload_bytes)


class Validator:
    """Checks decoded messages of one stage against the plan (module docstring).

    :meth:`check` raises :class:`Rejected` or returns ``"new"`` (accept) or ``"duplicate"``
    (an identical copy: ignore); :meth:`accepted` records an accepted message.
    """

    def __init__(self, plan: Plan | None = None, window: int = DEFAULT_WINDOW):
        self.plan = plan
        self.window = plan.window if plan is not None else int(window)
        self.highest = -1
        self.segments_total: int | None = plan.segments_total if plan is not None else None
        self.digests: dict[tuple[str, int], tuple] = {}
        self.conflicted: dict[str, RangeSet] = {}
        self._learned: dict[str, tuple[float, int]] = {}  # topic -> (fs, samples) without a plan
        self._producers: dict[str, str] = {}  # topic -> producer, learned without a plan

    def set_highest(self, index: int) -> None:
        """Move the window (e.g. to a checkpoint's position)."""
        self.highest = max(self.highest, int(index))
        self._forget_old()

    @property
    def floor(self) -> int:
        """Lowest index still compared with its accepted copy: ``highest - window`` (copies of
        lower indices are refused as too late, their digests forgotten)."""
        return self.highest - self.window

    def _forget_old(self) -> None:
        """Drop the digests below :attr:`floor`, once they are as many as those kept (amortized
        O(1) per message; memory O(window) per topic)."""
        floor = self.floor
        if len(self.digests) > 2 * (self.window + 1) * max(1, len({t for t, _ in self.digests})):
            self.digests = {k: v for k, v in self.digests.items() if k[1] >= floor}

    def check(self, topic: str, header, arrays: Mapping[str, np.ndarray]) -> str:
        plan, index = self.plan, header.index
        owner = plan.producers.get(topic) if plan is not None else self._producers.get(topic)
        if owner is not None and header.producer != owner:
            raise Rejected("forged", "producer", f"{topic} is published by {owner!r}, not {header.producer!r}")
        total = self.segments_total
        if total is None:
            t = header.meta.get("segments_total") if isinstance(header.meta, dict) else None
            total = t if isinstance(t, int) and 0 < t <= MAX_SEGMENTS else None
        if total is not None and index >= total:
            raise Rejected("rejected", "index", f"segment {index} is beyond the run's {total} segments")
        if self.highest >= 0 and index > self.highest + self.window:
            raise Rejected(
                "rejected",
                "index",
                f"segment {index} is more than {self.window} ahead of the highest accepted segment {self.highest}",
            )
        if index < self.floor:
            raise Rejected(
                "rejected",
                "index",
                f"segment {index} is more than {self.window} behind the "
                f"highest accepted segment {self.highest}: too late (a copy that "
                "old is not compared with the one accepted before)",
            )
        if self.highest < 0 and plan is None and index > self.window and total is None:
            raise Rejected("rejected", "index", f"first segment {index} with no plan and no segments_total")
        if plan is not None:
            t0, n = plan.segment(index)
            fs = plan.fs
            if abs(header.t0 - t0) > 0.5 / fs:
                raise Rejected("rejected", "t0", f"t0 {header.t0} s, segment {index} starts at {t0} s")
        else:
            fs, n = self._learned.get(topic, (header.fs, None))
        if not math.isclose(header.fs, fs, rel_tol=1e-9):
            raise Rejected("rejected", "fs", f"{header.fs} Hz, the run's rate is {fs} Hz")
        for name in TIME_ARRAYS.get(topic, ()):
            m = _last_axis(header, name)
            if (
                m is not None
                and n is not None
                and m != n
                and not (plan is None and total is not None and index == total - 1 and m < n)
            ):
                raise Rejected("rejected", f"arrays[{name}].shape", f"{m} samples, segment {index} has {n}")
        for name in FINITE_SOMEWHERE.get(topic, ()):
            a = arrays.get(name)
            if a is not None and a.dtype.kind in "fc" and a.size and not np.isfinite(a).any():
                raise Rejected("rejected", f"arrays[{name}]", "no finite sample (all NaN or inf)")
        for name in FINITE_EVERYWHERE.get(topic, ()):
            a = arrays.get(name)
            if a is not None and a.dtype.kind in "fc" and not np.isfinite(a).all():
                raise Rejected("rejected", f"arrays[{name}]", "non-finite values (must be finite everywhere)")
        if index in self.conflicted.get(topic, ()):
            raise Rejected("conflict", "index", f"{topic} segment {index} had conflicting copies: all refused")
        digest = content_digest(header)
        seen = self.digests.get((topic, index))
        if seen is not None:
            if seen == digest:
                return "duplicate"
            self.conflicted.setdefault(topic, RangeSet()).add(index)
            raise Rejected(
                "conflict",
                "payload",
                f"{topic} segment {index} differs from the copy accepted "
                f"before (producer {seen[0]!r}, checksum {seen[3]}): both copies "
                "refused",
            )
        return "new"

    def accepted(self, topic: str, header) -> None:
        self.digests[(topic, header.index)] = content_digest(header)
        self.highest = max(self.highest, header.index)
        self._forget_old()
        if self.plan is None:
            self._learned.setdefault(topic, (header.fs, _time_length(topic, header)))
            self._producers.setdefault(topic, header.producer)
            t = header.meta.get("segments_total") if isinstance(header.meta, dict) else None
            if self.segments_total is None and isinstance(t, int) and 0 < t <= MAX_SEGMENTS:
                self.segments_total = t


class Holdback:
    """Accepted messages held ``hold`` seconds before the stage uses them.

    A different copy of a held segment (a conflict, :meth:`Validator.check`) withdraws it, so
    that both copies are kept out; a message that waited ``hold`` seconds with no contender
    is handed to the stage.  Keyed by ``(topic, index)``; the wait is the same for every
    message, so they come out in arrival order.  Memory: the messages of ``hold`` seconds
    (the index window bounds them).
    """

    def __init__(self, hold: float):
        if not (math.isfinite(hold) and hold >= 0):
            raise ValueError(f"hold: {hold!r} is not a duration >= 0 s")
        self.hold = float(hold)
        self._items: dict[tuple[str, int], tuple[float, object]] = {}

    def put(self, topic: str, index: int, item, now: float) -> bool:
        """Hold ``item`` until ``now + hold``; False (not held: use it now) when ``hold`` is 0."""
        if self.hold <= 0:
            return False
        self._items[(topic, int(index))] = (now + self.hold, item)
        return True

    def due(self, now: float) -> list:
        """The items whose wait is over, in arrival order (taken out)."""
        out = []
        for key, (deadline, item) in list(self._items.items()):
            if deadline > now:
                break
            del self._items[key]
            out.append(item)
        return out

    def withdraw(self, topic: str, index: int) -> bool:
        """Drop the held copy of ``(topic, index)``; False when none is held (already used)."""
        return self._items.pop((topic, int(index)), None) is not None

    def __len__(self) -> int:
        return len(self._items)


def _time_length(topic: str, header) -> int | None:
    for name in TIME_ARRAYS.get(topic, ()):
        m = _last_axis(header, name)
        if m is not None:
            return m
    return None

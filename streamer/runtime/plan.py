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

Index bookkeeping is in ranges (:class:`streamer.runtime.rangeset.RangeSet`, re-exported here),
never per index: an index of 2^40 costs one range, not 2^40 entries.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..bus.segment_record import segments_total_of
from ..bus.topology import PRODUCERS
from .rangeset import RangeSet

__all__ = [
    "DEFAULT_WINDOW",
    "MAX_SEGMENTS",
    "Holdback",
    "Plan",
    "RangeSet",
    "Rejected",
    "Validator",
    "content_digest",
]

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
    inputs : tuple of dict
        The input files as they were when the run was planned
        (:func:`streamer.launch.input_pins.pin`: ``path``, ``size``, ``mtime_ns``, ``sha256_sampled``);
        empty for a simulation.  The replayer reads nothing else (docs/operations.md,
        "Pinned inputs").
    """

    segments_total: int
    fs: float
    t0: float
    samples: int
    samples_total: int
    table: tuple | None = None
    producers: dict = field(default_factory=lambda: dict(PRODUCERS))
    window: int = DEFAULT_WINDOW
    inputs: tuple = ()

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
            "inputs": [dict(p) for p in self.inputs],
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
        inputs = tuple(_input_pin(k, p) for k, p in enumerate(d.get("inputs") or ()))
        window = int(d.get("window") or DEFAULT_WINDOW)
        return cls(total, fs, t0, samples, samples_total, table, producers, window, inputs)


def _input_pin(k: int, p) -> dict:
    """One row of a plan's ``inputs``, checked (ValueError naming the row and field)."""
    if not isinstance(p, Mapping):
        raise ValueError(f"plan: inputs[{k}] is not an object")
    for name, kind in (("path", str), ("size", int), ("mtime_ns", int), ("sha256_sampled", str)):
        if not isinstance(p.get(name), kind) or isinstance(p.get(name), bool):
            raise ValueError(f"plan: inputs[{k}].{name}: expected {kind.__name__}, got {p.get(name)!r}")
    return {name: p[name] for name in ("path", "size", "mtime_ns", "sha256_sampled")}


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
        self._learned: dict[str, tuple[float, int | None]] = {}  # topic -> (fs, samples) without a plan
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
            t = segments_total_of(header.meta)
            total = t if t is not None and t <= MAX_SEGMENTS else None
        self._check_index(index, total)
        self._check_samples(topic, header, total)
        _check_finite(topic, arrays)
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

    def _check_index(self, index: int, total: int | None) -> None:
        """``index`` within the run's ``total`` segments (None: not known) and the window
        around the highest accepted segment."""
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
        if self.highest < 0 and self.plan is None and index > self.window and total is None:
            raise Rejected("rejected", "index", f"first segment {index} with no plan and no segments_total")

    def _check_samples(self, topic: str, header, total: int | None) -> None:
        """The segment's t0 (with a plan), rate and samples per time array: the plan's, else
        those learned from the topic's first message (the run's last segment may be shorter)."""
        plan, index = self.plan, header.index
        n: int | None  # samples of the segment (None: not learned yet)
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

    def accepted(self, topic: str, header) -> None:
        self.digests[(topic, header.index)] = content_digest(header)
        self.highest = max(self.highest, header.index)
        self._forget_old()
        if self.plan is None:
            self._learned.setdefault(topic, (header.fs, _time_length(topic, header)))
            self._producers.setdefault(topic, header.producer)
            t = segments_total_of(header.meta)
            if self.segments_total is None and t is not None and t <= MAX_SEGMENTS:
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


def _check_finite(topic: str, arrays: Mapping[str, np.ndarray]) -> None:
    """The arrays of ``topic`` that must hold a finite sample somewhere, or be finite everywhere."""
    for name in FINITE_SOMEWHERE.get(topic, ()):
        a = arrays.get(name)
        if a is not None and a.dtype.kind in "fc" and a.size and not np.isfinite(a).any():
            raise Rejected("rejected", f"arrays[{name}]", "no finite sample (all NaN or inf)")
    for name in FINITE_EVERYWHERE.get(topic, ()):
        a = arrays.get(name)
        if a is not None and a.dtype.kind in "fc" and not np.isfinite(a).all():
            raise Rejected("rejected", f"arrays[{name}]", "non-finite values (must be finite everywhere)")

"""Segments read back from their producers' recordings: the copy of last resort.

A publisher's cache keeps its last ``cache`` segments (:mod:`streamer.bus.segment_stream`).
A stage restarted after a long absence may need segments older than that. The monitor is
the usual case: killed and restarted while the fitter and the subtractor went on.
Nothing on the bus holds those segments any more; they would never come, and the stage
would wait for them as long as their producers live. The chaos test with model changes ran
into this: its run never ended.

The producer recorded each of them before publishing it, in
``<recordings>/<run>/<stage>.mcap`` (``<stage>.<n>.mcap`` for its earlier processes).
:func:`recorded_copies` reads the wanted segments of one topic back from there. It decodes
only those (:func:`streamer.recording.recording_reader.read_recording`'s ``keep``), so a week's
recording costs the few segments' memory, not the file's. This works where the stage runs
on the producer's host, or shares its recordings directory. Elsewhere nothing is found and
the segment is given up as lost.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from .recording_reader import RecordedSegment, RecordingError, read_recording

__all__ = ["recorded_copies", "recording_files", "wire_copy"]


def recording_files(run_dir: Path, stage: str) -> list[Path]:
    """``<stage>.mcap`` and the earlier processes' ``<stage>.<n>.mcap`` in ``run_dir``."""
    pattern = re.compile(rf"{re.escape(stage)}(\.\d+)?\.mcap")
    return sorted(p for p in Path(run_dir).glob(f"{stage}*.mcap") if pattern.fullmatch(p.name))


def recorded_copies(run_dir: Path, stage: str, topic: str, indices: Iterable[int]) -> dict[int, RecordedSegment]:
    """The first recorded copy of each of ``indices`` of ``topic`` in ``stage``'s recordings
    (an index no file holds is missing from the result; a file that cannot be read is
    passed over)."""
    wanted = set(indices)
    out: dict[int, RecordedSegment] = {}
    for path in recording_files(run_dir, stage):
        if not wanted - out.keys():
            break
        left = wanted - out.keys()

        def keep(t: str, header: dict, left: set[int] = left) -> bool:
            return t == topic and header.get("index") in left

        try:
            rec = read_recording(path, keep=keep)
        except RecordingError:
            continue
        for m in rec.segments(topic):
            out.setdefault(m.header.index, m)
    return out


def wire_copy(
    seg: RecordedSegment,
    rebuild: Callable[[Path, RecordedSegment], tuple[bytes, bytes]] | None = None,
    run_dir: Path | None = None,
) -> tuple[bytes, bytes]:
    """``(payload, attachment)`` of a recorded segment as it was published: its arrays' bytes
    at their header offsets, and its wire header (which carries the payload's size and
    checksum), so that a stage takes it through the checks any copy from the bus goes
    through.  A segment its producer recorded in part (``meta.recorded``: the arrays left out
    by :attr:`streamer.bus.transport.Output.record_arrays`) is ``rebuild(run_dir, seg)`` when
    given (the producer's own rule, e.g. :func:`stages.tdi_builder.rebuilt_copy`), else the
    recorded part (which a consumer that needs the rest refuses)."""
    if rebuild is not None and run_dir is not None and (seg.header.meta or {}).get("recorded"):
        return rebuild(run_dir, seg)
    if seg.data is None:
        raise RecordingError(f"{seg.topic} segment {seg.header.index}: recorded without its header")
    payload = bytearray(seg.header.payload_bytes)
    for spec in seg.header.arrays:
        raw = np.ascontiguousarray(seg.arrays[spec.name], dtype=np.dtype(spec.dtype)).tobytes()
        payload[spec.offset : spec.offset + len(raw)] = raw
    return bytes(payload), json.dumps(seg.data).encode()

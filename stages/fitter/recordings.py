"""What a restarted fitter reads from the run's recordings.

Its earlier processes' files ``<stage>.<n>.mcap`` (oldest first) give the model changes they
accepted and the fits they recorded (:func:`recorded_models`); the replayer's files
``replayer*.mcap`` give the telemetry of the segments before the first one the new process
receives, from which it rebuilds its window (:func:`recorded_telemetry`), their TDI computed
again as the TDI builder's stream (:func:`pushed_again`).  A damaged or
unreadable file is skipped with a warning: the others are used.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

from streamer.bus.messages import telemetry_of
from streamer.recording.recorder import read_recording
from streamer.runtime.stage_reports import earlier_recordings
from ttlcore.tdi.data import TDIStream


def recorded_models(
    run_dir: Path, stage: str, log: logging.Logger | logging.LoggerAdapter
) -> tuple[list[dict], set[int], set[int]]:
    """The ``model`` events of the earlier processes of ``stage`` (oldest file first), the
    segments they recorded a fit of (the fit message or its summary: a kill between the two
    leaves only the former), and those whose summary is recorded (what ``ttl inspect``
    lists)."""
    files = earlier_recordings(run_dir, stage)
    models: list[dict] = []
    segments: set[int] = set()
    summaries: set[int] = set()
    for path in files:
        try:
            rec = read_recording(path)
        except Exception as exc:  # noqa: BLE001 - a damaged file: use what the others have
            log.warning("cannot read %s: %s", path, exc)
            continue
        models += [e for e in rec.json("events") if e.get("kind") == "model"]
        # the fit's segment is written before its summary: a kill between leaves only the former
        segments.update(m.header.index for m in rec.segments("fit"))
        summaries.update(s["index"] for s in rec.json("fit/summary") if isinstance(s.get("index"), int))
    return models, segments | summaries, summaries


def recorded_telemetry(run_dir: Path, first: int, log: logging.Logger | logging.LoggerAdapter) -> dict:
    """Index -> the replayer's recorded telemetry message of each segment before ``first``
    (with its readouts), the first copy found across ``replayer*.mcap``."""
    segments: dict = {}
    for path in sorted(Path(run_dir).glob("replayer*.mcap")):
        try:
            for m in read_recording(path).segments("telemetry"):
                if m.header.index < first and "eta" in m.arrays:
                    segments.setdefault(m.header.index, m)
        except Exception as exc:  # noqa: BLE001 - a damaged file: use what the others have
            log.warning("cannot read %s: %s", path, exc)
    return segments


def pushed_again(segments: dict, start: int, first: int) -> Iterator[tuple]:
    """``(header, (TDIData, Telemetry))`` of the recorded segments ``start`` .. ``first - 1``
    (:func:`recorded_telemetry`), their TDI computed again from the telemetry by one TDI
    stream, as the TDI builder's from the run's first segment (a new stream after a
    discontinuity in time)."""
    stream = TDIStream()
    for i in range(start, first):
        m = segments[i]
        tm = telemetry_of(m.header, m.arrays)
        if stream.next_t0 is not None and abs(tm.t0 - stream.next_t0) > 0.5 / tm.fs:
            stream.reset()
        yield m.header, (stream.push(tm), tm)

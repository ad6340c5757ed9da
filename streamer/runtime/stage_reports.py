"""What a stage writes about itself: its recording file, errors, warnings, events, control
commands, and the stop note of a full disk.

Errors go on the bus (``ttl/<run>/errors/<index>``), in the recording (topic ``errors``) and
in the log; warnings and events in the recording (and warnings in the log).  The records are
:func:`streamer.recording.recorder.stage_record` objects.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from ..bus.keys import errors_key
from ..bus.session import Bus
from ..recording.recorder import Recorder, stage_record, stop_note_path
from .lifecycle import disk_full

# the logger of these lines before the stage was split into parts: log lines unchanged
log = logging.getLogger("streamer.runtime.stage")


def set_aside(path: Path) -> Path:
    """``path``, free to write: an existing file is first renamed ``<stem>.<n><suffix>``
    (the lowest ``n`` free), so that a restarted process keeps its predecessor's recording
    (and its stop note, :func:`streamer.recording.recorder.stop_note_path`)."""
    path = Path(path)
    if path.exists():
        n = 1
        while (old := path.with_name(f"{path.stem}.{n}{path.suffix}")).exists():
            n += 1
        path.rename(old)
        note = stop_note_path(path)
        if note.exists():
            note.rename(stop_note_path(old))
        log.info("kept the previous recording as %s", old)
    return path


def earlier_recordings(run_dir: Path, stage: str) -> list[Path]:
    """The recordings :func:`set_aside` kept of the earlier processes of ``stage``
    (``<stage>.<n>.mcap`` in ``run_dir``), in the order they ran (``n`` ascending)."""

    def number(path: Path) -> int:
        try:
            return int(path.name[len(stage) + 1 : -len(".mcap")])
        except ValueError:
            return 0

    return sorted(Path(run_dir).glob(f"{stage}.*.mcap"), key=number)


def recording_path(recordings: Path, run: str, stage: str) -> Path:
    """``<recordings>/<run>/<stage>.mcap``; an existing file is first renamed ``<stage>.<n>.mcap``."""
    return set_aside(Path(recordings) / run / f"{stage}.mcap")


class StageReports:
    """Errors, warnings and events of one stage, on the bus and in its recording.

    :attr:`bus` and :attr:`recorder` are set while the stage runs (None before and after:
    errors are then only logged).  :attr:`disk_full` says why the stage stops on a full disk
    (:meth:`note_disk_full`), after which writes that fail are logged, not raised
    (:meth:`last_words`).
    """

    def __init__(self, run: str, stage: str, log: logging.LoggerAdapter):
        self.run = run
        self.stage = stage
        self.log = log
        self.bus: Bus | None = None
        self.recorder: Recorder | None = None
        self.disk_full: str | None = None

    def error(
        self,
        kind: str,
        message: str,
        *,
        index: int | None = None,
        key: str | None = None,
        field: str | None = None,
        details: dict | None = None,
    ) -> dict:
        """Publish an error on ``ttl/<run>/errors/<index>``, record it, log it; returns it."""
        error = stage_record(self.run, self.stage, kind, message, index=index, details=details, key=key, field=field)
        self.log.warning(
            "%s%s%s: %s",
            kind,
            f" {key}" if key else "",
            f" field {field!r}" if field else "",
            message,
            extra={"index": index},
        )
        if self.bus is not None:
            try:
                self.bus.put_json(errors_key(self.run, index), error)
            except Exception:
                self.log.exception("could not publish the error")
        if self.recorder is not None:
            self.recorder.write_json("errors", error)
        return error

    def warn(self, kind: str, message: str, *, index: int | None = None, **details) -> None:
        """Log and record a warning (topic ``warnings``)."""
        self.log.warning("%s: %s", kind, message, extra={"index": index})
        if self.recorder is not None:
            self.recorder.write_json(
                "warnings", stage_record(self.run, self.stage, kind, message, index=index, details=details)
            )

    def event(self, kind: str, *, index: int | None = None, message: str = "", **details) -> None:
        """Record a lifecycle or bookkeeping event (topic ``events``)."""
        if self.recorder is not None:
            self.recorder.write_json(
                "events", stage_record(self.run, self.stage, kind, message, index=index, details=details)
            )

    def note_disk_full(self, exc: OSError, where) -> None:
        """The recording's disk is full: free the recorder's reserve, leave the stop note
        beside the file (``ttl inspect`` names the cause), report it on the bus."""
        self.disk_full = f"disk full: {exc.strerror or exc} (writing under {where})"
        self.log.error("%s: stopping (exit status 4)", self.disk_full)
        if self.recorder is not None:
            self.recorder.release_reserve()
            try:
                self.recorder.note_stop("disk-full", self.disk_full, run=self.run, stage=self.stage, errno=exc.errno)
            except OSError as again:
                self.log.error("could not write the stop note: %s", again)
        self.last_words(lambda: self.error("disk-full", f"{self.disk_full}: stage stops"))

    def last_words(self, write: Callable[[], object]) -> None:
        """Call ``write``; once the disk is full, a failure to write is logged, not raised."""
        if self.disk_full is None:
            write()
            return
        try:
            write()
        except OSError as exc:
            self.log.error("on the full disk: %s", exc)

    def closing_failed(self, exc: OSError) -> bool:
        """True (and logged) when closing the recording failed because of the full disk the
        stage is stopping on; False: not that, the error is the caller's to raise."""
        if self.disk_full is None or not disk_full(exc):
            return False
        self.log.error("could not close the recording on the full disk: %s", exc)
        return True

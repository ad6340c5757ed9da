"""MCAP recording of what a stage received and sent, and reading it back.

Layout of a recording (``recordings/<run>/<stage>.mcap``)
--------------------------------------------------------
* JSON channels (message encoding ``json``, schema encoding ``jsonschema``, so Foxglove
  and the ``mcap`` CLI can read them): ``errors`` (:data:`ERROR_SCHEMA`), ``warnings``
  (:data:`WARNING_SCHEMA`), ``events``
  (:data:`EVENT_SCHEMA`), ``<topic>/header`` (segment headers, :data:`HEADER_SCHEMA`),
  and summaries such as fits and diagnoses (:data:`FIT_SCHEMA`,
  :data:`DIAGNOSIS_SCHEMA`, or any schema given by the writer).
* A segment is two messages written back to back with the same ``sequence`` number and
  log time: its JSON header on ``<topic>/header``, then its payload (the raw array bytes,
  exactly as on the wire) on ``<topic>/payload`` (schema-less channel, message encoding
  ``application/octet-stream``, channel metadata ``header_topic``).  The reader pairs
  them by topic and sequence and decodes the arrays with :func:`streamer.bus.codec.decode`,
  which checks the payload against the header's checksum.
* File metadata record ``ttl`` (run, stage, ...), given at creation.

Each payload is stored once, by the stage that published it: a consumer records the
headers of what it received (``<topic>/input``, JSON), whose ``checksum`` names the
payload in the producer's file, and a producer may leave derived arrays out of its file
(the header then carries ``meta.recorded``: the arrays kept and the published checksum).

Time: a message's ``log_time`` is *mission* time [ns] (the segment's ``t0``, or the latest
mission time the recorder has seen for messages without one), so Foxglove and the ``mcap``
tools plot mission days; ``publish_time`` is the wall-clock time of the write [ns since epoch].

The file is chunked and compressed (zstd by default).  A chunk is closed after every
segment, after every message on :data:`FLUSHED_TOPICS` (errors, events, warnings, control) and whenever it has been open for :data:`MAX_CHUNK_AGE` seconds at a write, so a
killed process loses at most the chunk it was filling; :func:`read_recording` salvages
such files (no summary, no footer, maybe a truncated last chunk).

Parts: the JSON records and their schemas are in :mod:`streamer.recording.record_schemas`, the
reading in :mod:`streamer.recording.recording_reader`; this module writes, and re-exports both.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path

from mcap.writer import CompressionType, Writer

from ..bus.codec import Header
from ..bus.message_schema import to_jsonable
from .record_schemas import (
    ALERT_SCHEMA,
    CONTROL_SCHEMA,
    DIAGNOSIS_SCHEMA,
    ERROR_SCHEMA,
    EVENT_SCHEMA,
    FIT_SCHEMA,
    HEADER_SCHEMA,
    OBJECT_SCHEMA,
    PAYLOAD_ENCODING,
    SCHEMAS,
    TOPIC_SCHEMAS,
    WARNING_SCHEMA,
    stage_record,
)
from .recording_reader import MAGIC, RecordedMessage, RecordedSegment, Recording, RecordingError, read_recording

__all__ = [  # the reader's and the schemas' names too: stages, tools and tests import them from here
    "ALERT_SCHEMA",
    "CONTROL_SCHEMA",
    "DIAGNOSIS_SCHEMA",
    "ERROR_SCHEMA",
    "EVENT_SCHEMA",
    "FIT_SCHEMA",
    "HEADER_SCHEMA",
    "MAGIC",
    "OBJECT_SCHEMA",
    "PAYLOAD_ENCODING",
    "SCHEMAS",
    "TOPIC_SCHEMAS",
    "WARNING_SCHEMA",
    "RecordedMessage",
    "RecordedSegment",
    "Recorder",
    "Recording",
    "RecordingError",
    "mission_ns",
    "read_recording",
    "read_stop_note",
    "stage_record",
    "stop_note_path",
]

log = logging.getLogger(__name__)

PROFILE = ""
#: Compression of the chunks (``"zstd"``, ``"lz4"`` or ``""``).
COMPRESSION = "zstd"
#: A chunk is closed once it holds this many bytes (segments close theirs anyway) [bytes].
CHUNK_SIZE = 1 << 20
#: A chunk open for longer than this is closed at the next write [s].
MAX_CHUNK_AGE = 2.0
#: JSON topics whose messages close the chunk at once (rare, and wanted after a kill).
FLUSHED_TOPICS = frozenset({"errors", "events", "warnings", "control"})
_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "": CompressionType.NONE,
    "none": CompressionType.NONE,
}


def mission_ns(t: float) -> int:
    """Mission time ``t`` [s] as an MCAP ``log_time`` [ns] (clipped at 0: log times are unsigned)."""
    return max(0, int(round(float(t) * 1e9))) if math.isfinite(float(t)) else 0


#: Bytes a :class:`Recorder` sets aside for its last words on a full disk (the stop note, the
#: error and stop event, the summary written on close).
RESERVE_BYTES = 1 << 20


class Recorder:
    """Write an MCAP recording (see the module docstring for the layout).

    Parameters
    ----------
    path : str or Path
        File to write (``.mcap``); its directory is created.  An existing file is replaced.
    metadata : mapping of str to str, optional
        Written as the file's ``ttl`` metadata record (run, stage, ...).
    fsync : bool
        Also ``os.fsync`` after every record (survives power loss, not just a kill).
    reserve : int
        Bytes set aside beside the file (``<path>.reserve``, allocated, deleted on close):
        when the disk fills up, :meth:`release_reserve` frees them so that the stop can
        still be written down (:meth:`note_stop`) and the file closed.

    Use as a context manager, or call :meth:`close`.
    """

    def __init__(
        self,
        path,
        metadata: Mapping[str, str] | None = None,
        fsync: bool = False,
        compression: str = COMPRESSION,
        chunk_size: int = CHUNK_SIZE,
        max_chunk_age: float = MAX_CHUNK_AGE,
        reserve: int = RESERVE_BYTES,
    ):
        if compression not in _COMPRESSION:
            raise ValueError(f"compression: expected one of zstd, lz4, none, got {compression!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._reserve = self.path.with_name(self.path.name + ".reserve")
        _allocate(self._reserve, reserve)
        stop_note_path(self.path).unlink(missing_ok=True)  # a note of an earlier file at this path
        self._file = open(self.path, "wb")
        self._fsync = fsync
        self._writer = Writer(
            self._file, use_chunking=True, chunk_size=int(chunk_size), compression=_COMPRESSION[compression]
        )
        self._writer.start(profile=PROFILE, library="ttl-streamer")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0
        self._closed = False
        self._max_chunk_age = float(max_chunk_age)
        self._chunk_opened: float | None = None
        #: Latest mission time seen [ns]: the log time of messages that carry none.
        self.mission_time_ns = 0
        if metadata:
            self._writer.add_metadata("ttl", {str(k): str(v) for k, v in metadata.items()})
        self.flush()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ channels
    def _schema_id(self, name: str, schema: Mapping | None) -> int:
        if name not in self._schemas:
            schema = schema if schema is not None else SCHEMAS[name]
            data = json.dumps(schema, separators=(",", ":")).encode()
            self._schemas[name] = self._writer.register_schema(name=name, encoding="jsonschema", data=data)
        return self._schemas[name]

    def _json_channel(self, topic: str, schema) -> int:
        if topic not in self._channels:
            if schema is None:
                schema = TOPIC_SCHEMAS.get(topic, "ttl.Object")
            if isinstance(schema, str):
                if schema not in SCHEMAS:
                    raise KeyError(f"unknown schema {schema!r} (known: {', '.join(SCHEMAS)})")
                name, body = schema, SCHEMAS[schema]
            else:
                body = dict(schema)
                name = body.get("title", f"{topic}.schema")
            schema_id = self._schema_id(name, body)
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="json", schema_id=schema_id
            )
        return self._channels[topic]

    def _payload_channel(self, topic: str) -> int:
        name = f"{topic}/payload"
        if name not in self._channels:
            self._channels[name] = self._writer.register_channel(
                topic=name,
                message_encoding=PAYLOAD_ENCODING,
                schema_id=0,
                metadata={
                    "header_topic": f"{topic}/header",
                    "layout": "ttl-segment: raw arrays at the header's offsets, little endian, C order",
                },
            )
        return self._channels[name]

    # ------------------------------------------------------------------ writing
    def write_json(self, topic: str, obj, schema: str | Mapping | None = None, log_time: int | None = None) -> None:
        """Write one JSON message on ``topic``.

        Parameters
        ----------
        topic : str
            MCAP topic (``errors``, ``events``, ``fit/summary``...).
        obj : JSON-like
            The message (numpy values converted; NaN and inf written as null).
        schema : str or mapping, optional
            Name in :data:`SCHEMAS` or a JSON schema (with a ``title``), used when the
            channel is first written (default: by topic, else ``ttl.Object``).
        log_time : int, optional
            Mission time [ns] (:func:`mission_ns`); default the latest mission time seen.
        """
        channel = self._json_channel(topic, schema)
        data = json.dumps(to_jsonable(obj), separators=(",", ":"), allow_nan=False).encode()
        opened = self._add(channel, data, log_time)
        if topic in FLUSHED_TOPICS or time.monotonic() - opened >= self._max_chunk_age:
            self.flush()

    def write_segment(self, topic: str, header: Header | Mapping, payload, log_time: int | None = None) -> None:
        """Write one segment: its header on ``<topic>/header``, its payload on ``<topic>/payload``
        (log time: the segment's mission time ``t0`` unless given); the chunk is then closed."""
        header_dict = header.to_dict() if isinstance(header, Header) else dict(header)
        header_channel = self._json_channel(f"{topic}/header", "ttl.SegmentHeader")
        payload_channel = self._payload_channel(topic)
        if log_time is None:
            log_time = mission_ns(header_dict.get("t0", 0.0))
        data = json.dumps(header_dict, separators=(",", ":"), allow_nan=False).encode()
        raw = payload.to_bytes() if hasattr(payload, "to_bytes") else bytes(payload)
        self._add(header_channel, data, log_time)
        self._add(payload_channel, raw, log_time, new_sequence=False)
        self.flush()

    def _add(self, channel: int, data: bytes, log_time: int | None, new_sequence: bool = True) -> float:
        """Add a message to the open chunk; returns when the chunk was opened (monotonic [s])."""
        if log_time is None:
            log_time = self.mission_time_ns
        else:
            self.mission_time_ns = max(self.mission_time_ns, int(log_time))
        if new_sequence:
            self._sequence += 1
        if self._chunk_opened is None:
            self._chunk_opened = time.monotonic()
        self._writer.add_message(
            channel_id=channel, log_time=int(log_time), publish_time=time.time_ns(), data=data, sequence=self._sequence
        )
        return self._chunk_opened

    def flush(self) -> None:
        """Close the open chunk and push it to the OS (and to disk with ``fsync=True``)."""
        self._writer.flush()
        self._chunk_opened = None
        if self._fsync:
            os.fsync(self._file.fileno())

    def release_reserve(self) -> None:
        """Free the bytes set aside at open (the disk is full: make room for the last words)."""
        self._reserve.unlink(missing_ok=True)

    def note_stop(self, reason: str, message: str, **details) -> Path:
        """Write ``<path>.stop.json`` (atomically): why the recording stopped when the file
        itself may be unable to say so (a full disk).  ``ttl inspect`` reads it."""
        note = stop_note_path(self.path)
        tmp = note.with_name(note.name + ".tmp")
        tmp.write_text(json.dumps({"reason": reason, "message": message, "time": time.time(), **details}))
        os.replace(tmp, note)
        return note

    def close(self) -> None:
        """Write the summary and footer, and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
            self._file.flush()
        finally:
            try:
                self._file.close()
            finally:
                self.release_reserve()


def stop_note_path(path) -> Path:
    """``<recording>.stop.json``: the note :meth:`Recorder.note_stop` leaves beside ``path``."""
    path = Path(path)
    return path.with_name(path.name + ".stop.json")


def read_stop_note(path) -> dict | None:
    """The stop note of recording ``path`` (:meth:`Recorder.note_stop`), or None."""
    try:
        note = json.loads(stop_note_path(path).read_text())
    except (OSError, ValueError):
        return None
    return note if isinstance(note, dict) else None


def _allocate(path: Path, size: int) -> None:
    """Create ``path`` with ``size`` bytes really allocated (not a sparse file)."""
    if size <= 0:
        return
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        try:
            os.posix_fallocate(fd, 0, size)
        except (AttributeError, OSError):  # not supported here: write the bytes
            os.write(fd, b"\0" * size)
    finally:
        os.close(fd)

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
  them by topic and sequence and decodes the arrays with :func:`streamer.codec.decode`,
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
segment, after every message on :data:`FLUSHED_TOPICS` (errors, events, warnings) and whenever it has been open for :data:`MAX_CHUNK_AGE` seconds at a write, so a
killed process loses at most the chunk it was filling; :func:`read_recording` salvages
such files (no summary, no footer, maybe a truncated last chunk).
"""

from __future__ import annotations

import io
import json
import logging
import math
import mmap
import os
import struct
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from .codec import CodecError, Expect, Header, decode

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
#: Message encoding of payload channels.
PAYLOAD_ENCODING = "application/octet-stream"
PROFILE = ""
#: Compression of the chunks (``"zstd"``, ``"lz4"`` or ``""``).
COMPRESSION = "zstd"
#: A chunk is closed once it holds this many bytes (segments close theirs anyway) [bytes].
CHUNK_SIZE = 1 << 20
#: A chunk open for longer than this is closed at the next write [s].
MAX_CHUNK_AGE = 2.0
#: JSON topics whose messages close the chunk at once (rare, and wanted after a kill).
FLUSHED_TOPICS = frozenset({"errors", "events", "warnings"})
_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "": CompressionType.NONE,
    "none": CompressionType.NONE,
}


def mission_ns(t: float) -> int:
    """Mission time ``t`` [s] as an MCAP ``log_time`` [ns] (clipped at 0: log times are unsigned)."""
    return max(0, int(round(float(t) * 1e9))) if math.isfinite(float(t)) else 0


_NUMBER = {"type": "number"}
_NUMBERS = {"type": "array", "items": _NUMBER}
_STRING = {"type": "string"}
_INTEGER = {"type": "integer"}
_OBJECT = {"type": "object"}
_TIME = {"type": "number", "description": "wall-clock time [s since epoch]"}


def _object_schema(title: str, required, properties: dict) -> dict:
    """A JSON schema (draft 2020-12) of an object named ``title``."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "type": "object",
        "required": list(required),
        "properties": properties,
    }


#: JSON schema of a segment header (:mod:`streamer.codec`).
HEADER_SCHEMA = _object_schema(
    "ttl.SegmentHeader",
    [
        "schema",
        "version",
        "run",
        "index",
        "t0",
        "fs",
        "channels",
        "producer",
        "arrays",
        "payload_bytes",
        "checksum",
        "meta",
    ],
    {
        "schema": {"const": "ttl-segment"},
        "version": _INTEGER,
        "run": _STRING,
        "index": {"type": "integer", "minimum": 0},
        "t0": {"type": "number", "description": "mission time of the first sample [s]"},
        "fs": {"type": "number", "description": "sampling rate [Hz]"},
        "channels": {"type": "array", "items": _STRING},
        "producer": _STRING,
        "arrays": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["name", "dtype", "shape", "offset", "nbytes", "units", "channel_axis"],
                "properties": {
                    "name": _STRING,
                    "dtype": _STRING,
                    "shape": {"type": "array", "items": _INTEGER},
                    "offset": _INTEGER,
                    "nbytes": _INTEGER,
                    "units": _STRING,
                    "channel_axis": {"type": ["integer", "null"]},
                },
            },
        },
        "payload_bytes": _INTEGER,
        "checksum": _STRING,
        "meta": _OBJECT,
    },
)
#: Fields of a stage's error, warning and event records (:func:`stage_record`).
_RECORD = {
    "run": _STRING,
    "stage": _STRING,
    "kind": _STRING,
    "index": {"type": ["integer", "null"]},
    "message": _STRING,
    "time": _TIME,
    "details": _OBJECT,
}
#: JSON schema of an error (a rejected message, a failed segment, a gap).
ERROR_SCHEMA = _object_schema(
    "ttl.Error",
    ["run", "stage", "kind", "message", "time"],
    {
        **_RECORD,
        "kind": {"type": "string", "description": "rejected | failed | gap | ..."},
        "key": {"type": ["string", "null"]},
        "field": {"type": ["string", "null"], "description": "header field at fault"},
    },
)
#: JSON schema of a warning: something an operator should see that is not an error
#: (a fit that did not converge, ...).
WARNING_SCHEMA = _object_schema(
    "ttl.Warning",
    ["run", "stage", "kind", "message", "time"],
    {**_RECORD, "kind": {"type": "string", "description": "not-converged | ..."}},
)
#: JSON schema of a lifecycle or bookkeeping event (start, stop, duplicate, ...).
EVENT_SCHEMA = _object_schema("ttl.Event", ["run", "stage", "kind", "time"], _RECORD)
#: JSON schema of a fit of the TTL coefficients.
FIT_SCHEMA = _object_schema(
    "ttl.Fit",
    ["run", "index", "names", "coefficients"],
    {
        "run": _STRING,
        "index": _INTEGER,
        "t_start": {"type": "number", "description": "start of the fitted window [s]"},
        "t_end": {"type": "number", "description": "end of the fitted window [s]"},
        "names": {"type": "array", "items": _STRING},
        "coefficients": {**_NUMBERS, "description": "m/rad"},
        "sigma": _NUMBERS,
        "covariance": {"type": "array", "items": _NUMBERS},
        "chi2": _NUMBER,
        "dof": _NUMBER,
    },
)
#: JSON schema of a model-adequacy diagnosis.
DIAGNOSIS_SCHEMA = _object_schema(
    "ttl.Diagnosis",
    ["run", "index", "verdict"],
    {"run": _STRING, "index": _INTEGER, "verdict": _STRING, "checks": _OBJECT, "message": _STRING},
)
#: JSON schema of a control message received by a stage (``ttl/<run>/control/<stage>/<command>``).
CONTROL_SCHEMA = _object_schema(
    "ttl.Control",
    ["run", "stage", "command", "time"],
    {
        "run": _STRING,
        "stage": _STRING,
        "command": _STRING,
        "payload": {"description": "the message (JSON when it parses, else text)"},
        "accepted": {"type": "boolean"},
        "message": _STRING,
        "time": _TIME,
    },
)
#: JSON schema of a step or drift alert of the monitor (``alerts``).
ALERT_SCHEMA = _object_schema(
    "ttl.Alert",
    ["kind", "coefficient", "t", "value", "significance", "message"],
    {
        "run": _STRING,
        "kind": {"type": "string", "description": "step | drift"},
        "coefficient": _STRING,
        "t": {"type": ["number", "null"], "description": "step time or end of the drift span [s]"},
        "value": {"type": ["number", "null"], "description": "step [mm/rad] or drift rate [mm/rad/day]"},
        "significance": {"type": ["number", "null"]},
        "message": _STRING,
        "t_detected": {"type": ["number", "null"]},
        "index": {"type": ["integer", "null"], "description": "fit that raised it"},
        "units": _STRING,
        "details": _OBJECT,
    },
)
#: Schemas known by name (``Recorder.write_json(..., schema="ttl.Fit")``).
SCHEMAS = {
    s["title"]: s
    for s in (
        HEADER_SCHEMA,
        ERROR_SCHEMA,
        WARNING_SCHEMA,
        EVENT_SCHEMA,
        FIT_SCHEMA,
        DIAGNOSIS_SCHEMA,
        CONTROL_SCHEMA,
        ALERT_SCHEMA,
    )
}
#: Schema of JSON channels with no schema given.
OBJECT_SCHEMA = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "ttl.Object", "type": "object"}
SCHEMAS["ttl.Object"] = OBJECT_SCHEMA


def stage_record(
    run: str,
    stage: str,
    kind: str,
    message: str = "",
    *,
    index: int | None = None,
    details: dict | None = None,
    **fields,
) -> dict:
    """An error, warning or event of a stage (or the launcher), as :data:`ERROR_SCHEMA`,
    :data:`WARNING_SCHEMA` and :data:`EVENT_SCHEMA` describe it; ``fields`` (``key``,
    ``field`` of an error) are added, the time is now."""
    return {
        "run": run,
        "stage": stage,
        "kind": kind,
        "index": index,
        **fields,
        "message": message,
        "time": time.time(),
        "details": details or {},
    }


#: Default schema by topic.
TOPIC_SCHEMAS = {
    "errors": "ttl.Error",
    "warnings": "ttl.Warning",
    "events": "ttl.Event",
    "control": "ttl.Control",
    "alerts": "ttl.Alert",
}


class RecordingError(ValueError):
    """A recording cannot be read at all (message names the file)."""


def to_jsonable(obj):
    """``obj`` with numpy types turned into Python ones and non-finite floats into None."""
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


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
        self._add(channel, data, log_time)
        if topic in FLUSHED_TOPICS or time.monotonic() - self._chunk_opened >= self._max_chunk_age:
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

    def _add(self, channel: int, data: bytes, log_time: int | None, new_sequence: bool = True) -> None:
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


# ---------------------------------------------------------------------------- reading


@dataclass
class RecordedMessage:
    """One message of a recording.

    Attributes
    ----------
    topic : str
        For segments the segment topic (``tdi``), else the MCAP topic (``errors``).
    log_time : int
        Mission time [ns] (see the module docstring).
    kind : {"json", "segment", "incomplete", "invalid", "raw"}
        ``segment``: header and arrays decoded; ``incomplete``: a header whose payload
        was never written (killed in between); ``invalid``: a segment whose payload does
        not match its header (``error`` says why); ``raw``: a message of another encoding.
    data : dict or None
        The JSON message (for segments, the header as a dict).
    header : Header or None
    arrays : dict of str to ndarray, or None
    sequence : int
    error : str or None
    raw : bytes or None
        The bytes of ``raw`` messages.
    publish_time : int
        Wall-clock time of the write [ns since epoch].
    """

    topic: str
    log_time: int
    kind: str
    data: dict | None = None
    header: Header | None = None
    arrays: dict | None = None
    sequence: int = 0
    error: str | None = None
    raw: bytes | None = None
    publish_time: int = 0


@dataclass
class Recording:
    """What :func:`read_recording` found.

    Attributes
    ----------
    path : Path
    messages : list of RecordedMessage
        In file order.
    complete : bool
        True when the file has its footer (closed properly).
    records : int
        MCAP records read (all kinds).
    problem : str or None
        Why reading stopped early (truncated or corrupt record), for salvaged files.
    metadata : dict
        Metadata records, name -> dict.
    schemas : dict
        Channel topic -> (schema name, schema encoding, message encoding).
    """

    path: Path
    messages: list = field(default_factory=list)
    complete: bool = False
    records: int = 0
    problem: str | None = None
    metadata: dict = field(default_factory=dict)
    schemas: dict = field(default_factory=dict)
    #: Corrupt stretches skipped while salvaging (``{"start", "stop", "why"}``, byte offsets):
    #: a damaged file (flipped bytes) is read past them, from the next record that checks out.
    skipped: list = field(default_factory=list)

    def json(self, topic: str) -> list[dict]:
        """The JSON messages of ``topic``."""
        return [m.data for m in self.messages if m.topic == topic and m.kind == "json"]

    def segments(self, topic: str) -> list[RecordedMessage]:
        """The complete segments of ``topic``."""
        return [m for m in self.messages if m.topic == topic and m.kind == "segment"]

    def topics(self) -> list[str]:
        return sorted({m.topic for m in self.messages})


class _Assembler:
    """Turns MCAP (schema, channel, message) records into :class:`RecordedMessage`."""

    def __init__(self, recording: Recording):
        self.rec = recording
        self.channels: dict[int, Channel] = {}
        self.schemas: dict[int, Schema] = {}
        self.pending: dict[str, RecordedMessage] = {}  # segment topic -> header waiting for payload

    def record(self, record) -> None:
        """Take one parsed record: a schema, channel, message or metadata (others are skipped)."""
        if isinstance(record, Schema):
            self.schema(record)
        elif isinstance(record, Channel):
            self.channel(record)
        elif isinstance(record, Message):
            self.message(record)
        elif isinstance(record, Metadata):
            self.rec.metadata[record.name] = dict(record.metadata)

    def schema(self, schema: Schema) -> None:
        self.schemas[schema.id] = schema

    def channel(self, channel: Channel) -> None:
        self.channels[channel.id] = channel
        schema = self.schemas.get(channel.schema_id)
        self.rec.schemas[channel.topic] = (
            schema.name if schema else "",
            schema.encoding if schema else "",
            channel.message_encoding,
        )

    def message(self, msg: Message) -> None:
        before = len(self.rec.messages)
        self._message(msg)
        for m in self.rec.messages[before:]:
            m.publish_time = m.publish_time or msg.publish_time
        for m in self.pending.values():
            m.publish_time = m.publish_time or msg.publish_time

    def _message(self, msg: Message) -> None:
        channel = self.channels.get(msg.channel_id)
        if channel is None:
            self.rec.messages.append(
                RecordedMessage(
                    f"<channel {msg.channel_id}>",
                    msg.log_time,
                    "raw",
                    sequence=msg.sequence,
                    raw=bytes(msg.data),
                    error="unknown channel",
                )
            )
            return
        topic = channel.topic
        if channel.message_encoding == "json" and topic.endswith("/header"):
            seg = topic[: -len("/header")]
            self._flush_pending(seg)
            try:
                data = json.loads(msg.data)
            except ValueError as exc:
                self.rec.messages.append(
                    RecordedMessage(
                        seg, msg.log_time, "invalid", sequence=msg.sequence, error=f"header is not JSON: {exc}"
                    )
                )
                return
            self.pending[seg] = RecordedMessage(seg, msg.log_time, "incomplete", data=data, sequence=msg.sequence)
        elif channel.message_encoding == PAYLOAD_ENCODING and topic.endswith("/payload"):
            seg = topic[: -len("/payload")]
            head = self.pending.pop(seg, None)
            if head is None or head.sequence != msg.sequence:
                if head is not None:
                    self.rec.messages.append(head)
                self.rec.messages.append(
                    RecordedMessage(
                        seg,
                        msg.log_time,
                        "invalid",
                        sequence=msg.sequence,
                        raw=bytes(msg.data),
                        error="payload without its header",
                    )
                )
                return
            try:
                header, arrays = decode(msg.data, json.dumps(head.data).encode(), Expect(allow_nonfinite=True))
                head.kind, head.header, head.arrays = "segment", header, arrays
            except CodecError as exc:
                head.kind, head.error = "invalid", str(exc)
            self.rec.messages.append(head)
        elif channel.message_encoding == "json":
            try:
                data = json.loads(msg.data)
                self.rec.messages.append(RecordedMessage(topic, msg.log_time, "json", data=data, sequence=msg.sequence))
            except ValueError as exc:
                self.rec.messages.append(
                    RecordedMessage(
                        topic,
                        msg.log_time,
                        "invalid",
                        sequence=msg.sequence,
                        raw=bytes(msg.data),
                        error=f"not JSON: {exc}",
                    )
                )
        else:
            self.rec.messages.append(
                RecordedMessage(topic, msg.log_time, "raw", sequence=msg.sequence, raw=bytes(msg.data))
            )

    def _flush_pending(self, seg: str) -> None:
        head = self.pending.pop(seg, None)
        if head is not None:
            self.rec.messages.append(head)

    def finish(self) -> None:
        for seg in list(self.pending):
            self._flush_pending(seg)


def read_recording(path) -> Recording:
    """Read an MCAP recording written by :class:`Recorder`, salvaging unfinished files.

    A complete file is read with mcap's streaming reader (CRCs checked).  A file without footer (the process was
    killed) is read record by record up to the first truncated or corrupt record;
    ``complete`` is then False, ``records`` counts what was recovered and ``problem``
    says where reading stopped.

    Raises
    ------
    RecordingError
        If the file is missing or not MCAP at all.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            magic = f.read(len(MAGIC))
            size = os.fstat(f.fileno()).st_size
            f.seek(max(0, size - len(MAGIC)))
            tail = f.read(len(MAGIC))
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc}") from exc
    if magic != MAGIC:  # not even a damaged MCAP file: nothing to salvage
        raise RecordingError(f"{path}: not an MCAP file (bad magic {magic!r})")
    if size > 2 * len(MAGIC) and tail == MAGIC:
        try:
            return _read_complete(path)
        except Exception as exc:  # noqa: BLE001 - McapError, ZstdError, struct.error...: damaged
            log.warning(
                "%s: reading the closed file failed (%s: %s); salvaging record by record", path, type(exc).__name__, exc
            )
    return _salvage(path, size)


def _read_complete(path: Path) -> Recording:
    """Read a closed file with mcap's streaming reader (CRCs checked)."""
    rec = Recording(path, complete=True)
    asm = _Assembler(rec)
    with open(path, "rb") as f:
        for record in StreamReader(f, validate_crcs=True).records:
            rec.records += 1
            asm.record(record)
    asm.finish()
    return rec


def _salvage(path: Path, size: int) -> Recording:
    """Read ``path`` record by record, keeping every record that checks out.

    A record that does not parse (a chunk whose CRC or zstd frame fails: flipped bytes) is
    skipped when its length is plausible; when the length itself is damaged, reading resumes
    at the next chunk that parses and passes its CRC (:func:`_resync`).  Each skipped
    stretch is listed in ``rec.skipped``; ``problem`` says what was lost.  A file that merely
    ends early (a killed process) stops at its last whole record, as before.
    """
    rec = Recording(path, complete=False)
    asm = _Assembler(rec)
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        pos = len(MAGIC)
        end_problem = None
        while True:
            if pos == size:
                end_problem = f"file ends after {rec.records} records without footer (not closed)"
                break
            if pos + 9 > size:
                end_problem = f"truncated record header at byte {pos} ({size - pos} of 9 bytes)"
                break
            opcode, length = struct.unpack_from("<BQ", data, pos)
            if pos + 9 + length > size:
                why = (
                    f"truncated record (opcode 0x{opcode:02x}) at byte {pos}: "
                    f"{size - pos - 9} of {length} bytes present"
                )
                nxt = _resync(data, pos + 1, size)
                if nxt is None:
                    end_problem = why
                    break
                rec.skipped.append({"start": pos, "stop": nxt, "why": f"damaged record length ({why})"})
                pos = nxt
                continue
            body = data[pos + 9 : pos + 9 + length]
            try:
                done = _salvage_record(asm, opcode, body)
            except Exception as exc:  # noqa: BLE001 - a corrupt record: skip it, keep the rest
                rec.skipped.append(
                    {
                        "start": pos,
                        "stop": pos + 9 + length,
                        "why": f"corrupt record (opcode 0x{opcode:02x}): {type(exc).__name__}: {exc}",
                    }
                )
                pos += 9 + length
                continue
            rec.records += 1
            pos += 9 + length
            if done:
                rec.complete = True
                break
    asm.finish()
    parts = []
    if rec.skipped:
        lost = sum(s["stop"] - s["start"] for s in rec.skipped)
        parts.append(
            f"{len(rec.skipped)} corrupt stretch(es) skipped ({lost} bytes, first at byte "
            f"{rec.skipped[0]['start']}: {rec.skipped[0]['why']})"
        )
    if end_problem:
        parts.append(end_problem)
    rec.problem = "; ".join(parts) or None
    if rec.problem:
        log.warning("%s: salvaged %d records; %s", path, rec.records, rec.problem)
    return rec


#: Longest record :func:`_resync` accepts as the next chunk [bytes] (the recorder closes a
#: chunk after every segment; a day-long segment of telemetry is ~50 MB).
_RESYNC_MAX = 1 << 30


def _resync(data, start: int, size: int) -> int | None:
    """Offset of the first chunk record at or after ``start`` that parses and passes its
    CRC, or None.  Used when a record's length field is damaged: the stream can only be
    picked up again at a record that proves itself."""
    pos = start
    opcode = bytes([Opcode.CHUNK])
    while True:
        pos = data.find(opcode, pos, size - 9)
        if pos < 0:
            return None
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if 0 < length <= min(_RESYNC_MAX, size - pos - 9):
            try:
                chunk = Chunk.read(ReadDataStream(io.BytesIO(data[pos + 9 : pos + 9 + length])))
                for _ in breakup_chunk(chunk, validate_crc=True):
                    pass
                return pos
            except Exception:  # noqa: BLE001 - not a chunk after all
                pass
        pos += 1


def _salvage_record(asm: _Assembler, opcode: int, body: bytes) -> bool:
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.SCHEMA:
        asm.record(Schema.read(stream))
    elif opcode == Opcode.CHANNEL:
        asm.record(Channel.read(stream))
    elif opcode == Opcode.MESSAGE:
        asm.record(Message.read(stream, len(body)))
    elif opcode == Opcode.METADATA:
        asm.record(Metadata.read(stream))
    elif opcode == Opcode.CHUNK:
        for record in breakup_chunk(Chunk.read(stream), validate_crc=True):
            asm.record(record)
    elif opcode == Opcode.FOOTER:
        Footer.read(stream)
        return True
    return False

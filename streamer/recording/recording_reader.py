"""Reading a recording back (:func:`read_recording`), whole or salvaged.

A file with its footer is read with the ``mcap`` reader; a file without (the process was
killed) or damaged (flipped bytes) is salvaged record by record: a truncated last chunk is
read as far as it goes, a corrupt stretch is skipped to the next record that checks out,
and what was skipped is listed (:attr:`Recording.skipped`).  Segments are paired header and
payload by topic and sequence and decoded with :func:`streamer.bus.codec.decode`.  See
:mod:`streamer.recording.recorder` for the layout of a recording.
"""

from __future__ import annotations

import io
import json
import logging
import mmap
import os
import struct
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from ..bus.codec import CodecError, Expect, Header, decode
from .record_schemas import PAYLOAD_ENCODING

# the logger of these lines before the recorder was split: `ttl inspect` quiets its
# "salvaged ..." warnings by this name (they are in the report)
log = logging.getLogger("streamer.recording.recorder")

MAGIC = b"\x89MCAP0\r\n"


class RecordingError(ValueError):
    """A recording cannot be read at all (message names the file)."""


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


@dataclass(frozen=True)
class RecordedSegment:
    """A complete segment of a recording (:meth:`Recording.segments`): a
    :class:`RecordedMessage` of kind ``segment``, its header and arrays decoded (never None).

    Attributes
    ----------
    topic : str
    log_time : int
    header : Header
    arrays : dict of str to ndarray
    data : dict or None
        The header as a dict.
    sequence, publish_time : int
    """

    topic: str
    log_time: int
    header: Header
    arrays: dict
    data: dict | None = None
    sequence: int = 0
    publish_time: int = 0

    @classmethod
    def of(cls, m: RecordedMessage) -> RecordedSegment:
        """The segment ``m`` holds; a RecordingError if ``m`` is not a decoded segment."""
        if m.kind != "segment" or m.header is None or m.arrays is None:
            raise RecordingError(f"{m.topic}: a {m.kind} message, not a decoded segment")
        return cls(m.topic, m.log_time, m.header, m.arrays, m.data, m.sequence, m.publish_time)


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

    def segments(self, topic: str) -> list[RecordedSegment]:
        """The complete segments of ``topic``."""
        return [RecordedSegment.of(m) for m in self.messages if m.topic == topic and m.kind == "segment"]

    def topics(self) -> list[str]:
        return sorted({m.topic for m in self.messages})


class _Assembler:
    """Turns MCAP (schema, channel, message) records into :class:`RecordedMessage`."""

    def __init__(self, recording: Recording, keep: Keep | None = None, topics: Collection[str] = ()):
        self.rec = recording
        #: with ``keep``: the JSON topics read too (the others are skipped)
        self.topics = frozenset(topics)
        #: only the segments ``keep(topic, header)`` accepts are decoded and kept (nothing else)
        self.keep = keep
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
        if self.keep is not None:
            channel = self.channels.get(msg.channel_id)
            if channel is None or not self._wanted(channel, msg):
                return
        before = len(self.rec.messages)
        self._message(msg)
        for m in self.rec.messages[before:]:
            m.publish_time = m.publish_time or msg.publish_time
        for m in self.pending.values():
            m.publish_time = m.publish_time or msg.publish_time

    def _message(self, msg: Message) -> None:
        channel = self.channels.get(msg.channel_id)
        if channel is None:
            self._keep_bytes(f"<channel {msg.channel_id}>", msg, "raw", "unknown channel")
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
                self._keep_bytes(seg, msg, "invalid", "payload without its header")
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
                self._keep_bytes(topic, msg, "invalid", f"not JSON: {exc}")
        else:
            self._keep_bytes(topic, msg, "raw")

    def _keep_bytes(self, topic: str, msg: Message, kind: str, error: str | None = None) -> None:
        """Add ``msg`` to the recording as its bytes (``kind`` raw or invalid, and why)."""
        self.rec.messages.append(
            RecordedMessage(topic, msg.log_time, kind, sequence=msg.sequence, raw=bytes(msg.data), error=error)
        )

    def _wanted(self, channel: Channel, msg: Message) -> bool:
        """With a ``keep`` filter: a segment's header that it accepts, and the payload that
        follows such a header, and the JSON messages of ``topics``; nothing else."""
        assert self.keep is not None
        topic = channel.topic
        if channel.message_encoding == "json" and topic in self.topics:
            return True
        if channel.message_encoding == "json" and topic.endswith("/header"):
            try:
                data = json.loads(msg.data)
            except ValueError:
                return False
            return isinstance(data, dict) and bool(self.keep(topic[: -len("/header")], data))
        if channel.message_encoding == PAYLOAD_ENCODING and topic.endswith("/payload"):
            return topic[: -len("/payload")] in self.pending  # its header was kept
        return False

    def _flush_pending(self, seg: str) -> None:
        head = self.pending.pop(seg, None)
        if head is not None:
            self.rec.messages.append(head)

    def finish(self) -> None:
        for seg in list(self.pending):
            self._flush_pending(seg)


#: A filter of the segments to read: ``keep(topic, header)`` (the header as a dict).
Keep = Callable[[str, dict], bool]


def read_recording(path, keep: Keep | None = None, topics: Collection[str] = ()) -> Recording:
    """Read an MCAP recording written by :class:`Recorder`, salvaging unfinished files.

    ``keep``, optional, reads only the segments it accepts (``keep(topic, header)``): the
    others are skipped undecoded, so that a few segments of a week's recording cost their
    own memory, not the file's (:mod:`streamer.recording.recorded_inputs`); with it, the
    JSON messages of ``topics`` are read too, and no other.

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
            return _read_complete(path, keep, topics)
        except Exception as exc:  # noqa: BLE001 - McapError, ZstdError, struct.error...: damaged
            log.warning(
                "%s: reading the closed file failed (%s: %s); salvaging record by record", path, type(exc).__name__, exc
            )
    return _salvage(path, size, keep, topics)


def _read_complete(path: Path, keep: Keep | None = None, topics: Collection[str] = ()) -> Recording:
    """Read a closed file with mcap's streaming reader (CRCs checked)."""
    rec = Recording(path, complete=True)
    asm = _Assembler(rec, keep, topics)
    with open(path, "rb") as f:
        for record in StreamReader(f, validate_crcs=True).records:
            rec.records += 1
            asm.record(record)
    asm.finish()
    return rec


def _salvage(path: Path, size: int, keep: Keep | None = None, topics: Collection[str] = ()) -> Recording:
    """Read ``path`` record by record, keeping every record that checks out.

    A record that does not parse (a chunk whose CRC or zstd frame fails: flipped bytes) is
    skipped when its length is plausible; when the length itself is damaged, reading resumes
    at the next chunk that parses and passes its CRC (:func:`_resync`).  Each skipped
    stretch is listed in ``rec.skipped``; ``problem`` says what was lost.  A file that merely
    ends early (a killed process) stops at its last whole record, as before.
    """
    rec = Recording(path, complete=False)
    asm = _Assembler(rec, keep, topics)
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
    rec.problem = _salvage_problem(rec.skipped, end_problem)
    if rec.problem:
        log.warning("%s: salvaged %d records; %s", path, rec.records, rec.problem)
    return rec


def _salvage_problem(skipped: list[dict], end_problem: str | None) -> str | None:
    """What a salvaged file lost: its ``skipped`` stretches and why it ended early (None: nothing)."""
    parts = []
    if skipped:
        lost = sum(s["stop"] - s["start"] for s in skipped)
        parts.append(
            f"{len(skipped)} corrupt stretch(es) skipped ({lost} bytes, first at byte "
            f"{skipped[0]['start']}: {skipped[0]['why']})"
        )
    if end_problem:
        parts.append(end_problem)
    return "; ".join(parts) or None


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

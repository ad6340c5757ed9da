"""The segment codec: a JSON header (the Zenoh attachment) and raw array bytes (the payload).

Wire format (schema ``ttl-segment``, version :data:`SCHEMA_VERSION`)
-------------------------------------------------------------------
Payload
    The arrays of the message, one after the other, each in C order and little endian,
    each starting at an offset that is a multiple of 8 bytes (zero padding between).
Attachment
    UTF-8 JSON object, exactly these fields::

        schema         "ttl-segment"
        version        1
        run            run id (str)
        index          segment index (int >= 0)
        t0             mission time of the first sample [s] (finite number)
        fs             sampling rate [Hz] (finite number > 0)
        channels       channel names (list of str, may be empty)
        producer       stage (or tool) that made the message (str)
        arrays         list of {name, dtype, shape, offset, nbytes, units, channel_axis}
        payload_bytes  length of the payload (int)
        checksum       "crc32:<8 hex>" or "blake2b:<32 hex>" of the whole payload
        meta           free JSON object

    ``dtype`` is a numpy type string from :data:`ALLOWED_DTYPES` (``"<f8"`` ...).
    ``channel_axis`` is the axis of the array labelled by ``channels`` (its length must
    equal the number of channels), or null when the channels do not label the array.
    A single-array message names its array ``"data"``.

:func:`decode` validates everything (JSON, fields, types, version, dtypes, sizes against
the payload length, checksum, finiteness, and what the consumer expects, see
:class:`Expect`) and raises :class:`CodecError` naming the field at fault.  The header's
JSON is parsed with every size bounded by :mod:`streamer.bus.bounded_json`.

Size: about 640 lines, above the ~600 of the developers' guide on purpose: the wire format,
its encoder and its validating decoder are one specification, and reading :func:`encode`
and :func:`decode` side by side with the field checks is what keeps them in agreement
(the bounded JSON parsing, a concept of its own, is in :mod:`streamer.bus.bounded_json`).
"""

# size: the wire format and its validation are one contract (the docstring says why); the bounded
# JSON parser is in bounded_json.py.

from __future__ import annotations

import hashlib
import json
import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .bounded_json import BoundedJSONError, load_bounded
from .keys import parse_segment_key, parse_stream_key

#: Value of the header field ``schema``.
SCHEMA = "ttl-segment"
#: Header version understood by this module (bumped on incompatible change).
SCHEMA_VERSION = 1
#: numpy dtype strings allowed on the wire (all little endian or byte-sized).
ALLOWED_DTYPES = frozenset(
    {
        "<f8",
        "<f4",
        "<c16",
        "<c8",
        "<i8",
        "<i4",
        "<i2",
        "|i1",
        "<u8",
        "<u4",
        "<u2",
        "|u1",
        "|b1",
    }
)
#: Checksum algorithms, name -> function of the payload returning a hex digest.
CHECKSUMS = {
    "crc32": lambda data: f"{zlib.crc32(data) & 0xFFFFFFFF:08x}",
    "blake2b": lambda data: hashlib.blake2b(data, digest_size=16).hexdigest(),
}
#: Alignment of each array in the payload [bytes].
ALIGNMENT = 8
#: Largest header accepted [bytes].
MAX_HEADER_BYTES = 1 << 20
#: Name of the array of a single-array message.
DEFAULT_NAME = "data"
#: Longest name, unit, run id, producer, dtype or checksum string [characters].
MAX_NAME_CHARS = 256
#: Most axes of an array (numpy's limit is 32 or 64, the messages have at most 3).
MAX_NDIM = 16

#: the fields of a segment header and of each of its arrays (all required; the recorded
#: JSON schema, :mod:`streamer.recording.record_schemas`, is built from these)
HEADER_FIELDS = (
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
)
ARRAY_FIELDS = ("name", "dtype", "shape", "offset", "nbytes", "units", "channel_axis")


class CodecError(ValueError):
    """A segment message does not fit; the message names the field at fault.

    Attributes
    ----------
    field : str
        The field at fault: a header field (``"fs"``), an array field
        (``"arrays[data].shape"``), ``"header"`` (unreadable JSON), ``"attachment"``,
        ``"payload"`` or ``"checksum"``.
    what : str
        What is wrong.
    key : str or None
        The Zenoh key the message came on, when known.
    """

    #: Longest ``what`` kept [characters]: a refused value is quoted, and may be huge.
    MAX_WHAT = 500

    def __init__(self, field: str, what: str, key: str | None = None):
        if len(what) > self.MAX_WHAT:
            what = f"{what[: self.MAX_WHAT]}... ({len(what)} characters)"
        self.field = field
        self.what = what
        self.key = key
        where = f"{key}: " if key else ""
        super().__init__(f"{where}field {field!r}: {what}")


@dataclass(frozen=True)
class ArraySpec:
    """Where one array lives in the payload and what it is."""

    name: str
    dtype: str
    shape: tuple[int, ...]
    offset: int
    nbytes: int
    units: str = ""
    channel_axis: int | None = None

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "dtype": self.dtype,
            "shape": list(self.shape),
            "offset": self.offset,
            "nbytes": self.nbytes,
            "units": self.units,
            "channel_axis": self.channel_axis,
        }


@dataclass(frozen=True)
class Header:
    """A validated segment header.

    ``key`` is the Zenoh key the message came on (not part of the wire header; set by
    :func:`decode` when given).
    """

    run: str
    index: int
    t0: float
    fs: float
    channels: tuple[str, ...]
    producer: str
    arrays: tuple[ArraySpec, ...]
    payload_bytes: int
    checksum: str
    meta: dict = field(default_factory=dict)
    version: int = SCHEMA_VERSION
    key: str | None = field(default=None, compare=False)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the arrays, in payload order."""
        return tuple(a.name for a in self.arrays)

    @property
    def topic(self) -> str | None:
        """Topic of :attr:`key` (None when the key is unknown)."""
        if self.key is None:
            return None
        if self.key.count("/") == 2:  # a stream key ttl/<run>/<topic>
            return parse_stream_key(self.key)
        return parse_segment_key(self.key).topic

    def array(self, name: str) -> ArraySpec:
        """The :class:`ArraySpec` called ``name``."""
        for spec in self.arrays:
            if spec.name == name:
                return spec
        raise KeyError(name)

    def to_dict(self) -> dict:
        """The wire header as a JSON-ready dict."""
        return {
            "schema": SCHEMA,
            "version": self.version,
            "run": self.run,
            "index": self.index,
            "t0": self.t0,
            "fs": self.fs,
            "channels": list(self.channels),
            "producer": self.producer,
            "arrays": [a.to_dict() for a in self.arrays],
            "payload_bytes": self.payload_bytes,
            "checksum": self.checksum,
            "meta": self.meta,
        }

    def to_json(self) -> bytes:
        """The wire header (the Zenoh attachment)."""
        return json.dumps(self.to_dict(), separators=(",", ":"), allow_nan=False).encode()


@dataclass(frozen=True)
class Expect:
    """What a consumer expects of a message; anything else is rejected by :func:`decode`.

    Attributes
    ----------
    run : str, optional
        Required run id.
    index : int, optional
        Required segment index (normally the index of the key).
    arrays : mapping, optional
        Required arrays: name -> ``(dtype, shape)``; ``dtype`` None accepts any allowed
        dtype, ``shape`` None any shape, and a None inside ``shape`` any length on that
        axis, e.g. ``{"data": ("<f8", (3, None)), "regressors": ("<f8", (3, 24, None))}``.
        Arrays not listed are accepted.
    channels : sequence of str, optional
        Required channel names.
    allow_nonfinite : bool
        Accept NaN and inf in float arrays (default: reject).
    finite : tuple of str
        Arrays that must be finite even with ``allow_nonfinite`` (a fit's coefficients: NaN
        there makes the message malformed, not a second opinion on the segment).
    """

    run: str | None = None
    index: int | None = None
    arrays: Mapping[str, tuple[str | None, tuple | None]] | None = None
    channels: tuple[str, ...] | None = None
    allow_nonfinite: bool = False
    finite: tuple[str, ...] = ()


def _fail(field: str, what: str, key: str | None = None):
    raise CodecError(field, what, key)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _as_arrays(arrays) -> dict[str, np.ndarray]:
    if isinstance(arrays, Mapping):
        if not arrays:
            _fail("arrays", "a message needs at least one array")
        return {str(k): np.asarray(v) for k, v in arrays.items()}
    return {DEFAULT_NAME: np.asarray(arrays)}


def _per_array(value, name: str, default):
    if isinstance(value, Mapping):
        return value.get(name, default)
    return value


def _wire_dtype(arr: np.ndarray, name: str) -> np.dtype:
    dt = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
    if dt.str not in ALLOWED_DTYPES:
        _fail(
            f"arrays[{name}].dtype",
            f"dtype {arr.dtype.str!r} is not allowed (allowed: {', '.join(sorted(ALLOWED_DTYPES))})",
        )
    return dt


def _count_nonfinite(arr: np.ndarray) -> tuple[int, int]:
    if arr.dtype.kind not in "fc" or arr.size == 0:
        return 0, -1
    bad = ~np.isfinite(arr)
    n = int(np.count_nonzero(bad))
    return n, (int(np.flatnonzero(bad.ravel())[0]) if n else -1)


def _checksum(algorithm: str, payload) -> str:
    return f"{algorithm}:{CHECKSUMS[algorithm](payload)}"


def encode(
    arrays, fields: Mapping[str, Any], *, checksum: str = "crc32", allow_nonfinite: bool = False
) -> tuple[bytes, bytes]:
    """Encode arrays and header fields into ``(payload, attachment)``.

    Parameters
    ----------
    arrays : ndarray or mapping of str to ndarray
        One array (named ``"data"``) or several named arrays, put in the payload in the
        mapping's order.
    fields : mapping
        Header fields: ``run``, ``index``, ``t0`` [s], ``fs`` [Hz] (required);
        ``channels`` (sequence of str, default none), ``producer`` (str), ``units`` (str
        for all arrays or mapping name -> str), ``channel_axis`` (int or None, or a
        mapping name -> int or None; default 0 when there are channels, else None),
        ``meta`` (JSON-serialisable dict).
    checksum : {"crc32", "blake2b"}
        Checksum algorithm of the payload.
    allow_nonfinite : bool
        Accept NaN/inf in the arrays (default: raise).

    Returns
    -------
    payload : bytes
        The arrays' bytes.
    attachment : bytes
        The JSON header.

    Raises
    ------
    CodecError
        If a field or array cannot be encoded (message names it).
    """
    unknown = set(fields) - {"run", "index", "t0", "fs", "channels", "producer", "units", "channel_axis", "meta"}
    if unknown:
        _fail(sorted(unknown)[0], "unknown header field")
    for name in ("run", "index", "t0", "fs"):
        if name not in fields:
            _fail(name, "missing (required to encode)")
    if checksum not in CHECKSUMS:
        _fail("checksum", f"unknown algorithm {checksum!r} (known: {', '.join(CHECKSUMS)})")
    named = _as_arrays(arrays)
    channels = tuple(fields.get("channels", ()))
    units = fields.get("units", "")
    axes = fields.get("channel_axis", 0 if channels else None)

    parts: list = []
    specs: list[ArraySpec] = []
    offset = 0
    for name, arr in named.items():
        dt = _wire_dtype(arr, name)
        if not allow_nonfinite:
            n, first = _count_nonfinite(arr)
            if n:
                _fail(f"arrays[{name}]", f"{n} non-finite values (NaN or inf), first at flat index {first}")
        data = np.ascontiguousarray(arr, dtype=dt)
        pad = (-offset) % ALIGNMENT
        if pad:
            parts.append(b"\0" * pad)
            offset += pad
        axis = _per_array(axes, name, 0 if channels else None)
        specs.append(
            ArraySpec(
                name=name,
                dtype=dt.str,
                shape=tuple(int(s) for s in data.shape),
                offset=offset,
                nbytes=data.nbytes,
                units=str(_per_array(units, name, "")),
                channel_axis=None if axis is None else int(axis),
            )
        )
        parts.append(data.reshape(-1).view(np.uint8).data)  # (a memoryview of the array's bytes)
        offset += data.nbytes
    payload = b"".join(parts)
    header = Header(
        run=fields["run"],
        index=fields["index"],
        t0=fields["t0"],
        fs=fields["fs"],
        channels=channels,
        producer=str(fields.get("producer", "")),
        arrays=tuple(specs),
        payload_bytes=len(payload),
        checksum=_checksum(checksum, payload),
        meta=dict(fields.get("meta") or {}),
    )
    # Check the header as a consumer would, so that nothing undecodable leaves.
    attachment = _dump(header)
    parse_header(attachment)
    return payload, attachment


def _dump(header: Header) -> bytes:
    try:
        return header.to_json()
    except (TypeError, ValueError) as exc:
        # find the culprit for the message
        for name, value in header.to_dict().items():
            try:
                json.dumps(value, allow_nan=False)
            except (TypeError, ValueError):
                _fail(name, f"not JSON-serialisable (finite numbers only): {exc}")
        raise


def _to_bytes(data) -> bytes | bytearray | memoryview:
    if data is None:
        return b""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return data
    if hasattr(data, "to_bytes"):  # zenoh.ZBytes
        return data.to_bytes()
    return bytes(data)


def parse_header(attachment, key: str | None = None) -> Header:
    """Parse and validate a JSON header on its own (without the payload).

    Raises
    ------
    CodecError
        Naming the field at fault.
    """
    if attachment is None:
        _fail("attachment", "missing (a segment message carries its JSON header as attachment)", key)
    raw = bytes(_to_bytes(attachment))
    if len(raw) > MAX_HEADER_BYTES:
        _fail("header", f"{len(raw)} bytes, larger than the limit of {MAX_HEADER_BYTES}", key)
    try:
        obj = load_bounded(raw)
    except BoundedJSONError as exc:
        _fail(exc.field, exc.what, key)
    if not isinstance(obj, dict):
        _fail("header", f"expected a JSON object, got {type(obj).__name__}", key)
    return _header_from_dict(obj, key)


def _check_name(value, field: str, key: str | None) -> None:
    """A short identifier string (run id, producer, array name, units, channel)."""
    if isinstance(value, str) and len(value) > MAX_NAME_CHARS:
        _fail(field, f"a string of {len(value)} characters (at most {MAX_NAME_CHARS})", key)


def _header_from_dict(obj: dict, key: str | None) -> Header:
    """The header of ``obj``, every field checked in the order of :data:`HEADER_FIELDS`'s
    contract: schema and version, no unknown or missing field, then each value."""
    version = _check_envelope(obj, key)
    _check_identity(obj, key)
    channels = _checked_channels(obj["channels"], key)
    _check_payload_fields(obj, key)
    specs = _array_specs(obj["arrays"], channels, obj["payload_bytes"], key)
    return Header(
        run=obj["run"],
        index=obj["index"],
        t0=float(obj["t0"]),
        fs=float(obj["fs"]),
        channels=tuple(channels),
        producer=obj["producer"],
        arrays=specs,
        payload_bytes=obj["payload_bytes"],
        checksum=obj["checksum"],
        meta=obj["meta"],
        version=version,
        key=key,
    )


def _check_envelope(obj: dict, key: str | None) -> int:
    """The schema and its version (returned), no unknown field, no missing one."""

    def need(name):
        if name not in obj:
            _fail(name, "missing", key)
        return obj[name]

    if need("schema") != SCHEMA:
        _fail("schema", f"expected {SCHEMA!r}, got {obj['schema']!r}", key)
    version = need("version")
    if version != SCHEMA_VERSION or not _is_int(version):
        _fail("version", f"schema version {version!r} not supported (this reader knows {SCHEMA_VERSION})", key)
    unknown = sorted(set(obj) - set(HEADER_FIELDS))
    if unknown:
        _fail(unknown[0], "unknown header field", key)
    missing = [name for name in HEADER_FIELDS if name not in obj]
    if missing:
        _fail(missing[0], "missing", key)
    return version


def _check_identity(obj: dict, key: str | None) -> None:
    """The short names (run, producer, checksum), then run, index, t0 and fs."""
    for name in ("run", "producer", "checksum"):
        _check_name(obj[name], name, key)
    run = obj["run"]
    if not isinstance(run, str) or not run:
        _fail("run", f"expected a non-empty string, got {run!r}", key)
    index = obj["index"]
    if not _is_int(index) or index < 0:
        _fail("index", f"expected an integer >= 0, got {index!r}", key)
    t0 = obj["t0"]
    if not _is_number(t0) or not math.isfinite(t0):
        _fail("t0", f"expected a finite number [s], got {t0!r}", key)
    fs = obj["fs"]
    if not _is_number(fs) or not math.isfinite(fs) or fs <= 0:
        _fail("fs", f"expected a finite number > 0 [Hz], got {fs!r}", key)


def _checked_channels(channels, key: str | None) -> list[str]:
    """``channels``: a list of distinct short names."""
    if not isinstance(channels, list) or not all(isinstance(c, str) for c in channels):
        _fail("channels", f"expected a list of strings, got {channels!r}", key)
    for i, c in enumerate(channels):
        _check_name(c, f"channels[{i}]", key)
    if len(set(channels)) != len(channels):
        _fail("channels", f"duplicate channel names in {channels!r}", key)
    return channels


def _check_payload_fields(obj: dict, key: str | None) -> None:
    """The producer, payload_bytes, checksum and meta."""
    producer = obj["producer"]
    if not isinstance(producer, str):
        _fail("producer", f"expected a string, got {producer!r}", key)
    payload_bytes = obj["payload_bytes"]
    if not _is_int(payload_bytes) or payload_bytes < 0:
        _fail("payload_bytes", f"expected an integer >= 0, got {payload_bytes!r}", key)
    checksum = obj["checksum"]
    algorithm, _, digest = checksum.partition(":") if isinstance(checksum, str) else ("", "", "")
    if algorithm not in CHECKSUMS or not digest:
        _fail(
            "checksum", f"expected '<algorithm>:<hex>' with algorithm in {', '.join(CHECKSUMS)}, got {checksum!r}", key
        )
    meta = obj["meta"]
    if not isinstance(meta, dict):
        _fail("meta", f"expected a JSON object, got {type(meta).__name__}", key)


def _array_specs(arrays, channels: list[str], payload_bytes: int, key: str | None) -> tuple[ArraySpec, ...]:
    """The array descriptions: a non-empty list, each valid, names distinct, no two overlapping."""
    if not isinstance(arrays, list) or not arrays:
        _fail("arrays", "expected a non-empty list of array descriptions", key)
    specs = tuple(_array_spec(i, a, channels, payload_bytes, key) for i, a in enumerate(arrays))
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        _fail("arrays", f"duplicate array names in {names}", key)
    spans = sorted((s.offset, s.offset + s.nbytes, s.name) for s in specs)
    for (_, end, a), (start, _, b) in zip(spans, spans[1:]):
        if start < end:
            _fail(f"arrays[{b}].offset", f"overlaps array {a!r}", key)
    return specs


def _array_spec(i: int, a, channels: list, payload_bytes: int, key: str | None) -> ArraySpec:
    name = _array_name(i, a, key)
    where = f"arrays[{name}]"
    dtype, shape, offset, nbytes = a["dtype"], a["shape"], a["offset"], a["nbytes"]
    _check_layout(where, dtype, shape, offset, nbytes, payload_bytes, key)
    units = a["units"]
    _check_name(units, f"{where}.units", key)
    if not isinstance(units, str):
        _fail(f"{where}.units", f"expected a string, got {units!r}", key)
    axis = a["channel_axis"]
    if axis is not None:
        if not _is_int(axis) or not 0 <= axis < len(shape):
            _fail(f"{where}.channel_axis", f"expected null or an axis of shape {shape}, got {axis!r}", key)
        if shape[axis] != len(channels):
            _fail(
                "channels",
                f"{len(channels)} channel names {channels} but array {name!r} "
                f"has {shape[axis]} along its channel axis {axis} (shape {shape})",
                key,
            )
    return ArraySpec(
        name=name, dtype=dtype, shape=tuple(shape), offset=offset, nbytes=nbytes, units=units, channel_axis=axis
    )


def _array_name(i: int, a, key: str | None) -> str:
    """The name of array description ``i`` (``a``: an object with every field of
    :data:`ARRAY_FIELDS` and no other)."""
    if not isinstance(a, dict):
        _fail(f"arrays[{i}]", "expected a JSON object", key)
    name = a.get("name")
    _check_name(name, f"arrays[{i}].name", key)
    if not isinstance(name, str) or not name:
        _fail(f"arrays[{i}].name", f"expected a non-empty string, got {name!r}", key)
    where = f"arrays[{name}]"
    unknown = sorted(set(a) - set(ARRAY_FIELDS))
    if unknown:
        _fail(f"{where}.{unknown[0]}", "unknown array field", key)
    for f in ARRAY_FIELDS:
        if f not in a:
            _fail(f"{where}.{f}", "missing", key)
    return name


def _check_layout(where: str, dtype, shape, offset, nbytes, payload_bytes: int, key: str | None) -> None:
    """An array's dtype (allowed), shape, offset and size: within the payload."""
    if not isinstance(dtype, str) or dtype not in ALLOWED_DTYPES:
        _fail(f"{where}.dtype", f"dtype {dtype!r} is not allowed (allowed: {', '.join(sorted(ALLOWED_DTYPES))})", key)
    if not isinstance(shape, list) or not all(_is_int(s) and s >= 0 for s in shape):
        _fail(f"{where}.shape", f"expected a list of integers >= 0, got {shape!r}", key)
    if len(shape) > MAX_NDIM:
        _fail(f"{where}.shape", f"{len(shape)} axes (at most {MAX_NDIM})", key)
    if not _is_int(offset) or offset < 0:
        _fail(f"{where}.offset", f"expected an integer >= 0, got {offset!r}", key)
    expected = math.prod(shape) * np.dtype(dtype).itemsize
    if not _is_int(nbytes) or nbytes != expected:
        _fail(f"{where}.nbytes", f"{nbytes!r} does not match shape {shape} of {dtype} ({expected} bytes)", key)
    if offset + nbytes > payload_bytes:
        _fail(f"{where}.offset", f"bytes {offset}..{offset + nbytes} lie beyond payload_bytes={payload_bytes}", key)


def decode(
    payload, attachment, expect: Expect | None = None, *, key: str | None = None
) -> tuple[Header, dict[str, np.ndarray]]:
    """Validate and decode a segment message.

    Parameters
    ----------
    payload : bytes-like or zenoh.ZBytes
        The array bytes.
    attachment : bytes-like, str, zenoh.ZBytes or None
        The JSON header.
    expect : Expect, optional
        What the consumer requires (run, index, arrays, channels, finiteness).
    key : str, optional
        The Zenoh key the message came on; named in errors and kept in ``header.key``.

    Returns
    -------
    header : Header
    arrays : dict of str to ndarray
        Read-only views of the payload, in payload order.

    Raises
    ------
    CodecError
        If anything does not fit; ``err.field`` names the field at fault.
    """
    expect = expect or Expect()
    header = parse_header(attachment, key)
    data = _to_bytes(payload)
    n = len(data)
    if n != header.payload_bytes:
        what = "truncated" if n < header.payload_bytes else "too long"
        _fail("payload", f"{what}: {n} bytes received, header says payload_bytes={header.payload_bytes}", key)
    algorithm = header.checksum.partition(":")[0]
    actual = _checksum(algorithm, data)
    if actual != header.checksum:
        _fail("checksum", f"payload checksum {actual} does not match header {header.checksum}", key)

    _check_expected(header, expect, key)
    arrays: dict[str, np.ndarray] = {}
    for spec in header.arrays:
        arr = np.frombuffer(data, dtype=np.dtype(spec.dtype), count=math.prod(spec.shape), offset=spec.offset).reshape(
            spec.shape
        )
        arrays[spec.name] = arr
    _check_expected_arrays(header, arrays, expect, key)
    checked = arrays if not expect.allow_nonfinite else {k: arrays[k] for k in expect.finite if k in arrays}
    for name, arr in checked.items():
        bad, first = _count_nonfinite(arr)
        if bad:
            _fail(f"arrays[{name}]", f"{bad} non-finite values (NaN or inf), first at flat index {first}", key)
    return header, arrays


def _check_expected(header: Header, expect: Expect, key: str | None) -> None:
    """The run, index and channels the consumer expects."""
    if expect.run is not None and header.run != expect.run:
        _fail("run", f"message of run {header.run!r}, expected run {expect.run!r}", key)
    if expect.index is not None and header.index != expect.index:
        _fail("index", f"header index {header.index} differs from expected {expect.index}", key)
    if expect.channels is not None and tuple(header.channels) != tuple(expect.channels):
        _fail("channels", f"channels {list(header.channels)}, expected {list(expect.channels)}", key)


def _check_expected_arrays(header: Header, arrays: dict[str, np.ndarray], expect: Expect, key: str | None) -> None:
    """Each array the consumer requires: present, of its dtype and shape (``None``: any length)."""
    for name, (dtype, shape) in (expect.arrays or {}).items():
        if name not in arrays:
            _fail(f"arrays[{name}]", f"missing (message has {list(arrays)})", key)
        spec = header.array(name)
        if dtype is not None and np.dtype(dtype) != np.dtype(spec.dtype):
            _fail(f"arrays[{name}].dtype", f"{spec.dtype}, expected {np.dtype(dtype).str}", key)
        if shape is not None:
            ok = len(shape) == len(spec.shape) and all(e is None or e == s for e, s in zip(shape, spec.shape))
            if not ok:
                want = "(" + ", ".join("n" if e is None else str(e) for e in shape) + ")"
                _fail(f"arrays[{name}].shape", f"{spec.shape}, expected {want}", key)

"""The segment codec: round trips, and each malformed message rejected naming its field."""

import json
import time
import zlib

import numpy as np
import pytest

from streamer.bus.codec import CodecError, Expect, decode, encode, parse_header

FIELDS = {
    "run": "r1",
    "index": 7,
    "t0": 1.5e7,
    "fs": 4.0,
    "channels": ["X2", "Y2", "Z2"],
    "producer": "tdi_builder",
    "meta": {"note": "test"},
}


def tdi_message(n=64, **overrides):
    rng = np.random.default_rng(0)
    arrays = {"data": rng.standard_normal((3, n)), "regressors": rng.standard_normal((3, 24, n))}
    return arrays, encode(arrays, {**FIELDS, "units": {"data": "1", "regressors": "1/(m/rad)"}, **overrides})


def tamper(attachment: bytes, edit) -> bytes:
    header = json.loads(attachment)
    edit(header)
    return json.dumps(header).encode()


def test_round_trip_several_arrays_and_dtypes():
    rng = np.random.default_rng(1)
    arrays = {
        "data": rng.standard_normal((3, 100)),
        "regressors": rng.standard_normal((3, 24, 100)).astype(">f8"),  # big endian in, little out
        "f32": rng.standard_normal((3, 5)).astype(np.float32),
        "counts": np.arange(7, dtype=np.int64),
        "small": np.arange(3, dtype=np.int16),
        "mask": np.array([True, False, True]),
        "spectrum": (rng.standard_normal(3) + 1j).astype(np.complex128),
        "empty": np.zeros((3, 0)),
        "view": rng.standard_normal((6, 10))[::2, ::3],  # not contiguous
    }
    axes = {"counts": None, "small": 0, "mask": 0}
    payload, attachment = encode(arrays, {**FIELDS, "channel_axis": axes}, checksum="blake2b")
    header, out = decode(payload, attachment, Expect(run="r1", index=7, channels=("X2", "Y2", "Z2")))
    assert header.run == "r1" and header.index == 7 and header.t0 == 1.5e7 and header.fs == 4.0
    assert header.channels == ("X2", "Y2", "Z2") and header.producer == "tdi_builder"
    assert header.meta == {"note": "test"} and header.checksum.startswith("blake2b:")
    assert header.names == tuple(arrays)
    for name, arr in arrays.items():
        assert out[name].dtype == arr.dtype.newbyteorder("=") and out[name].shape == arr.shape, name
        np.testing.assert_array_equal(out[name], arr)
        assert header.array(name).offset % 8 == 0
    assert header.array("counts").channel_axis is None
    assert header.array("data").channel_axis == 0


def test_single_array_and_zenoh_bytes():
    import zenoh

    payload, attachment = encode(np.ones((3, 4)), FIELDS)
    header, arrays = decode(zenoh.ZBytes(payload), zenoh.ZBytes(attachment), key="ttl/r1/tdi/7")
    assert list(arrays) == ["data"] and header.key == "ttl/r1/tdi/7" and header.topic == "tdi"
    assert header.checksum == f"crc32:{zlib.crc32(payload):08x}"


def test_expectations_pass():
    _, (payload, attachment) = tdi_message()
    decode(payload, attachment, Expect(arrays={"data": ("<f8", (3, None)), "regressors": (None, (3, 24, 64))}))


def _cases():
    arrays, (payload, att) = tdi_message()
    n = len(payload)
    yield "attachment", payload, None, None
    yield "header", payload, b"{not json", None
    yield "header", payload, b"\xff\xfe", None
    yield "header", payload, b"[1, 2]", None
    yield "schema", payload, tamper(att, lambda h: h.update(schema="other")), None
    yield "version", payload, tamper(att, lambda h: h.update(version=2)), None
    yield "run", payload, tamper(att, lambda h: h.pop("run")), None
    yield "fs", payload, tamper(att, lambda h: h.pop("fs")), None
    yield "fs", payload, tamper(att, lambda h: h.update(fs=-4.0)), None
    yield "t0", payload, tamper(att, lambda h: h.update(t0="soon")), None
    yield "index", payload, tamper(att, lambda h: h.update(index=-1)), None
    yield "bogus", payload, tamper(att, lambda h: h.update(bogus=1)), None
    yield "meta", payload, tamper(att, lambda h: h.update(meta=[])), None
    yield "checksum", payload, tamper(att, lambda h: h.update(checksum="md5:abc")), None
    yield "arrays[data].dtype", payload, tamper(att, lambda h: h["arrays"][0].update(dtype=">f8")), None
    yield "arrays[data].dtype", payload, tamper(att, lambda h: h["arrays"][0].update(dtype="|O")), None
    yield "arrays[data].nbytes", payload, tamper(att, lambda h: h["arrays"][0].update(shape=[3, 65])), None
    yield "arrays[data].shape", payload, tamper(att, lambda h: h["arrays"][0].update(shape=[3, -64])), None
    yield "arrays[regressors].offset", payload, tamper(att, lambda h: h["arrays"][1].update(offset=8)), None
    yield "channels", payload, tamper(att, lambda h: h.update(channels=["X2", "Y2"])), None
    yield "payload", payload[: n - 100], att, None  # truncated
    yield "payload", payload + b"\0" * 8, att, None
    corrupted = bytearray(payload)
    corrupted[100] ^= 0xFF
    yield "checksum", bytes(corrupted), att, None
    yield "run", payload, att, Expect(run="another-run")
    yield "index", payload, att, Expect(index=8)
    yield "channels", payload, att, Expect(channels=("A", "E", "T"))
    yield "arrays[data].shape", payload, att, Expect(arrays={"data": (None, (2, None))})
    yield "arrays[data].dtype", payload, att, Expect(arrays={"data": ("<f4", None)})
    yield "arrays[truth]", payload, att, Expect(arrays={"truth": (None, None)})
    bad = {**arrays, "data": arrays["data"].copy()}
    bad["data"][1, 5] = np.nan
    bad["regressors"] = bad["regressors"].copy()
    bad["regressors"][0, 0, 0] = np.inf
    p2, a2 = encode(bad, {**FIELDS}, allow_nonfinite=True)
    yield "arrays[data]", p2, a2, None


@pytest.mark.parametrize(
    "field, payload, attachment, expect", list(_cases()), ids=[f"{i}-{c[0]}" for i, c in enumerate(_cases())]
)
def test_malformed_messages_are_rejected_naming_the_field(field, payload, attachment, expect):
    with pytest.raises(CodecError) as err:
        decode(payload, attachment, expect, key="ttl/r1/tdi/7")
    assert err.value.field == field
    assert repr(field) in str(err.value) and "ttl/r1/tdi/7" in str(err.value)


def test_nonfinite_allowed_when_expected():
    bad = np.ones((3, 4))
    bad[0, 0] = np.nan
    payload, attachment = encode(bad, FIELDS, allow_nonfinite=True)
    _, arrays = decode(payload, attachment, Expect(allow_nonfinite=True))
    assert np.isnan(arrays["data"][0, 0])


def test_arrays_named_finite_are_checked_when_nonfinite_is_allowed():
    """A fit may carry NaN in its model parts, never in its coefficients: Expect.finite."""
    fields = {k: v for k, v in FIELDS.items() if k != "channels"}
    coefficients = np.ones(24)
    coefficients[3] = np.inf
    parts = np.full((1, 3, 8), np.nan)
    payload, attachment = encode({"coefficients": coefficients, "model_parts": parts}, fields, allow_nonfinite=True)
    with pytest.raises(CodecError) as err:
        decode(payload, attachment, Expect(allow_nonfinite=True, finite=("coefficients",)))
    assert err.value.field == "arrays[coefficients]" and "first at flat index 3" in str(err.value)
    coefficients[3] = 1.0
    payload, attachment = encode({"coefficients": coefficients, "model_parts": parts}, fields, allow_nonfinite=True)
    _, arrays = decode(payload, attachment, Expect(allow_nonfinite=True, finite=("coefficients",)))
    assert np.isnan(arrays["model_parts"]).all()


@pytest.mark.parametrize(
    "arrays, fields, field",
    [
        (np.array([np.nan, 1.0, 2.0]), FIELDS, "arrays[data]"),
        (np.array(["a", "b", "c"]), FIELDS, "arrays[data].dtype"),
        (np.ones((2, 4)), FIELDS, "channels"),
        (np.ones(3), {k: v for k, v in FIELDS.items() if k != "fs"}, "fs"),
        (np.ones(3), {**FIELDS, "fs": float("inf")}, "fs"),
        (np.ones(3), {**FIELDS, "meta": {"x": object()}}, "meta"),
        (np.ones(3), {**FIELDS, "colour": "red"}, "colour"),
        ({}, FIELDS, "arrays"),
    ],
)
def test_encode_refuses_what_decode_would_reject(arrays, fields, field):
    with pytest.raises(CodecError) as err:
        encode(arrays, fields)
    assert err.value.field == field


def test_parse_header_alone():
    _, (_, attachment) = tdi_message()
    header = parse_header(attachment)
    assert header.to_json() and json.loads(header.to_json())["arrays"][1]["name"] == "regressors"


# ---------------------------------------------------------------------------- bounded parsing


def _raw_header(edit_text) -> tuple[bytes, bytes]:
    """A valid message whose header text is rewritten by ``edit_text(str) -> str``."""
    _, (payload, attachment) = tdi_message()
    return payload, edit_text(attachment.decode()).encode()


def _meta(text: str):
    """Edit: the header's ``meta`` replaced by JSON text ``text``."""
    return lambda h: h.replace('"meta":{"note":"test"}', f'"meta":{text}')


def _hostile_cases():
    deep = "[" * 100_000 + "]" * 100_000
    yield "deep-list", "header", _meta('{"x":' + deep + "}")
    yield "deep-object", "header", _meta('{"a":' * 50_000 + "1" + "}" * 50_000)
    yield "deep-33", "header", _meta('{"x":' + "[" * 31 + "]" * 31 + "}")
    yield "huge-exponent", "meta.x", _meta('{"x":1e999999}')
    yield "huge-negative-exponent-t0", "t0", lambda h: h.replace('"t0":15000000.0', '"t0":-1e400')
    yield "huge-int-index", "index", lambda h: h.replace('"index":7', '"index":' + "9" * 5000)
    yield (
        "int-beyond-64-bits",
        "payload_bytes",
        lambda h: h.replace('"payload_bytes":', '"payload_bytes":1' + "0" * 20 + ',"x":'),
    )
    yield "long-float", "fs", lambda h: h.replace('"fs":4.0', '"fs":4.' + "0" * 100)
    yield "nan", "meta.x", _meta('{"x":NaN}')
    yield "long-string-in-meta", "meta.s", _meta('{"s":"' + "a" * 900_000 + '"}')
    yield "long-key-in-meta", "meta", _meta('{"' + "k" * 70_000 + '":1}')
    yield "long-run", "run", lambda h: h.replace('"run":"r1"', '"run":"' + "r" * 5000 + '"')
    yield (
        "long-producer",
        "producer",
        lambda h: h.replace('"producer":"tdi_builder"', '"producer":"' + "p" * 5000 + '"'),
    )
    yield "long-channel", "channels[0]", lambda h: h.replace('"X2"', '"' + "X" * 5000 + '"', 1)
    yield "long-units", "arrays[data].units", lambda h: h.replace('"units":"1"', '"units":"' + "u" * 5000 + '"', 1)
    yield "escaped-quotes", "header", lambda h: h[:-1] + ',"z":"' + '\\"' * 400_000 + "}"
    yield "dtype-a-list", "arrays[data].dtype", lambda h: h.replace('"dtype":"<f8"', '"dtype":["<f8"]', 1)
    yield "dtype-an-object", "arrays[data].dtype", lambda h: h.replace('"dtype":"<f8"', '"dtype":{"a":1}', 1)
    yield (
        "too-many-axes",
        "arrays[data].shape",
        lambda h: h.replace('"shape":[3,64]', '"shape":[' + "1," * 40 + "3,64]", 1),
    )


@pytest.mark.parametrize("name, field, edit", list(_hostile_cases()), ids=[c[0] for c in _hostile_cases()])
def test_hostile_headers_are_refused_quickly_naming_the_field(name, field, edit):
    """Deep nesting, huge numbers and long strings: a CodecError naming the field, never a
    RecursionError or a ValueError from Python's JSON parser, in well under a second."""
    payload, attachment = _raw_header(edit)
    assert len(attachment) <= (1 << 20)  # under the size limit: the parser has to deal with it
    t = time.perf_counter()
    with pytest.raises(CodecError) as err:
        decode(payload, attachment, key="ttl/r1/tdi/7")
    assert time.perf_counter() - t < 1.0
    assert err.value.field == field, err.value
    assert len(str(err.value)) < 700  # the refused value is not quoted whole


def test_legitimate_nesting_and_sizes_pass():
    meta = {
        "a": [{"b": [{"c": [[1, 2], [3.5e300, -2.5e-300]]}]}],
        "path": "/x" * 2000,
        "big": 2**63,
        "quote": 'a "[{" b \\ c',
    }
    payload, attachment = encode(np.ones((3, 4)), {**FIELDS, "meta": meta})
    header, _ = decode(payload, attachment)
    assert header.meta == meta


JSON_VALUES = [
    None,
    True,
    False,
    0,
    -1,
    2**63,
    1.5,
    -1e308,
    1e-308,
    "",
    "x",
    "<f8",
    [],
    [1],
    [[]],
    ["a"],
    {},
    {"a": 1},
    {"name": "data"},
]


def _every_field_every_type():
    _, (payload, attachment) = tdi_message()
    header = json.loads(attachment)
    for name in header:
        for value in JSON_VALUES:
            h = json.loads(attachment)
            h[name] = value
            yield f"{name}={json.dumps(value)}", payload, json.dumps(h).encode()
    for name in header["arrays"][0]:
        for value in JSON_VALUES:
            h = json.loads(attachment)
            h["arrays"][0][name] = value
            yield f"arrays[0].{name}={json.dumps(value)}", payload, json.dumps(h).encode()
    for value in JSON_VALUES:
        h = json.loads(attachment)
        h["arrays"][0] = value
        yield f"arrays[0]={json.dumps(value)}", payload, json.dumps(h).encode()
        yield f"header={json.dumps(value)}", payload, json.dumps(value).encode()


def test_every_json_type_in_every_field_is_decoded_or_refused_by_field():
    """The only outcomes of any value in any field: a decoded message, or a CodecError."""
    outcomes = {}
    for case, payload, attachment in _every_field_every_type():
        try:
            decode(payload, attachment, key="ttl/r1/tdi/7")
            outcomes[case] = "ok"
        except CodecError as exc:
            outcomes[case] = exc.field
    assert len(outcomes) > 300
    assert outcomes["meta={}"] == "ok" and outcomes["index=0"] == "ok"
    assert outcomes["arrays[0].dtype=[]"] == "arrays[data].dtype"
    assert outcomes["header=[1]"] == "header" and outcomes["run=0"] == "run"

"""Unit tests of :mod:`streamer.bus.bounded_json`: JSON from an untrusted peer, every size bounded."""

import json

import pytest

from streamer.bus.bounded_json import (
    MAX_DEPTH,
    MAX_NUMBER_CHARS,
    MAX_STRING_CHARS,
    BoundedJSONError,
    load_bounded,
    nesting_depth,
)


@pytest.mark.parametrize(
    "text, depth",
    [
        (b"", 0),
        (b"1", 0),
        (b"{}", 1),
        (b'{"a": [1, {"b": []}]}', 4),
        # brackets inside strings do not count, an escaped quote does not end the string
        (b'{"a": "[[[{{{"}', 1),
        (b'{"a": "x\\"[[[", "b": [1]}', 2),
        # an escaped backslash before a quote: the quote ends the string
        (b'{"a": "x\\\\", "b": [[1]]}', 3),
    ],
)
def test_nesting_depth_counts_brackets_outside_strings(text, depth):
    assert nesting_depth(text) == depth


def test_a_header_within_bounds_is_read_as_json():
    header = {"run": "r1", "index": 7, "t0": 1.5e3, "meta": {"truth": {"coefficients": [1.0, -2, 3e-12]}}}
    assert load_bounded(json.dumps(header).encode()) == header


def test_too_deep_is_refused_before_parsing():
    raw = b"[" * (MAX_DEPTH + 1) + b"]" * (MAX_DEPTH + 1)
    with pytest.raises(BoundedJSONError, match=f"nested {MAX_DEPTH + 1} levels") as err:
        load_bounded(raw)
    assert err.value.field == "header"
    assert load_bounded(b"[" * MAX_DEPTH + b"]" * MAX_DEPTH) is not None


@pytest.mark.parametrize(
    "raw, field, what",
    [
        (
            b'{"meta": {"truth": {"coefficients": [1, 2, 3, ' + b"9" * (MAX_NUMBER_CHARS + 1) + b"]}}}",
            "meta.truth.coefficients[3]",
            "an integer of",
        ),
        (b'{"t0": 1' + b"0" * MAX_NUMBER_CHARS + b".5}", "t0", "a number of"),
        (b'{"index": 18446744073709551616}', "index", "outside [-2**63, 2**64)"),
        (b'{"fs": 1e999}', "fs", "non-finite"),
        (b'{"fs": NaN}', "fs", "non-finite number NaN"),
        (b'{"a": [Infinity]}', "a[0]", "non-finite number Infinity"),
    ],
)
def test_a_bad_number_is_named_by_its_field(raw, field, what):
    with pytest.raises(BoundedJSONError) as err:
        load_bounded(raw)
    assert err.value.field == field
    assert what in err.value.what


def test_long_strings_and_keys_are_refused():
    value = json.dumps({"meta": {"source": "x" * (MAX_STRING_CHARS + 1)}}).encode()
    with pytest.raises(BoundedJSONError, match="a string of") as err:
        load_bounded(value)
    assert err.value.field == "meta.source"
    key = json.dumps({"meta": {"k" * (MAX_STRING_CHARS + 1): 1}}).encode()
    with pytest.raises(BoundedJSONError, match="a key of") as err:
        load_bounded(key)
    assert err.value.field == "meta"


def test_text_that_is_not_json_names_the_root():
    with pytest.raises(BoundedJSONError, match="not valid JSON") as err:
        load_bounded(b'{"a": ', root="payload")
    assert err.value.field == "payload"
    with pytest.raises(BoundedJSONError, match="not valid JSON"):
        load_bounded(b"\xff\xfe")

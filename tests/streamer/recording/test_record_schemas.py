"""Unit tests of :mod:`streamer.recording.record_schemas`: the schemas describe what is written."""

import json
import time

import numpy as np
import pytest

from streamer.bus.codec import ARRAY_FIELDS, HEADER_FIELDS, encode
from streamer.recording.record_schemas import (
    ERROR_SCHEMA,
    EVENT_SCHEMA,
    HEADER_SCHEMA,
    SCHEMAS,
    TOPIC_SCHEMAS,
    WARNING_SCHEMA,
    stage_record,
)

_TYPES = {
    "string": str,
    "integer": int,
    "number": (int, float),
    "object": dict,
    "array": list,
    "null": type(None),
}


def _fits(value, schema) -> list[str]:
    """What of ``value`` does not fit ``schema`` (the keywords these schemas use)."""
    wrong = []
    if "const" in schema and value != schema["const"]:
        wrong.append(f"{value!r} is not {schema['const']!r}")
    if "type" in schema:
        types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(isinstance(value, _TYPES[t]) and not isinstance(value, bool) for t in types):
            wrong.append(f"{value!r} is not {types}")
    if isinstance(value, dict):
        wrong += [f"missing {k}" for k in schema.get("required", []) if k not in value]
        for k, sub in schema.get("properties", {}).items():
            if k in value:
                wrong += [f"{k}: {w}" for w in _fits(value[k], sub)]
    if isinstance(value, list) and "items" in schema:
        for i, item in enumerate(value):
            wrong += [f"[{i}]: {w}" for w in _fits(item, schema["items"])]
    return wrong


def test_every_schema_is_named_and_requires_only_what_it_describes():
    for title, schema in SCHEMAS.items():
        assert schema["title"] == title
        assert set(schema.get("required", [])) <= set(schema.get("properties", {})), title
    assert set(TOPIC_SCHEMAS.values()) <= set(SCHEMAS)


def test_a_real_segment_header_fits_the_header_schema():
    assert HEADER_SCHEMA["required"] == list(HEADER_FIELDS)
    assert HEADER_SCHEMA["properties"]["arrays"]["items"]["required"] == list(ARRAY_FIELDS)
    arrays = {"data": np.zeros((3, 8)), "regressors": np.ones((3, 2, 8), dtype=np.float32)}
    _, attachment = encode(arrays, {"run": "r1", "index": 4, "t0": 3600.0, "fs": 4.0, "channels": ["X", "Y", "Z"]})
    header = json.loads(attachment)
    assert _fits(header, HEADER_SCHEMA) == []
    header["index"] = "4"
    assert _fits(header, HEADER_SCHEMA) == ["index: '4' is not ['integer']"]


@pytest.mark.parametrize("schema", [ERROR_SCHEMA, WARNING_SCHEMA, EVENT_SCHEMA])
def test_stage_records_fit_their_schemas(schema):
    before = time.time()
    record = stage_record("r1", "fitter", "rejected", "bad header", index=3, details={"n": 1}, key="ttl/r1/tdi/3")
    assert _fits(record, schema) == []
    assert before <= record["time"] <= time.time()
    assert (record["index"], record["key"], record["details"]) == (3, "ttl/r1/tdi/3", {"n": 1})
    # no index (the launcher's records), no details: still a record of the schema
    bare = stage_record("r1", "launcher", "start")
    assert bare["index"] is None and bare["details"] == {} and bare["message"] == ""
    assert _fits(bare, schema) == []

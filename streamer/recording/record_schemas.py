"""The JSON records of a recording: their JSON schemas (:data:`SCHEMAS`, by name; the
schema of each fixed topic, :data:`TOPIC_SCHEMAS`) and the record of an error, warning or
event of a stage (:func:`stage_record`).  See :mod:`streamer.recording.recorder` for the
layout of a recording (values are made JSON by :func:`streamer.bus.message_schema.to_jsonable`)."""

from __future__ import annotations

import time

from ..bus.codec import ARRAY_FIELDS, HEADER_FIELDS

#: Message encoding of payload channels.
PAYLOAD_ENCODING = "application/octet-stream"

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


#: JSON schema of a segment header (:mod:`streamer.bus.codec`).
HEADER_SCHEMA = _object_schema(
    "ttl.SegmentHeader",
    list(HEADER_FIELDS),
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
                "required": list(ARRAY_FIELDS),
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

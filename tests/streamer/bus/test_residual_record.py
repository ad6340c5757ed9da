"""The residual message's meta as a value (streamer/bus/residual_record.py): round trip, the
errors at the boundary, and headers as the subtractor wrote them before the schema field."""

from __future__ import annotations

import json

import numpy as np
import pytest

from streamer.bus.residual_record import SCHEMA, MessageError, ResidualMessage

# residual/0 and residual/1 of a recording written by main before ``schema`` (ttl run
# --simulate "--duration 12h --orbit unequal --seed 1" --segment 1h, commit 88bef55)
RECORDED = [
    {"fit_index": 0, "coefficients_t_start": -30.0, "coefficients_t_stop": 3570.0, "segments_total": 12, "effects": []},
    {"fit_index": 1, "coefficients_t_start": -30.0, "coefficients_t_stop": 7170.0, "segments_total": 12, "effects": []},
]
# the other fields the subtractor of that commit wrote: no fit yet; a fit's parts not
# subtracted; an earlier fit applied again (its ``stale``)
NO_FIT = {"fit_index": None, "coefficients_t_start": None, "coefficients_t_stop": None, "segments_total": None}
OLD = {
    "fit_index": 7,
    "coefficients_t_start": 0.0,
    "coefficients_t_stop": 28800.0,
    "segments_total": 48,
    "effects": [],
    "model_parts_missing": ["drift", "glitch:t=100s"],
    "fit_stale": {"since": 5, "no_data": True},
}


@pytest.mark.parametrize("old", [*RECORDED, {**NO_FIT, "effects": []}, OLD], ids=["rec0", "rec1", "no-fit", "stale"])
def test_an_old_header_without_schema_is_read_and_written_back_with_it(old):
    m = ResidualMessage.from_header(json.loads(json.dumps(old)), "residual 3")
    assert m.schema == 0
    assert m.fit_index == old["fit_index"] and m.effects == tuple(old["effects"])
    header = m.to_header()
    assert header == {**old, "schema": SCHEMA}
    assert list(header) == [*old, "schema"]  # the order the subtractor writes
    assert ResidualMessage.from_header(header) == m


def test_the_attributes_of_an_old_header():
    m = ResidualMessage.from_header(OLD)
    assert m.model_parts_missing == ("drift", "glitch:t=100s")
    assert m.fit_stale == {"since": 5, "no_data": True}
    assert m.coefficients_t_stop == 28800.0 and m.segments_total == 48


def test_an_old_header_may_lack_fields_and_hold_ones_no_longer_read():
    m = ResidualMessage.from_header({"fit_index": 4, "segments_total": 14, "retired": 1}, "residual 4")
    assert m.fit_index == 4 and m.effects is None and m.coefficients_t_start is None


def test_the_producer_builds_the_header_the_subtractor_wrote():
    m = ResidualMessage.build(
        "residual 7",
        fit_index=np.int64(7),
        coefficients_t_start=np.float64(0.0),
        coefficients_t_stop=28800.0,
        segments_total=48,
        effects=[],
        model_parts_missing=["drift", "glitch:t=100s"],
        fit_stale={"since": 5, "no_data": True},
    )
    assert json.dumps(m.to_header()) == json.dumps({**OLD, "schema": SCHEMA})
    none = ResidualMessage.build(**NO_FIT, effects=[], model_parts_missing=None, fit_stale=None)
    assert none.to_header() == {**NO_FIT, "effects": [], "schema": SCHEMA}
    with pytest.raises(MessageError, match=r"residual 7: meta field 'effects': missing"):
        ResidualMessage.build("residual 7", **NO_FIT)
    with pytest.raises(MessageError, match=r"residual 7: meta field 'fit': unknown field"):
        ResidualMessage.build("residual 7", **NO_FIT, effects=[], fit=3)


def test_a_current_header_is_read_strictly():
    header = {**OLD, "schema": SCHEMA}
    assert ResidualMessage.from_header(header).to_header() == header
    for name in ("fit_index", "coefficients_t_start", "coefficients_t_stop", "segments_total", "effects"):
        missing = {k: v for k, v in header.items() if k != name}
        with pytest.raises(MessageError, match=rf"residual 9: meta field '{name}': missing"):
            ResidualMessage.from_header(missing, "residual 9")
    with pytest.raises(MessageError, match=r"residual 9: meta field 'retired': unknown field"):
        ResidualMessage.from_header({**header, "retired": 1}, "residual 9")
    with pytest.raises(MessageError, match=r"residual 9: meta field 'schema': this reader knows schemas"):
        ResidualMessage.from_header({**header, "schema": SCHEMA + 1}, "residual 9")
    with pytest.raises(MessageError, match=r"residual 9: meta field 'meta': expected a mapping"):
        ResidualMessage.from_header([1], "residual 9")


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("fit_index", 2.5),
        ("fit_index", True),
        ("coefficients_t_start", "early"),
        ("segments_total", "12"),
        ("effects", "drift"),
        ("effects", [1]),
        ("model_parts_missing", [None]),
        ("fit_stale", True),
    ],
)
def test_a_field_of_the_wrong_type_is_an_error_naming_it(field, value):
    for header in (OLD, {**OLD, "schema": SCHEMA}):
        with pytest.raises(MessageError, match=f"residual 2: meta field '{field}': expected"):
            ResidualMessage.from_header({**header, field: value}, "residual 2")

"""The monitor's status message's meta as a value (streamer/bus/monitor_record.py): round trip,
the errors at the boundary, and a header as the monitor wrote it before the schema field."""

from __future__ import annotations

import json

import numpy as np
import pytest

from streamer.bus.monitor_record import SCHEMA, MessageError, MonitorMessage
from ttlcore.conventions import COEFFICIENT_NAMES

# monitor/11 of a recording written by main before ``schema`` (ttl run --simulate "--duration
# 12h --orbit unequal --seed 1" --segment 1h, commit 88bef55)
RECORDED = {
    "names": list(COEFFICIENT_NAMES),
    "alerts": [],
    "drifting": [],
    "drift_windows": 12,
    "model_epoch": {"number": 0, "index": 0, "t_start": -30.0, "t_stop": 3570.0, "model": ["linear-ttl"], "breaks": []},
    "residual_over_expected": {"index": 11, "ratio": 1.0045337428086927},
    "fit": {"index": 11, "chi2_dof": 0.9389324385664655, "t_start": -30.0, "t_stop": 43170.0},
    "segments_total": 12,
}
ALERT = {"kind": "step", "coefficient": "12.phi.rx", "t": 3600.0, "value": 0.1, "units": "mm/rad"}
# before the first fit and trend evaluation
FIRST = {**RECORDED, "drift_windows": 0, "model_epoch": None, "residual_over_expected": None, "fit": None}


@pytest.mark.parametrize("old", [RECORDED, FIRST, {**RECORDED, "alerts": [ALERT], "drifting": ["12.phi.rx"]}])
def test_an_old_header_without_schema_is_read_and_written_back_with_it(old):
    m = MonitorMessage.from_header(json.loads(json.dumps(old)), "monitor 11")
    assert m.schema == 0 and m.names == tuple(COEFFICIENT_NAMES)
    assert m.alerts == tuple(old["alerts"]) and m.drift_windows == old["drift_windows"]
    header = m.to_header()
    assert json.dumps(header) == json.dumps({**old, "schema": SCHEMA})  # same order and values
    assert m.summary_fields() == old
    assert MonitorMessage.from_header(header) == m


def test_the_producer_builds_the_header_the_monitor_wrote():
    fields = {**RECORDED, "fit": {**RECORDED["fit"], "chi2_dof": np.float64(0.9389324385664655)}}
    m = MonitorMessage.build("monitor 11", **fields)
    assert json.dumps(m.to_header()) == json.dumps({**RECORDED, "schema": SCHEMA})
    # non-finite values become null, as to_jsonable made them
    nan = MonitorMessage.build(**{**RECORDED, "residual_over_expected": {"index": 3, "ratio": float("nan")}})
    assert nan.residual_over_expected == {"index": 3, "ratio": None}
    with pytest.raises(MessageError, match=r"monitor 4: meta field 'fit': missing"):
        MonitorMessage.build("monitor 4", **{k: v for k, v in RECORDED.items() if k != "fit"})


def test_a_current_header_is_read_strictly():
    header = {**RECORDED, "schema": SCHEMA}
    for name in RECORDED:
        with pytest.raises(MessageError, match=rf"monitor 2: meta field '{name}': missing"):
            MonitorMessage.from_header({k: v for k, v in header.items() if k != name}, "monitor 2")
    with pytest.raises(MessageError, match=r"monitor 2: meta field 'extra': unknown field"):
        MonitorMessage.from_header({**header, "extra": 1}, "monitor 2")
    # schema 0: unknown fields dropped, absent ones None
    m = MonitorMessage.from_header({"alerts": [ALERT], "extra": 1}, "monitor 2")
    assert m.alerts == (ALERT,) and m.fit is None


@pytest.mark.parametrize(
    ("field", "value", "where"),
    [
        ("alerts", {"kind": "step"}, "'alerts'"),
        ("alerts", ["step"], r"'alerts\[0\]'"),
        ("drifting", [1], "'drifting'"),
        ("drift_windows", 1.5, "'drift_windows'"),
        ("fit", [11], "'fit'"),
        ("segments_total", "12", "'segments_total'"),
    ],
)
def test_a_field_of_the_wrong_type_is_an_error_naming_it(field, value, where):
    for header in (RECORDED, {**RECORDED, "schema": SCHEMA}):
        with pytest.raises(MessageError, match=f"monitor 5: meta field {where}: expected"):
            MonitorMessage.from_header({**header, field: value}, "monitor 5")

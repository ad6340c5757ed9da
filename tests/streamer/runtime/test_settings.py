"""Typed settings (streamer.runtime.settings): StageConfig and RunOptions round-trip through JSON,
and a value that does not fit is refused naming the field."""

import json
from pathlib import Path

import pytest

from streamer.bus.session import SessionConfigError
from streamer.launch.launch_plan import RunOptions
from streamer.runtime.settings import SettingsError
from streamer.runtime.stage_config import StageConfig


def test_stage_config_round_trips_through_json():
    config = StageConfig(
        run="r1",
        stage="fitter",
        recordings=Path("/tmp/rec"),
        history=4,
        hold=0,
        options={"effects": ["linear-ttl"]},
        plan={"segments_total": 3, "fs": 4.0, "t0": 0.0, "samples": 14400, "samples_total": 43200},
        launcher_pid=12,
        progress_from="launcher",
    )
    d = json.loads(json.dumps(config.to_dict()))
    assert d["recordings"] == "/tmp/rec" and d["hold"] == 0 and isinstance(d["zenoh"], dict)
    assert StageConfig.from_dict(d) == config
    assert list(d) == [
        "run",
        "stage",
        "zenoh",
        "recordings",
        "cache",
        "history",
        "record_inputs",
        "record_outputs",
        "poll_interval",
        "gap_grace",
        "hold",
        "options",
        "plan",
        "launcher_pid",
        "orphan_grace",
        "progress_from",
    ]


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"hold": "x"}, "field 'hold': expected a number, got 'x'"),
        ({"hold": -1}, "field 'hold': expected a number >= 0"),
        ({"poll_interval": 0}, "field 'poll_interval': expected a number > 0"),
        ({"cache": 1.5}, "field 'cache': expected an integer"),
        ({"record_inputs": "no"}, "field 'record_inputs': expected true or false"),
        ({"progress_from": "me"}, "field 'progress_from': expected one of 'stages', 'launcher'"),
        ({"options": []}, "field 'options': expected a mapping"),
        ({"plan": {"x": 1}}, "field 'plan': not a plan"),
        ({"run": "a b"}, "field 'run'"),
        ({"colour": 1}, "unknown field 'colour'"),
    ],
)
def test_bad_stage_config_names_the_field(fields, message):
    with pytest.raises(SettingsError, match="^stage configuration: ") as err:
        StageConfig.from_dict({"run": "r1", **fields})
    assert message in str(err.value)


def test_stage_config_missing_run_and_bad_session():
    with pytest.raises(SettingsError, match="field 'run' missing"):
        StageConfig.from_dict({})
    with pytest.raises(SessionConfigError, match="unknown field 'colour'"):
        StageConfig.from_dict({"run": "r1", "zenoh": {"colour": 1}})
    assert StageConfig.from_dict({"run": "r1", "zenoh": None}).zenoh == StageConfig(run="r1").zenoh


def test_stage_config_checked_when_built_in_code():
    with pytest.raises(SettingsError, match="field 'gap_grace'"):
        StageConfig(run="r1", gap_grace=float("nan"))
    config = StageConfig(run="r1", recordings="rec")  # a string path is converted
    assert config.recordings == Path("rec")
    config.cache = 0
    with pytest.raises(SettingsError, match="field 'cache'"):
        config.check()


def test_run_options_round_trip_and_errors():
    opts = RunOptions(run_id="r1", recordings="rec", listen=["tls/127.0.0.1:7447"], skip=("monitor",), pace=450)
    assert opts.recordings == Path("rec") and opts.listen == ("tls/127.0.0.1:7447",)
    assert RunOptions.from_dict(json.loads(json.dumps(opts.to_dict()))) == opts
    with pytest.raises(SettingsError, match="run options: field 'window': expected an integer, got '4'"):
        RunOptions(run_id="r1", window="4")
    with pytest.raises(SettingsError, match="run options: field 'restart': expected a number >= 0"):
        RunOptions(run_id="r1", restart=-1)
    with pytest.raises(SettingsError, match="run options: unknown field 'colour'"):
        RunOptions.from_dict({"run_id": "r1", "colour": 1})

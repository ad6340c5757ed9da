"""Each stage's options parsed once into a frozen value (issue 34 item 3): an unknown option
or a value that does not parse stops the stage at start with the option named; the stage
reads them by attribute."""

import dataclasses

import pytest

from stages.fitter.fitter import Fitter
from stages.fitter.options import FitterOptions
from stages.monitor.options import MonitorOptions
from stages.replayer import ReplayerOptions
from stages.subtractor import Subtractor, SubtractorOptions
from stages.tdi_builder import TDIBuilderOptions
from streamer.runtime.stage import StageConfig
from streamer.runtime.stage_options import OrderedOptions
from ttlcore.conventions import DAY
from ttlcore.errors import ConfigError


def test_defaults_and_given_values_are_read_once_with_their_units():
    o = FitterOptions.parse(
        {"window_duration": "12h", "band": [1e-3, 0.5], "effect_modules": "a.py,b", "adopt": None}, "fitter"
    )
    assert o.window_duration == 43200.0 and o.band == (1e-3, 0.5) and o.effect_modules == ("a.py", "b")
    assert o.adopt == "ask" and o.diagnose_every == 24 and o.settle == 1.0 and o.effects == ("linear-ttl",)
    assert o.diagnosis_workers == 1 and FitterOptions.parse({"diagnosis_workers": 2}, "fitter").diagnosis_workers == 2
    assert FitterOptions.parse({}, "fitter").window_duration == DAY
    assert isinstance(FitterOptions.parse({}, "fitter"), OrderedOptions)
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.adopt = "auto"  # type: ignore[misc]
    r = ReplayerOptions.parse({"telemetry": "a.h5", "segment": "30min", "wait_for": ["fitter"]}, "replayer")
    assert r.telemetry == ("a.h5",) and r.segment == 1800.0 and r.wait_for == ("fitter",) and r.window >= 1
    assert SubtractorOptions.parse({"fit_timeout": 5}, "subtractor").fit_timeout == 5.0
    assert TDIBuilderOptions.parse({"order": 31}, "tdi_builder").order == 31
    assert MonitorOptions.parse({"trends": {"step_threshold": 6.0}}, "monitor").trends.step_threshold == 6.0


@pytest.mark.parametrize(
    ("cls", "given", "message"),
    [
        (FitterOptions, {"adopt": "sometimes"}, "fitter option adopt (--adopt): expected one of ask, auto, never"),
        (FitterOptions, {"window_duration": "soon"}, "fitter option window_duration (--window-duration)"),
        (FitterOptions, {"band": [0.5, 0.1]}, "0 < FMIN < FMAX"),
        (FitterOptions, {"diagnose_every": -1}, "expected an integer >= 0"),
        (FitterOptions, {"diagnose_evry": 6}, "fitter: unknown option 'diagnose_evry' (known: settle, gap_timeout"),
        (ReplayerOptions, {"pace": float("nan")}, "replayer option pace (--pace)"),
        (ReplayerOptions, {"window": 0}, "replayer option window (--window): expected an integer >= 1"),
        (ReplayerOptions, {"telemetry": ["a.h5"], "simulate": "--duration 1h"}, "either --telemetry or --simulate"),
        (SubtractorOptions, {"fit_timeout": "x"}, "subtractor option fit_timeout (--fit-timeout)"),
        (MonitorOptions, {"live": "somewhere"}, "monitor option live (--live)"),
        (MonitorOptions, {"trends": {"step_treshold": 5}}, "unknown field 'step_treshold'"),
    ],
)
def test_a_bad_option_is_refused_with_its_name(cls, given, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        cls.parse(given, cls.__name__.removesuffix("Options").lower().replace("tdibuilder", "tdi_builder"))


def test_a_stage_with_a_bad_option_stops_at_start(tmp_path):
    with pytest.raises(ConfigError, match="fitter option adopt"):
        Fitter(StageConfig(run="u", recordings=tmp_path, options={"adopt": "sometimes"}))
    with pytest.raises(ConfigError, match="subtractor: unknown option 'fit_timout'"):
        Subtractor(StageConfig(run="u", recordings=tmp_path, options={"fit_timout": 5}))
    s = Subtractor(StageConfig(run="u", recordings=tmp_path, options={"fit_timeout": 5, "settle": 0}))
    assert isinstance(s.options, SubtractorOptions) and s.fit_timeout == 5.0 and s.settle == 0.0

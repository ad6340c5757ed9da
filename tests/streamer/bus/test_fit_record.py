"""The fit message's meta as a value (streamer/bus/fit_record.py): round trip, the errors at the
boundary, and a header as the fitter wrote it before the schema field (recordings on disk)."""

from __future__ import annotations

import json

import pytest

from streamer.bus.diagnosis_record import Adoption, LiveDiagnosis
from streamer.bus.fit_record import (
    SCHEMA,
    SUMMARY_META,
    Adequacy,
    FitMessage,
    FitSummary,
    MessageError,
    ModelChange,
    RankedCandidate,
    RollingEstimate,
)

# the meta of a fit message as stages/fitter/fitter.py put it on the wire before ``schema`` (a window
# refit of the rolling model, the live diagnosis, an FFT segment left out): what a recording
# already on disk holds
OLD = {
    "names": ["a", "b"],
    "chi2_dof": 1.02,
    "t_start": 0.0,
    "t_stop": 86400.0,
    "segments": 23,
    "band": [0.003, 0.9],
    "converged": True,
    "chi2": 1020.0,
    "dof": 1000,
    "iterations": 3,
    "method": "gls",
    "window_duration": 86400.0,
    "fft_segment": 3600.0,
    "segments_total": 48,
    "model": ["linear-ttl", "drift"],
    "extra_parameters": {"drift": [1e-9, 1e-10]},
    "model_parts": ["drift"],
    "model_update": "window refit",
    "rolling": {"coefficients": [1.0, 2.0], "sigma": [0.1, 0.2]},
    "adequacy": {
        "noise_model": "instrument",
        "chi2_dof": 1.1,
        "fails": False,
        "summary": [],
        "bands": [{"f_lo": 0.003, "f_hi": 0.01, "chi2_dof": 1.1, "p_value": 0.2, "fails": False}],
        "gates": [[10.0, 20.0]],
    },
    "window": {"first": 0, "last": 23},
    "model_change": {"before": ["linear-ttl"], "after": ["linear-ttl", "drift"], "bands_before": [2.0]},
    "candidates": [{"effect": "step", "spec": "step", "delta_chi2": 3.0}],
    "diagnosis": {"adoption": {"adopted": True, "reason": "better"}},
    "stale": {"since": 3, "no_data": True},
    "excluded": {"t_start": 0.0, "t_stop": 3600.0, "gap": True},
}


def test_an_old_header_without_schema_is_read_and_written_back_with_it():
    m = FitMessage.from_header(json.loads(json.dumps(OLD)))
    assert m.schema == 0
    assert m.names == ("a", "b") and m.model == ("linear-ttl", "drift") and m.segments_total == 48
    assert isinstance(m.adequacy, Adequacy) and m.adequacy.bands[0].p_value == 0.2
    assert m.adequacy.gates == ((10.0, 20.0),)
    assert m.rolling == RollingEstimate((1.0, 2.0), (0.1, 0.2))
    assert m.adopted == Adoption(None, True, "better")
    header = m.to_header()
    assert header == {**OLD, "schema": SCHEMA}  # the same fields and values, and the schema
    assert FitMessage.from_header(header) == m


def test_an_old_header_may_lack_fields_and_hold_ones_no_longer_read():
    m = FitMessage.from_header({"names": ["a"], "t_start": 0.0, "t_stop": 1.0, "retired": 3})
    assert m.model is None and m.adequacy is None and m.t_stop == 1.0


def test_a_current_header_is_read_strictly():
    header = {**OLD, "schema": SCHEMA}
    assert FitMessage.from_header(header).to_header() == header
    missing = dict(header)
    del missing["fft_segment"]
    with pytest.raises(MessageError, match=r"fit 7: meta field 'fft_segment': missing"):
        FitMessage.from_header(missing, "fit 7")
    with pytest.raises(MessageError, match=r"fit 7: meta field 'retired': unknown field"):
        FitMessage.from_header({**header, "retired": 1}, "fit 7")
    with pytest.raises(MessageError, match="knows schemas"):
        FitMessage.from_header({**header, "schema": SCHEMA + 1}, "fit 7")


# a model change and a ranking as stages/fitter/window_refit.py writes them (every key, null where
# the models cannot be compared)
CHANGE = {
    "before": ["linear-ttl"],
    "after": ["linear-ttl", "drift"],
    "chi2_dof_before": 1.4,
    "chi2_dof_after": 1.01,
    "bands_before": [2.0, None],
    "bands_after": [1.0, 1.02],
    "delta_chi2": None,
    "log_bayes_factor": None,
    "band_edges": [0.003, 0.01, 0.9],
}
RANKING = [
    {
        "effect": "drift",
        "spec": "drift",
        "delta_chi2": 40.5,
        "log_bayes_factor": 12.0,
        "explained_fraction": 0.8,
        "significant": True,
    },
    {
        "effect": "step",
        "spec": None,
        "delta_chi2": None,
        "log_bayes_factor": None,
        "explained_fraction": None,
        "significant": False,
    },
]


def test_the_model_change_and_candidates_are_values_written_back_as_they_came():
    header = {**OLD, "model_change": CHANGE, "candidates": RANKING, "schema": SCHEMA}
    m = FitMessage.from_header(json.loads(json.dumps(header)), "fit 5")
    mc = m.model_change
    assert isinstance(mc, ModelChange) and mc.after == ("linear-ttl", "drift") and mc.bands_before == (2.0, None)
    assert mc.delta_chi2 is None and mc.band_edges == (0.003, 0.01, 0.9)
    assert m.candidates is not None and all(isinstance(c, RankedCandidate) for c in m.candidates)
    assert [c.effect for c in m.candidates] == ["drift", "step"] and m.candidates[0].significant is True
    # null and absent keys kept apart, in their order: the header's bytes come back
    assert json.dumps(m.to_header()) == json.dumps(header)
    assert json.dumps(m.summary_fields()["model_change"]) == json.dumps(CHANGE)
    # built by the producer (stages/fitter/window_refit.py's dicts) as read by the reader
    assert FitMessage().with_fields({"model_change": CHANGE, "candidates": RANKING}).model_change == mc


@pytest.mark.parametrize(
    ("field", "value", "where"),
    [
        ("names", "a", "'names'"),
        ("converged", 1, "'converged'"),
        ("segments", 2.5, "'segments'"),
        ("t_stop", "late", "'t_stop'"),
        ("adequacy", {"chi2_dof": 1.0}, "'adequacy.fails'"),
        ("adequacy", {"chi2_dof": 1.0, "fails": False, "bands": [{"f_lo": 1}]}, r"'adequacy.bands\[0\]'"),
        ("rolling", {"coefficients": [1.0]}, "'rolling'"),
        ("candidates", [1], r"'candidates\[0\]'"),
        ("candidates", [{"spec": "step"}], r"'candidates\[0\]\.effect': missing"),
        ("candidates", [{"effect": "step", "significant": "yes"}], r"'candidates\[0\]\.significant'"),
        ("model_change", {"after": ["linear-ttl"]}, r"'model_change\.before': missing"),
        ("model_change", {**CHANGE, "bands_after": "high"}, r"'model_change\.bands_after'"),
        ("model_change", {**CHANGE, "verdict": 1}, r"'model_change': unknown fields \['verdict'\]"),
    ],
)
def test_a_field_of_the_wrong_type_is_an_error_naming_it(field, value, where):
    for header in (OLD, {**OLD, "schema": SCHEMA}):
        with pytest.raises(MessageError, match=f"fit 2: meta field {where}"):
            FitMessage.from_header({**header, field: value}, "fit 2")


def test_a_producer_sets_fields_checked_as_the_reader_checks_them():
    m = FitMessage().with_fields({k: v for k, v in OLD.items() if k in ("names", "model")})
    assert m.names == ("a", "b")
    with pytest.raises(MessageError, match="'bogus': unknown field"):
        m.with_fields({"bogus": 1})
    assert "model" in m.summary_fields() and "names" not in m.summary_fields()


# a live diagnosis as stages/fitter/live_diagnosis.py writes it (the fitter set the adoption)
DIAGNOSIS = {
    "index": 23,
    "segments": [0, 23],
    "model": ["linear-ttl"],
    "chi2_dof": 1.6,
    "fails": True,
    "bands": [
        {"f_lo": 0.003, "f_hi": 0.01, "chi2_dof": 2.5, "fails": True},
        {"f_lo": 0.01, "f_hi": 0.9, "chi2_dof": 1.01, "fails": False},
    ],
    "failing_hours": [[0.0, 3600.0]],
    "summary": ["0.003-0.01 Hz fails"],
    "witnesses": [{"name": "dws", "spec": "drift", "delta_chi2": 40.0, "best_band": [0.003, 0.01]}],
    "candidates": [],
    "transients": None,
    "text": "a drift",
    "recommendation": {
        "spec": "drift",
        "option": "--effects linear-ttl,drift",
        "explains": True,
        "message": "add drift",
        "log_bayes_factor": 12.0,
        "effects": ["linear-ttl", "drift"],
        "command": 'ttl control u fitter model \'{"effects": ["linear-ttl", "drift"]}\'',
    },
    "adoption": {"mode": "auto", "adopted": True, "reason": "drift explains the excess"},
    "removal": [],
}


def test_the_live_diagnosis_is_a_value_written_back_as_it_came():
    m = FitMessage.from_header({**OLD, "diagnosis": DIAGNOSIS, "schema": SCHEMA}, "fit 23")
    d = m.diagnosis
    assert isinstance(d, LiveDiagnosis) and d.segments == (0, 23) and d.fails is True
    assert d.failing_bands == [[0.003, 0.01, 2.5]] and d.text == "a drift"
    assert d.recommendation is not None and d.recommendation.advised == "drift"
    assert d.recommendation.effects == ("linear-ttl", "drift")
    assert m.adopted == Adoption("auto", True, "drift explains the excess")
    assert json.dumps(m.to_header()["diagnosis"]) == json.dumps(DIAGNOSIS)  # keys not read are kept too
    not_advised = {**DIAGNOSIS["recommendation"], "option": None, "command": None}
    assert LiveDiagnosis.from_json({**DIAGNOSIS, "recommendation": not_advised}, "fit 1").recommendation.advised is None
    refused = FitMessage.from_header({**OLD, "diagnosis": {**DIAGNOSIS, "adoption": {"adopted": False}}})
    assert refused.adopted is None


@pytest.mark.parametrize(
    ("value", "where"),
    [
        ({**DIAGNOSIS, "fails": "yes"}, r"'diagnosis\.fails'"),
        ({**DIAGNOSIS, "bands": [1.0]}, r"'diagnosis\.bands\[0\]'"),
        ({**DIAGNOSIS, "recommendation": "drift"}, r"'diagnosis\.recommendation'"),
        ({**DIAGNOSIS, "recommendation": {"effects": "drift"}}, r"'diagnosis\.recommendation\.effects'"),
        ({**DIAGNOSIS, "adoption": {"adopted": 1}}, r"'diagnosis\.adoption\.adopted'"),
    ],
)
def test_a_diagnosis_field_of_the_wrong_type_is_an_error_naming_it(value, where):
    with pytest.raises(MessageError, match=f"fit 23: meta field {where}: expected"):
        FitMessage.from_header({**OLD, "diagnosis": value, "schema": SCHEMA}, "fit 23")


def test_a_recorded_fit_summary_is_a_value():
    # as stages/fitter/message.py:fit_summary records it (the meta of OLD with the diagnosis)
    fit = {"names": ["a", "b"], "converged": True, "chi2_dof": 1.02, "window": {"t_start": 0.0, "t_stop": 86400.0}}
    d = {
        "run": "u",
        "index": 23,
        "names": ["a", "b"],
        "coefficients": [1.0, 2.0],
        "sigma": [0.1, 0.2],
        "covariance": [[0.01, 0.0], [0.0, 0.04]],
        "chi2": 1020.0,
        "dof": 1000,
        "chi2_dof": 1.02,
        "t_start": 0.0,
        "t_end": 86400.0,
        "segments": 23,
        "fit": fit,
        **{k: OLD[k] for k in SUMMARY_META if k in OLD},
        "diagnosis": DIAGNOSIS,
    }
    s = FitSummary.from_dict(json.loads(json.dumps(d)))
    assert (s.index, s.names, s.t_start, s.t_stop, s.converged) == (23, ("a", "b"), 0.0, 86400.0, True)
    assert s.coefficients == [1.0, 2.0] and s.covariance == [[0.01, 0.0], [0.0, 0.04]]
    assert s.meta.model == ("linear-ttl", "drift") and s.meta.diagnosis is not None
    assert s.meta.adopted is not None and s.to_dict() == d
    # a bare FitResult.to_json: coefficients and sigma by name, the window under fit
    bare = {"index": 4, "coefficients": {"b": 2.0, "a": 1.0}, "sigma": {"a": 0.1, "b": 0.2}, "fit": fit}
    s = FitSummary.from_dict(bare)
    assert s.coefficients == [1.0, 2.0] and s.sigma == [0.1, 0.2] and s.t_stop == 86400.0 and s.chi2_dof == 1.02
    assert s.meta.model is None
    with pytest.raises(MessageError, match=r"fit/summary: meta field 'index': expected int"):
        FitSummary.from_dict({"index": "4"})
    with pytest.raises(MessageError, match=r"fit/summary 4: meta field 't_start': expected number"):
        FitSummary.from_dict({**bare, "t_start": "early"})
    with pytest.raises(MessageError, match=r"fit/summary 4: meta field 'model': expected strs"):
        FitSummary.from_dict({**bare, "model": "drift"})

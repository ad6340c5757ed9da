"""The diagnosis as values (ttlcore.diagnose.diagnosis, issue 34 item 2): ``diagnose()`` and
``refit()`` return frozen values read by attribute, the fitted model among them; ``to_json()``
is the JSON report of docs/diagnostics.md, its keys pinned here, no live object in it."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from ttlcore.diagnose.diagnoser import diagnose, refit
from ttlcore.diagnose.diagnosis import Diagnosis, Refit
from ttlcore.diagnose.model_fit import ModelFit
from ttlcore.diagnose.whitened import WhitenedData
from ttlcore.sim.simulator import SimulationConfig, simulate

HOURS = 3 * 3600.0

#: the report's parts, in the order the report holds them (``candidates_gated`` only beside
#: a signal; ``file``, ``truth_file``, ``figures`` are added by ``ttl diagnose``)
REPORT_KEYS = [
    "model",
    "adequacy",
    "before",
    "change",
    "witnesses",
    "candidates",
    "transients",
    "recommendation",
    "settings",
    "timings_s",
]
MODEL_KEYS = ["effects", "n_parameters", "cli_effects", "searched", "chi2_dof", "adequacy", "coefficients"]
ADEQUACY_KEYS = [
    "noise_model",
    "tolerance",
    "alpha",
    "variance_factor",
    "band",
    "segment_duration",
    "segments",
    "chi2",
    "dof",
    "chi2_dof",
    "bands",
    "fine_bands",
    "time",
    "fails",
    "summary",
]
BAND_KEYS = ["f_lo", "f_hi", "chi2", "dof", "chi2_dof", "p_value", "fails", "channels"]
CHANGE_KEYS = [
    "added",
    "delta_chi2",
    "log_bayes_factor",
    "chi2_dof_before",
    "chi2_dof_after",
    "bands_before",
    "bands_after",
]
SETTINGS_KEYS = [
    "band",
    "n_bands",
    "segment_duration",
    "time_segment",
    "tolerance",
    "alpha",
    "log_bf_threshold",
    "dws_asd",
]
TRANSIENT_KEYS = {"events", "gaps", "quiet", "classification", "robustness", "actions", "not_advised", "gated_model"}
CANDIDATE_KEYS = {
    "effect",
    "spec",
    "cli_spec",
    "n_parameters",
    "delta_chi2",
    "p_value",
    "log_bayes_factor",
    "explained_fraction",
    "significant",
    "where",
}


@pytest.fixture(scope="module")
def diagnosed():
    """A 3-h simulated day diagnosed with a model beyond the linear TTL (``before`` and
    ``change`` in the report), the witness search on, one named candidate."""
    tm, truth = simulate(SimulationConfig(duration=HOURS, orbit="keplerian", seed=7), chunk_size=int(HOURS * 4))
    d = diagnose(
        tm,
        ["linear-ttl", "drift"],
        candidates=["cross-coupling"],
        truth_coefficients=truth["coefficients"].mean(axis=1),
    )
    return d


def _private_keys(x, path="") -> list[str]:
    """Every key starting with ``_`` anywhere in a JSON value, by path."""
    if isinstance(x, dict):
        return [f"{path}/{k}" for k in x if str(k).startswith("_")] + [
            p for k, v in x.items() for p in _private_keys(v, f"{path}/{k}")
        ]
    if isinstance(x, list):
        return [p for i, v in enumerate(x) for p in _private_keys(v, f"{path}/{i}")]
    return []


def test_the_report_keeps_its_schema(diagnosed):
    rep = diagnosed.to_json()
    assert [k for k in rep if k != "candidates_gated"] == REPORT_KEYS
    assert list(rep["model"]) == MODEL_KEYS and list(rep["before"]) == MODEL_KEYS
    assert list(rep["adequacy"]) == ADEQUACY_KEYS and rep["adequacy"] == rep["model"]["adequacy"]
    assert all(list(b) == BAND_KEYS for b in rep["adequacy"]["bands"])
    assert list(rep["change"]) == CHANGE_KEYS and rep["change"]["added"] == ["drift"]
    assert list(rep["settings"]) == SETTINGS_KEYS
    assert TRANSIENT_KEYS <= set(rep["transients"]) and "map" in rep["transients"]
    assert rep["candidates"] and all(CANDIDATE_KEYS <= set(c) for c in rep["candidates"])
    assert {"n_witnesses", "overall", "bands"} <= set(rep["witnesses"])
    # no live object, no in-memory key: the report is JSON as it stands
    assert _private_keys(rep) == []
    json.dumps(rep, allow_nan=True)


def test_the_diagnosis_is_read_by_attribute(diagnosed):
    d, rep = diagnosed, diagnosed.to_json()
    assert isinstance(d, Diagnosis)
    assert isinstance(d.fit, ModelFit) and isinstance(d.data, WhitenedData) and d.data is d.fit.data
    assert d.transient_map is not None
    assert d.model.effects == tuple(rep["model"]["effects"]) and d.model.n_parameters == rep["model"]["n_parameters"]
    assert d.model.n_parameters == len(d.fit.names)
    assert d.adequacy is d.model.adequacy and d.adequacy.fails == rep["adequacy"]["fails"]
    assert d.adequacy.chi2_dof == pytest.approx(d.fit.chi2_dof)
    assert [b.chi2_dof for b in d.adequacy.bands] == [b["chi2_dof"] for b in rep["adequacy"]["bands"]]
    assert len(d.adequacy.time) == len(rep["adequacy"]["time"]["segments"]) > 0
    assert d.adequacy.band_edges[0] == rep["adequacy"]["bands"][0]["f_lo"]
    assert d.before is not None and d.before.effects == ("linear-ttl",)
    assert d.change is not None and d.change.added == ("drift",)
    assert d.change.delta_chi2 == rep["change"]["delta_chi2"]
    assert [c.spec for c in d.candidates] == [c["spec"] for c in rep["candidates"]]
    assert d.witnesses is not None and [w.name for w in d.witnesses.overall] == [
        w["name"] for w in rep["witnesses"]["overall"]
    ]
    assert d.transients is not None and d.transients.excess_class == rep["transients"]["classification"]["class"]
    values = d.model.coefficients.values
    assert np.allclose([values[n] for n in d.fit.parameter_names], d.fit.theta)
    assert (d.recommendation is None) == (rep["recommendation"] is None)
    assert d.timings == rep["timings_s"] and [c.seconds for c in d.candidates] == [
        c["seconds"] for c in rep["candidates"]
    ]
    assert (
        d.adequacy.segments == rep["adequacy"]["segments"]
        and d.witnesses.n_witnesses == rep["witnesses"]["n_witnesses"]
    )
    assert d.text("3h").startswith("3h: model linear-ttl, drift")


def test_the_values_are_frozen_and_their_json_fresh(diagnosed):
    with pytest.raises(dataclasses.FrozenInstanceError):
        diagnosed.model = diagnosed.before  # type: ignore[misc]
    rep = diagnosed.to_json()
    rep["adequacy"]["bands"].clear()
    rep["file"] = "x.h5"
    again = diagnosed.to_json()
    assert again["adequacy"]["bands"] and "file" not in again  # a copy each time: the value is unchanged
    assert json.dumps(again, sort_keys=True) == json.dumps(diagnosed.to_json(), sort_keys=True)


def test_a_refit_is_read_by_attribute(diagnosed):
    r = refit(diagnosed.data, ["linear-ttl", "drift"])
    assert isinstance(r, Refit) and isinstance(r.fit, ModelFit) and isinstance(r.baseline_fit, ModelFit)
    rep = r.to_json()
    assert list(rep) == ["model", "baseline", "change"] and _private_keys(rep) == []
    assert list(rep["model"]) == MODEL_KEYS and list(rep["change"]) == CHANGE_KEYS[1:]
    assert r.model.effects == ("linear-ttl", "drift") and r.baseline.effects == ("linear-ttl",)
    assert r.change.added == () and r.change.bands_after == tuple(rep["change"]["bands_after"])
    assert r.baseline.n_parameters == len(r.baseline_fit.names) == 24
    json.dumps(rep)

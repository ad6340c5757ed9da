"""Unit tests of :mod:`stages.fitter.window_refit`: the window's telemetry refitted with the model
and the fit message's meta of it (a real simulated window and ``refit``; no bus in it)."""

import logging

import numpy as np
import pytest

from stages.fitter.window_refit import TOP_CANDIDATES, transient_gates, window_refit, window_refit_meta
from streamer.bus.fit_record import FitMessage
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.effects import make_effects
from ttlcore.io.telemetry import Telemetry
from ttlcore.sim.simulator import SimulationConfig, simulate

HOUR = 3600.0


@pytest.fixture(scope="module")
def window():
    tm, _ = simulate(SimulationConfig(duration=5 * HOUR, orbit="keplerian", seed=41), chunk_size=int(5 * HOUR * 4))
    return tm


def test_transient_gates_cover_the_outliers_inside_the_window(window):
    excluded = [
        {"t_start": -100.0, "t_stop": 600.0, "z": 9.0},  # clipped to the window's start
        {"t_start": 2 * HOUR, "t_stop": 3 * HOUR, "gate": "gate:start=2h,stop=3h"},  # the model's own gate
        {"t_start": 4 * HOUR, "t_stop": 4.5 * HOUR, "z": 12.0},
        {"t_start": 6 * HOUR, "t_stop": 7 * HOUR, "z": 12.0},  # after the window
    ]
    gates = transient_gates(window, excluded)
    assert len(gates) == 2 and all(g.startswith("gate:") for g in gates)
    assert [g.span for g in make_effects(gates)] == [(0.0, 600.0), (4 * HOUR, 4.5 * HOUR)]
    assert transient_gates(window, []) == []


def test_a_window_too_short_is_no_refit_yet(window, caplog):
    short = Telemetry(
        t0=window.t0,
        fs=window.fs,
        eta=window.eta[:, :64],
        dws_phi=window.dws_phi[:, :64],
        dws_eta=window.dws_eta[:, :64],
        ltt=window.ltt[:, :64],
    )
    log = logging.getLogger("test_window_refit")
    with caplog.at_level(logging.INFO, logger="test_window_refit"):
        assert window_refit(short, ["linear-ttl"], ["linear-ttl"], dws_asd=None, band=None, log=log) is None
    assert any(r.getMessage().startswith("no window refit yet") for r in caplog.records)


def test_the_refit_of_an_extended_model_and_its_meta(window):
    r = window_refit(window, ["linear-ttl", "drift"], ["linear-ttl"], dws_asd=None, band=None)
    assert r is not None
    change = {"before": ["linear-ttl"], "after": ["linear-ttl", "drift"]}
    meta = window_refit_meta(r, change=change, extended=True, window=(0, 5, 3600 * 4), ranked=True)
    arrays = meta.pop("arrays")
    assert arrays["coefficients"].shape == (24,) and arrays["covariance"].shape == (24, 24)
    np.testing.assert_allclose(arrays["sigma"], np.sqrt(np.diag(arrays["covariance"])), rtol=1e-6)
    assert set(meta["extra_parameters"]) and all(len(v) == 2 for v in meta["extra_parameters"].values())
    assert not set(meta["extra_parameters"]) & set(COEFFICIENT_NAMES)  # the drift's, not the 24
    assert meta["model_update"] == "window refit" and meta["window"] == {"first": 0, "last": 5}
    assert meta["model_change"]["before"] == ["linear-ttl"] and meta["model_change"]["after"][-1] == "drift"
    assert len(meta["candidates"]) <= TOP_CANDIDATES
    if "model_parts" in meta:
        assert arrays["model_parts"].shape[1:] == (3, 3600 * 4)
    # the fit message reads every field of it
    fit = FitMessage().with_fields(meta)
    assert fit.adequacy is not None and fit.adequacy.chi2_dof == meta["adequacy"]["chi2_dof"]
    # the 24 alone: adequacy only
    plain = window_refit(window, ["linear-ttl"], ["linear-ttl"], dws_asd=None, band=None)
    only = window_refit_meta(plain, change=None, extended=False, window=(0, 5, 3600 * 4), ranked=False)
    assert set(only) == {"adequacy"}
    assert (
        window_refit_meta(plain, change=None, extended=False, window=(0, 5, 1), ranked=True)["candidates"] is not None
    )
    # a change not ranked (the live diagnosis ranks them): both models, no candidates
    unranked = window_refit_meta(r, change=change, extended=True, window=(0, 5, 3600 * 4), ranked=False)
    assert "model_change" in unranked and "candidates" not in unranked


def test_the_refit_from_the_shared_whitened_window_is_the_refit_of_its_telemetry(window):
    """The fitter hands the window's whitened data to the refit and then to the live diagnosis
    (:meth:`stages.fitter.window.TelemetryWindow.whitened`): the refit from them is the refit
    built from the telemetry, to rounding (the same arithmetic on the same arrays)."""
    from streamer.tools.refit import refit_settings
    from ttlcore.diagnose.whitened import whiten_telemetry

    effects, gates = ["linear-ttl", "drift"], [{"t_start": 3 * HOUR, "t_stop": 3.5 * HOUR, "z": 9.0}]
    alone = window_refit(window, effects, ["linear-ttl"], dws_asd=None, band=None, transients=gates)
    data = whiten_telemetry(window, refit_settings(None, None))
    shared = window_refit(window, effects, ["linear-ttl"], dws_asd=None, band=None, transients=gates, whitened=data)
    assert alone is not None and shared is not None
    np.testing.assert_allclose(shared.fit.theta, alone.fit.theta, rtol=0, atol=1e-12 * np.abs(alone.fit.theta).max())
    np.testing.assert_allclose(shared.fit.robust_sigma, alone.fit.robust_sigma, rtol=1e-10)
    assert shared.model.adequacy.chi2_dof == pytest.approx(alone.model.adequacy.chi2_dof, rel=1e-12)
    assert shared.model.gates == alone.model.gates

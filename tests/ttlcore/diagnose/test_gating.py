"""An FFT segment with no data (a long gap) is left out of the analysis grid and the gated data.

A live window of 25 h over the blind week's 7-h gap: of its four 6-h FFT segments one lay
wholly in the gap.  The rule keeps a segment holding at least ``MIN_KEPT`` of its taper's
power; measured against the samples the data hold (none), 0 >= 0.6 x 0 kept it, its zeros
scaled by 1e150, and the window refit read chi2/dof 16080 (the glitches then advised at the
gap's end had another cause: the window began with hours of NaN, the last test here).  The
check here is the chi^2 of a gapped day against the instrument noise model (expectation 1
per degree of freedom); on the old code the whitening of this day stopped (a zero window power).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.diagnoser import refit
from ttlcore.diagnose.gating import MIN_KEPT, gated_data, missing_data
from ttlcore.diagnose.settings import DiagnoseSettings
from ttlcore.diagnose.whitened import whiten_telemetry
from ttlcore.sim.simulator import SimulationConfig, simulate

HOURS = 8.0


@pytest.fixture(scope="module")
def clean_day():
    return simulate(SimulationConfig(duration=HOURS * 3600.0, orbit="keplerian", seed=7))


@pytest.fixture(scope="module")
def gapped_day(clean_day):
    tm, truth = clean_day
    t = tm.t0 + np.arange(tm.size) / tm.fs
    hole = (t >= 2.5 * 3600) & (t < 6.0 * 3600)  # 3.5 h of missing data: more than one FFT segment
    nan = np.where(hole, np.nan, 1.0)
    gapped = replace(tm, eta=tm.eta * nan, dws_phi=tm.dws_phi * nan, dws_eta=tm.dws_eta * nan)
    return gapped, truth["coefficients"].mean(axis=1), (2.5 * 3600, 6.0 * 3600)


def test_a_segment_inside_a_gap_is_left_out(gapped_day):
    tm, _, (a, b) = gapped_day
    data = whiten_telemetry(tm, DiagnoseSettings(segment_duration=3600.0))
    gaps = missing_data(data)
    assert len(gaps) == 1 and gaps[0][0] <= a + 200 and gaps[0][1] >= b - 200, gaps
    gated = gated_data(data, [], gaps)
    L = data.grid.L / data.grid.fs
    for grid in (data.grid, gated.grid):  # every segment kept holds data for MIN_KEPT of its taper
        for t0 in grid.seg_t0:
            inside = max(0.0, min(t0 + L, b) - max(t0, a))
            assert inside < (1 - MIN_KEPT) * L, (t0, inside)
    # 8 h less the 3.5-h gap and its edges: at most 4 of the 1-h segments, none in the gap
    assert 2 <= len(gated.grid.starts) <= 4, gated.grid.seg_t0


def test_a_gapped_day_reads_one_per_degree_of_freedom(gapped_day):
    tm, C, _ = gapped_day
    fit = refit(tm, ["linear-ttl"], settings=DiagnoseSettings(segment_duration=3600.0)).fit
    # the linear model is the truth here: chi2/dof is 1 within the statistical 1 % of ~3 h of
    # kept data and the noise model's 2 % tolerance
    assert abs(fit.chi2_dof - 1.0) < 0.03, fit.chi2_dof
    z = np.abs(fit.ttl_coefficients() - C) / fit.ttl_sigma()
    assert z.max() < 4.0, z


def _ttl_block(fit, covariance):
    sel = [fit.parameter_names.index(n) for n in COEFFICIENT_NAMES]
    return fit.theta[sel], covariance[np.ix_(sel, sel)]


def test_a_gated_fit_differs_from_the_whole_days_by_its_sigmas(clean_day):
    """Issue 32: where a span is gated, the fit loses that span and no more.  The fit of a
    day with 25 min gated (and its 15-min ramps) against the fit of the whole day: the two
    estimates are nested (the gated one uses a subset of the data), so their difference has
    the covariance ``C_gated - C_whole`` and its chi^2 against it is chi^2 with as many
    degrees of freedom as that difference has modes (expectation ~24; the 1e-3 bound).  The
    gated segment's power was restored but not its resolution: its bins counted as
    independent kept the sigmas of the whole day (ratio 1.000) and this chi^2 read 1159 for
    11 modes on a 12-h day; with the segment's own variance factor, 16-37 for 24."""
    tm, _ = clean_day
    whole = refit(tm, ["linear-ttl"]).fit
    gated = refit(tm, ["linear-ttl", "gate:start=3h,stop=3.4h"]).fit
    for name in ("covariance", "robust_covariance"):
        tw, cw = _ttl_block(whole, getattr(whole, name))
        tg, cg = _ttl_block(gated, getattr(gated, name))
        ratio = np.sqrt(np.diag(cg) / np.diag(cw))
        # 40 min of ~8 h taken (the span and half its ramps' power): sigmas a few % larger
        assert 1.005 < np.median(ratio) < 1.1, (name, ratio)
        w, v = np.linalg.eigh(cg - cw)
        modes = w > 1e-6 * w.max()
        chi2 = float(np.sum((v[:, modes].T @ (tg - tw)) ** 2 / w[modes]))
        assert chi2 < stats.chi2.isf(1e-3, modes.sum()), (name, chi2, modes.sum())


def test_an_event_in_a_gaps_ramps_is_the_gap():
    from ttlcore.diagnose.excess import gap_of
    from ttlcore.effects.gate import GATE_TAPER

    gaps = [(422037.5, 447237.25)]  # the blind week's gap
    hop = 225.0
    # an event 460 s after the gap's end, inside its 900-s ramp
    assert gap_of(447700.0, 448600.0, gaps, hop) == gaps[0]
    assert gap_of(421000.0, 421500.0, gaps, hop) == gaps[0]  # before its start, in the ramp
    # beyond the ramp and a hop: an event of its own
    assert gap_of(447237.25 + GATE_TAPER + hop + 1.0, 460000.0, gaps, hop) is None
    assert gap_of(100.0, 200.0, [], hop) is None


def test_missing_data_at_the_ends_is_cut_off(gapped_day):
    """A live window that begins inside a gap: hours of NaN before the data.  The analysis is
    that of the data from their first valid sample (the blind week's window 120..143 read an
    'event' at the data's start, SNR 17000, that the data without the leading NaN do not have)."""
    from ttlcore.diagnose.whitened import without_missing_ends

    tm, _, (a, b) = gapped_day
    k = int(round((b - tm.t0) * tm.fs))  # from the end of the gap on: data only
    data = replace(
        tm,
        t0=tm.t0 + k / tm.fs,
        eta=tm.eta[:, k:],
        dws_phi=tm.dws_phi[:, k:],
        dws_eta=tm.dws_eta[:, k:],
        ltt=tm.ltt[:, k:],
    )
    n = 4 * 3600  # an hour of NaN before them, the light travel times held (TelemetryWindow.add_gap)
    blank = np.full((6, n), np.nan)
    led = replace(
        data,
        t0=data.t0 - n / tm.fs,
        eta=np.concatenate([blank, data.eta], axis=1),
        dws_phi=np.concatenate([blank, data.dws_phi], axis=1),
        dws_eta=np.concatenate([blank, data.dws_eta], axis=1),
        ltt=np.concatenate([np.repeat(data.ltt[:, :1], n, axis=1), data.ltt], axis=1),
    )
    cut = without_missing_ends(led)
    assert cut.t0 == data.t0 and cut.size == data.size
    settings = DiagnoseSettings(segment_duration=1800.0)
    one, two = (refit(x, ["linear-ttl"], settings=settings).fit for x in (data, led))
    np.testing.assert_allclose(two.ttl_coefficients(), one.ttl_coefficients(), rtol=0, atol=1e-12)
    assert two.chi2_dof == pytest.approx(one.chi2_dof, rel=1e-12)


def test_the_ungated_data_are_not_held_through_a_gapped_diagnosis(gapped_day, monkeypatch):
    """Once a gapped window is gated, the diagnosis lets its ungated whitened data go (a day's:
    220 MB, held through the candidates and the transient phase before); the transient refit
    whitens the telemetry again and gets the same fit as gating it from scratch."""
    import weakref

    import ttlcore.diagnose.diagnoser as diagnoser

    class Stop(Exception):
        pass

    tm, _, _ = gapped_day
    s = DiagnoseSettings(segment_duration=3600.0, workers=1)
    handed = [whiten_telemetry(tm, s)]
    alive = weakref.ref(handed[0])
    gaps = missing_data(handed[0])
    seen = {}

    held = whiten_telemetry(tm, s)  # the same data, held as the diagnosis held them before

    def finder(model, report, refit=None, onsets=None):
        seen["alive"] = alive() is not None
        seen["refit"] = refit([(7000.0, 7600.0)])
        seen["held"] = diagnoser.gated_model(model, list(model.effects), [(7000.0, 7600.0)], lambda: held, gaps=gaps)
        raise Stop

    monkeypatch.setattr(diagnoser, "transient_report", finder)
    with pytest.raises(Stop):
        diagnoser.diagnose(tm, ["linear-ttl"], settings=s, candidates=["drift"], witnesses=False, whitened=handed.pop())
    assert seen["alive"] is False
    assert np.array_equal(seen["refit"].theta, seen["held"].theta)
    assert seen["refit"].data.grid.gap_spans == tuple(gaps) and len(seen["refit"].data.grid.gates) == 1


def test_the_residual_from_the_stored_series_is_the_refits(clean_day):
    """:func:`ttlcore.diagnose.excess.model_residual` of a fitted model without series takes
    the series the column store holds with the model's own coefficients instead of refitting
    (a day's gated model: a second copy of its columns, 0.18 GB).  The refit's residual is
    the reference: the same data, columns and coefficients, so equal to rounding (1e-12 of
    the residual's scale: a sum of 24-plus products in another order)."""
    from ttlcore.diagnose.excess import model_residual, stored_residual
    from ttlcore.diagnose.fitting import fit_model, fit_resolved
    from ttlcore.effects.gate import Gate

    tm, _ = clean_day
    data = whiten_telemetry(tm, DiagnoseSettings(), ())
    gated = gated_data(data, [Gate(start=3 * 3600.0, stop=3.4 * 3600.0)])  # a gated model's data
    fit = fit_model(gated, ["linear-ttl", "witness:source=12.eta,link=23,delay=1"], keep_series=False)
    assert fit.columns.series is None
    reference = fit_resolved(fit.data, list(fit.effects), None, True)
    expected = fit.data.tdi.data_series - np.einsum("p,cpn->cn", reference.theta, reference.columns.series)
    got = stored_residual(fit)
    assert got is not None
    scale = np.nanmax(np.abs(expected))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(model_residual(fit), expected, rtol=0, atol=1e-12 * scale)

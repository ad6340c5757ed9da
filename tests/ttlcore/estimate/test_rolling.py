"""The rolling fitter equals the batch analysis on the same span; it tracks drifts and steps."""

import numpy as np
import pytest

from ttlcore.conventions import DAY
from ttlcore.estimate.fit import FitSettings, fit_tdi
from ttlcore.estimate.gls import NormalEquations
from ttlcore.estimate.rolling import RollingFit, StreamingDecimator, _own_fit_chi2_dof
from ttlcore.sim.simulator import SimulationConfig, simulate
from ttlcore.tdi.data import TDIStream, compute_tdi, lowpass_taps

HOUR = 3600.0


def test_streaming_decimator_equals_batch_filter():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((2, 10_000))
    x[:, :37] = np.nan
    h = lowpass_taps(4.0)
    dec = StreamingDecimator(h, 2)
    pieces = np.concatenate(
        [dec.push(x[:, a:b]) for a, b in ((0, 3001), (3001, 3002), (3002, 7777), (7777, 10_000))], axis=-1
    )
    from ttlcore.tdi.data import TDIData

    td = TDIData(
        t0=0.0,
        fs=4.0,
        channels=("A", "E", "T"),
        data=np.vstack([x, x[:1]]),
        regressors=np.zeros((3, 1, 10_000)),
        names=("c",),
    )
    batch = td.decimated(2).data[:2]
    np.testing.assert_allclose(pieces, batch, rtol=0, atol=1e-12, equal_nan=True)


@pytest.fixture(scope="module")
def streamed():
    """1.25 days (Keplerian arms, all noises) and their TDI streamed hour by hour: (telemetry,
    30 TDI segments).  Both tests below feed the same segments to their rolling fits (the
    simulation and the streaming TDI are most of their cost; they used to make one each)."""
    tm, _ = simulate(SimulationConfig(duration=1.25 * DAY, orbit="keplerian", seed=5))
    stream = TDIStream()
    return tm, [stream.push(tm.slice(k * 14400, (k + 1) * 14400)) for k in range(30)]


def test_a_segments_own_fit_never_reads_more_than_its_data():
    """The outlier statistic (chi^2/dof of one FFT segment at its own least-squares fit) is at
    most the chi^2 at zero coefficients, whatever the columns: two glitches on one test mass
    are, after their times, one constant velocity step, and normal equations whose null
    direction rounds slightly negative (weights from an inverse CSD) with a right-hand side
    a hair off their range made ``dd - b @ solve(N, b)`` read 1e5 here (1e16 on the live
    merger-and-glitches day, hour 22-23) for a segment whose data read 1.7."""
    rng = np.random.default_rng(3)
    n = 2000
    X = np.column_stack([rng.normal(size=(n, 4)), np.full((n, 2), 1e-3)])
    y = X[:, :4] @ rng.normal(size=4) + rng.normal(size=n)
    v = np.array([0, 0, 0, 0, 1.0, -1.0]) / np.sqrt(2)
    N = X.T @ X - 1e-18 * np.trace(X.T @ X) * np.outer(v, v)
    b = X.T @ y + 1e-6 * np.abs(X.T @ y).max() * v
    neq = NormalEquations(
        tuple("abcdef"),
        np.array([0.0, 1.0]),
        N[None] / 2,
        b[None] / 2,
        np.array([y @ y]) / 2,
        np.zeros((1, 6, 6)),
        np.array([n // 2]),
        1,
    )
    r, dof = _own_fit_chi2_dof(neq)
    resid = y - X[:, :5] @ np.linalg.lstsq(X[:, :5], y, rcond=None)[0]
    assert dof == n - 6 and r <= y @ y / dof
    assert r == pytest.approx(resid @ resid / dof, rel=1e-9)


def test_rolling_window_over_a_day_equals_batch_analysis(streamed):
    # Telemetry fed hour by hour through the streaming TDI and the rolling fitter; when the
    # window covers exactly the first simulated day, the result equals the batch fit of that
    # day with the same settings (1-h FFT segments) to 1e-9 relative.
    tm, segments = streamed
    settings = FitSettings(segment_duration=HOUR)
    batch, _ = fit_tdi(compute_tdi(tm.slice(0, 24 * 14400)), settings)
    rolling = RollingFit(settings, window_duration=DAY)
    results = [rolling.push(td) for td in segments[:24]]
    assert all(r is not None for r in results)
    last = results[-1]
    assert last.n_segments == batch.n_segments == 24
    # Streamed and batch TDI cut the TDI engine's blocks at different places (polynomial-in-time
    # delay weights, 2e-10 of the largest sample apart: tests/ttlcore/tdi), which moves the
    # coefficients by ~1e-5 sigma: equal to 1e-4 sigma, the covariance and chi2 to 1e-6
    dc = np.abs(last.coefficients - batch.coefficients) / batch.sigma
    print(
        f"streamed - batch: {dc.max():.2e} sigma, covariance "
        f"{np.max(np.abs(last.covariance - batch.covariance)) / np.max(np.abs(batch.covariance)):.2e}, "
        f"chi2 {abs(last.chi2 - batch.chi2) / batch.chi2:.2e}"
    )
    assert dc.max() < 1e-4
    assert np.max(np.abs(last.covariance - batch.covariance)) < 1e-6 * np.max(np.abs(batch.covariance))
    assert abs(last.chi2 - batch.chi2) < 1e-6 * batch.chi2


def test_incremental_updates_track_the_full_refits(streamed):
    # Between the full refits (every 6 h of data), the rolling fit adds the new segment's
    # normal equations with the weights of the last full refit and drops the oldest: the
    # bookkeeping must equal a from-scratch sum with those weights (to rounding), and the
    # estimates must stay close to a full refit of the same window (weights lag by < 6 h and
    # both sets of weights are noisy estimates: within a sigma while the window fills, half a
    # sigma once it holds 12 segments; sigmas within 5 %; measured up to 0.8 sigma while it
    # fills, 0.1-0.3 sigma after, sigmas 0.1-2.5 %).
    from ttlcore.estimate.fit import accumulate

    _, segments = streamed
    settings = FitSettings(segment_duration=HOUR)
    inc, full = RollingFit(settings, window_duration=DAY), RollingFit(settings, window_duration=DAY, full_every=None)
    kinds = []
    for td in segments:  # one TDI segment feeds both fits
        r_inc, r_full = inc.push(td), full.push(td)
        kinds.append(r_inc.extra["update"])
        if kinds[-1] == "incremental":
            limit = 0.5 if r_full.n_segments >= 12 else 1.0
            assert np.max(np.abs(r_inc.coefficients - r_full.coefficients) / r_full.sigma) < limit
            assert np.allclose(r_inc.sigma, r_full.sigma, rtol=0.05)
        else:
            np.testing.assert_array_equal(r_inc.coefficients, r_full.coefficients)
    # full refits while the window fills (6 segments) and at every 6 h of data; incremental between
    assert kinds == ["full"] * 6 + (["incremental"] * 5 + ["full"]) * 4
    # after 4 updates past the last full refit (window sliding since segment 24)
    w = inc._weights
    masked = [inc._masked(sp) for sp in inc._spectra]
    direct = accumulate(masked, w["weights"], w["band_edges"], inc.names, w["eiv_response"], w["dws_psd"])
    summed = inc._sums[0][0]
    for neq, _ in list(inc._sums)[1:]:
        summed = summed + neq
    assert len(inc._sums) == inc.n_segments == 24
    np.testing.assert_allclose(summed.N, direct.N, rtol=1e-10, atol=1e-12 * np.abs(direct.N).max())
    np.testing.assert_allclose(summed.b, direct.b, rtol=1e-10, atol=1e-12 * np.abs(direct.b).max())


def test_a_loud_transient_is_left_out_and_does_not_pull_the_fit(streamed):
    # A burst (a sine-Gaussian at 8 mHz, 10 min long, in X2 of the data only: no DWS witness
    # sees it) in hour 9 of 12: the rolling fit leaves that FFT segment out - its
    # residual at its own best fit is far above the window's - and ends where the same fit
    # ends without the burst and without that hour (the same spectra; the light travel
    # times of the blanked hour stay in the clean fit's mean, hence not to rounding), while
    # a fit that keeps every segment is pulled by the burst.  The clean hours are never left
    # out (their statistic within 10 sigma of the median).  Measured: the naive fit moves by
    # 1.47 sigma, the robust one by 0.06 sigma; the burst's hour is 300 sigma out.
    _, segments = streamed
    settings = FitSettings(segment_duration=HOUR)
    burst_at = 9
    td = segments[burst_at]
    t = np.arange(td.size) / td.fs
    burst = np.sin(2 * np.pi * 8e-3 * t) * np.exp(-0.5 * ((t - 1800) / 300) ** 2)
    loud = td.data.copy()
    loud[0] += 3 * np.nanstd(td.data[0]) * burst
    from dataclasses import replace

    dirty = segments[:burst_at] + [replace(td, data=loud)] + segments[burst_at + 1 : 12]
    robust, naive = RollingFit(settings, window_duration=DAY), RollingFit(settings, window_duration=DAY, outlier_z=None)
    r_robust = [robust.push(x) for x in dirty][-1]
    r_naive = [naive.push(x) for x in dirty][-1]
    assert [round(e["t_start"] / HOUR) for e in robust.excluded] == [burst_at], robust.excluded
    assert robust.excluded[0]["z"] > 100
    assert r_robust.n_segments == 11 and r_naive.n_segments == 12

    # the same fit without the burst's hour: the clean segments, that hour blanked (NaN: an
    # FFT segment less than half valid is skipped, its light travel times dropped alike)
    blank = replace(td, data=np.full_like(td.data, np.nan), regressors=np.full_like(td.regressors, np.nan))
    clean = RollingFit(settings, window_duration=DAY, outlier_z=None)
    r_clean = [clean.push(x) for x in segments[:burst_at] + [blank] + segments[burst_at + 1 : 12]][-1]
    assert r_clean.n_segments == 11
    pulled = np.max(np.abs(r_naive.coefficients - r_clean.coefficients) / r_clean.sigma)
    kept = np.max(np.abs(r_robust.coefficients - r_clean.coefficients) / r_clean.sigma)
    print(f"burst: the naive fit moves by {pulled:.2f} sigma, the robust one by {kept:.2e}")
    assert pulled > 1.0 and kept < 0.1


def test_gates_leave_their_hours_out(streamed):
    # A model's gate (the diagnosis' advice for a merger or a gap) leaves the FFT segments it
    # overlaps out of the rolling fit, those already in the window (the next fit a full
    # refit) and those to come: the same fit as one whose overlapping hours were never there.
    _, segments = streamed
    settings = FitSettings(segment_duration=HOUR)
    gated = RollingFit(settings, window_duration=DAY)
    for td in segments[:8]:
        gated.push(td)
    gated.set_gates([(5.2 * HOUR, 8.5 * HOUR)])  # hours 5, 6, 7 (in the window) and 8 (to come)
    r_gated = [gated.push(td) for td in segments[8:12]][-1]
    assert [round(e["t_start"] / HOUR) for e in gated.excluded] == [5, 6, 7, 8]
    assert r_gated.n_segments == 8 and r_gated.extra["update"] == "full"
    from dataclasses import replace

    blank = [
        replace(td, data=np.full_like(td.data, np.nan), regressors=np.full_like(td.regressors, np.nan))
        for td in segments[5:9]
    ]
    never = RollingFit(settings, window_duration=DAY)
    r_never = [never.push(td) for td in segments[:5] + blank + segments[9:12]][-1]
    assert r_never.n_segments == 8
    # the same spectra and weights from a full refit; only the window's mean light travel
    # times differ (the blanked hours' stay in the other's mean): a small fraction of sigma
    assert np.max(np.abs(r_gated.coefficients - r_never.coefficients) / r_never.sigma) < 0.1


def test_the_short_last_segment_gets_its_fit(streamed):
    # The last telemetry segment of a file is often short (a lisainstrument day loses its
    # first 49 samples to the eta reduction, so its last hour holds 14351 samples): its
    # samples never complete an FFT segment, and before flush() no fit covered it. Flushed,
    # the FFT segment is closed with a gap at its end; the result equals the batch fit of the
    # same data padded with NaN to whole hours (the batch cuts the same segments and masks
    # the same gap), to the streaming/batch agreement of the day-long test above (1e-4 sigma).
    from dataclasses import replace

    tm, segments = streamed
    settings = FitSettings(segment_duration=HOUR)
    n = 14400 - 49
    rolling = RollingFit(settings, window_duration=DAY, full_every=None)
    for td in segments[:6]:
        assert rolling.push(td) is not None
    assert rolling.push(segments[6].slice(slice(0, n))) is None  # the FFT segment is not complete
    flushed = rolling.flush()
    assert flushed is not None and flushed.n_segments == 7
    assert rolling.flush() is None  # nothing pending any more

    td = compute_tdi(tm.slice(0, 6 * 14400 + n))
    pad = np.full(td.data.shape[:-1] + (14400 - n,), np.nan)
    padded = replace(
        td,
        data=np.concatenate([td.data, pad], axis=-1),
        regressors=np.concatenate([td.regressors, np.full(td.regressors.shape[:-1] + (14400 - n,), np.nan)], axis=-1),
    )
    batch, _ = fit_tdi(padded, settings)
    assert batch.n_segments == 7
    assert np.max(np.abs(flushed.coefficients - batch.coefficients) / batch.sigma) < 1e-4


def test_a_segment_mostly_gap_leaves_the_window_fit_standing(streamed):
    # An FFT segment less than half valid (a gap in the data) is skipped; the fit of that
    # segment is the window's fit before it, flagged (extra["excluded"]["gap"]) so that the
    # stage says so, and it is not counted as an outlier.
    from dataclasses import replace

    _, segments = streamed
    rolling = RollingFit(FitSettings(segment_duration=HOUR), window_duration=DAY)
    before = [rolling.push(td) for td in segments[:7]][-1]
    holed = segments[7].data.copy()
    holed[:, : 14400 * 2 // 3] = np.nan
    r = rolling.push(replace(segments[7], data=holed))
    assert r is not None and r.extra["excluded"]["gap"] is True
    assert np.array_equal(r.coefficients, before.coefficients) and r.n_segments == before.n_segments
    assert rolling.excluded == []


def test_incremental_updates_take_no_cholesky_factor_of_their_own(streamed, monkeypatch):
    # the weights of the last full refit are factored once (with it); an incremental update
    # sums its segment, scores it and tests it for an outlier with that factor - and gives
    # the same numbers as sums taken from scratch with those weights
    import ttlcore.estimate.fit as fit
    import ttlcore.estimate.whitening as whitening

    _, tds = streamed
    rf = RollingFit(FitSettings(segment_duration=HOUR))
    for td in tds[:8]:
        rf.push(td)
    calls = []
    cholesky = whitening.cholesky_factor
    monkeypatch.setattr(whitening, "cholesky_factor", lambda w: calls.append(1) or cholesky(w))
    res = rf.push(tds[8])
    assert res.extra["update"] == "incremental"
    assert calls == []
    w = rf._weights
    sp = rf._masked(rf._spectra[-1])
    neq, M = rf._sums[-1]
    again = fit.accumulate([sp], w["weights"], w["band_edges"], rf.names, w["eiv_response"], w["dws_psd"])
    np.testing.assert_array_equal(neq.N, again.N)
    np.testing.assert_array_equal(neq.E, again.E)


def test_dropping_a_models_columns_keeps_the_window(streamed):
    # A model's columns leaving it (a transient out of the window, an effect removed):
    # dropped from the rolling fit, whose window is kept and refitted in full - the fit of
    # a window that never had them, to rounding (the data's and the other regressors'
    # spectra do not depend on them); then it rolls on as that one does.
    from dataclasses import replace

    from ttlcore.conventions import COEFFICIENT_NAMES
    from ttlcore.estimate.fit import with_extra_regressors

    _, segments = streamed
    settings = FitSettings(segment_duration=HOUR)
    rng = np.random.default_rng(7)
    extra_names = ("g.a", "g.b")

    def with_columns(td):
        scale = np.nanstd(td.regressors[:, :2], axis=-1, keepdims=True)  # (3, 2, 1): their size
        cols = scale * rng.standard_normal((3, 2, td.size))
        return with_extra_regressors(td, replace(td, regressors=cols, names=extra_names))

    wide = RollingFit(settings, window_duration=DAY, names=COEFFICIENT_NAMES + extra_names, outlier_z=None)
    never = RollingFit(settings, window_duration=DAY, outlier_z=None)
    always_full = RollingFit(settings, window_duration=DAY, outlier_z=None, full_every=None)
    for td in segments[:10]:
        wide.push(with_columns(td))
        never.push(td)
        always_full.push(td)
    dropped = wide.drop(list(extra_names))
    assert wide.names == COEFFICIENT_NAMES and dropped.extra["update"] == "full" and dropped.n_segments == 10
    ref = always_full.last
    np.testing.assert_allclose(dropped.coefficients, ref.coefficients, rtol=0, atol=1e-9 * np.max(ref.sigma))
    np.testing.assert_allclose(dropped.sigma, ref.sigma, rtol=1e-9)
    assert wide.drop(list(extra_names)) is dropped  # nothing left to drop: the fit stands
    kinds = []
    for td in segments[10:16]:  # pushed on without the columns, as the fit that never had them
        a, b = wide.push(td), never.push(td)
        kinds.append((a.extra["update"], b.extra["update"]))
        assert a.names == b.names and a.n_segments == b.n_segments
        if kinds[-1] == ("full", "full"):  # the same window, both refitted in full
            np.testing.assert_allclose(a.coefficients, b.coefficients, rtol=0, atol=1e-9 * np.max(b.sigma))
        else:  # weights of different full refits (test_incremental_updates_track_the_full_refits)
            assert np.max(np.abs(a.coefficients - b.coefficients) / b.sigma) < (0.5 if b.n_segments >= 12 else 1.0)
    # the incremental updates from the drop's weights, and the full refit at 12 h of data
    assert kinds == [("incremental", "incremental"), ("full", "full")] + [("incremental", "incremental")] * 4

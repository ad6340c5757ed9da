"""Unit tests of :mod:`stages.fitter.window`: the fitter's window of telemetry (no bus in it)."""

from dataclasses import replace

import numpy as np
import pytest

from stages.fitter.window import TelemetryWindow
from ttlcore.io.telemetry import Telemetry

FS = 2.0
N = 100  # samples of a segment: 50 s


def segment(index: int) -> Telemetry:
    values = np.full((6, N), float(index))
    return Telemetry(
        t0=index * N / FS,
        fs=FS,
        eta=values,
        dws_phi=values + 0.5,
        dws_eta=values - 0.5,
        ltt=np.full((6, N), 8.3 + index),
        source="test",
    )


def test_segments_older_than_the_window_go():
    window = TelemetryWindow(duration=120.0)  # two segments and a bit
    for i in range(5):
        window.add(i, segment(i))
    # the newest ends at 250 s: a segment starting before 250 - 120 - 1 = 129 s goes
    assert [i for i, _ in window] == [3, 4]
    assert (window.first, window.last, len(window)) == (3, 4, 2)
    assert window.t_start == 150.0
    assert [tm.t0 for tm in window.telemetry] == [150.0, 200.0]
    window.clear()
    assert len(window) == 0


def test_a_gap_is_nan_readouts_with_the_light_travel_times_bridged():
    window = TelemetryWindow(duration=1000.0)
    window.add_gap(0, 0.0, FS, N)  # nothing before it: nothing to hold
    assert len(window) == 0
    window.add(0, segment(0))
    window.add_gap(1, N / FS, FS, N)
    window.add(2, segment(2))
    assert [i for i, _ in window] == [0, 1, 2]
    joined = window.joined(source="window")
    assert joined.eta.shape == (6, 3 * N) and joined.t0 == 0.0 and joined.source == "window"
    gap = slice(N, 2 * N)
    assert np.isnan(joined.eta[:, gap]).all() and np.isnan(joined.dws_phi[:, gap]).all()
    # the delays go straight from the last of segment 0 (8.3 s at sample N - 1) to the first
    # of segment 2 (10.3 s at sample 2N)
    expected = 8.3 + 2.0 * (np.arange(N, 2 * N) - (N - 1)) / (N + 1)
    np.testing.assert_allclose(joined.ltt[:, gap], np.broadcast_to(expected, (6, N)), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(joined.ltt[:, :N], 8.3)
    np.testing.assert_array_equal(joined.ltt[:, 2 * N :], 10.3)
    np.testing.assert_array_equal(joined.eta[:, 2 * N :], 2.0)
    assert not np.isnan(joined.eta[:, :N]).any()
    # a gap at the end: the last segment's trend extended (flat here: held)
    window.add_gap(3, 3 * N / FS, FS, N)
    np.testing.assert_allclose(window.joined("window").ltt[:, 3 * N :], 10.3, rtol=0, atol=1e-12)


def test_an_empty_window_does_not_join():
    with pytest.raises(ValueError, match="no telemetry"):
        TelemetryWindow(10.0).joined("window")


def test_a_second_of_slack_at_the_window_edge():
    # newest ends at 250 s: with a window of 149.5 s a segment that starts at 100 s, 0.5 s
    # too early, stays (1 s of slack: rounding of t0 across segments does not drop one)
    window = TelemetryWindow(duration=149.5)
    for i in range(5):
        window.add(i, segment(i))
    assert [i for i, _ in window] == [2, 3, 4]
    window = TelemetryWindow(duration=148.5)  # 1.5 s too early: it goes
    for i in range(5):
        window.add(i, segment(i))
    assert [i for i, _ in window] == [3, 4]


def test_the_whitened_window_is_built_once_while_the_window_stands(monkeypatch):
    built = []

    def whiten(tm, settings, modules):  # stands in for whiten_telemetry: counts the builds
        built.append((tm.t0, tm.size, settings, modules))
        return object()

    monkeypatch.setattr("stages.fitter.window.whiten_telemetry", whiten)
    window = TelemetryWindow(duration=1000.0)
    window.add(0, segment(0))
    window.add(1, segment(1))
    tm, first = window.whitened("w", "settings-a")
    assert (tm.t0, tm.size) == (0.0, 2 * N) and len(built) == 1
    assert window.whitened("w", "settings-a")[1] is first and len(built) == 1  # the same window
    assert window.whitened("w", "settings-b")[1] is not first and len(built) == 2  # other settings
    # a new segment, a gap or a cleared window: built again
    window.add(2, segment(2))
    assert window.whitened("w", "settings-b")[0].size == 3 * N and len(built) == 3
    window.add_gap(3, 3 * N / FS, FS, N)
    assert window.whitened("w", "settings-b")[0].size == 4 * N and len(built) == 4
    # keep=False: handed over, not kept; release() lets the kept one go
    window.whitened("w", "settings-b", keep=False)
    window.whitened("w", "settings-b")
    assert len(built) == 5
    window.release()
    window.whitened("w", "settings-b")
    assert len(built) == 6
    window.clear()
    window.add(7, segment(7))
    assert window.whitened("w", "settings-b")[0].t0 == 7 * N / FS and len(built) == 7


def test_segments_are_held_once_with_the_joined_window(monkeypatch):
    # after a join the segments are views of the joined series (the window's telemetry held
    # once through a diagnosis, not twice); their values and a later join are unchanged
    monkeypatch.setattr("stages.fitter.window.whiten_telemetry", lambda tm, settings, modules: object())
    window = TelemetryWindow(duration=1000.0)
    segments = [segment(i) for i in range(3)]
    for i, seg in enumerate(segments):
        window.add(i, seg)
    tm, _ = window.whitened("w", "s")
    for (_, held), seg in zip(window, segments):
        for name in ("eta", "dws_phi", "dws_eta", "ltt"):
            assert np.shares_memory(getattr(held, name), getattr(tm, name))
            np.testing.assert_array_equal(getattr(held, name), getattr(seg, name))
    window.add(3, segment(3))
    again, _ = window.whitened("w", "s")
    np.testing.assert_array_equal(again.eta[:, : 3 * N], tm.eta)
    assert not np.shares_memory(again.eta, tm.eta)


def test_the_tdi_after_a_gap_is_that_of_the_contiguous_data():
    # A Keplerian day's hours 0-3 as the fitter's window gets them, hour 2 stepped over (a
    # gap): the TDI of the joined window after the gap against the TDI of the telemetry that
    # had no gap (compute_tdi of the simulator's contiguous series: an independent join).
    # The light travel times held over the gap stepped by 1.2e-5 s at its end (the delays
    # change by ~3e-9 s/s); the engine's delays, smooth over ~2.2-h blocks, went wrong in the
    # valid samples around the gap: 2e-4 of the TDI's rms before it, 2e-3 after.  Bridged,
    # the delays in the gap miss the orbit's by nanoseconds and the TDI agrees to 1e-6
    # (measured 2e-7 to 5e-7).
    from ttlcore.sim.simulator import SimulationConfig, simulate
    from ttlcore.tdi.data import compute_tdi

    tm, _ = simulate(SimulationConfig(duration=4 * 3600, orbit="keplerian", seed=3))
    n = int(3600 * tm.fs)

    def hour(i: int) -> Telemetry:
        sl = slice(i * n, (i + 1) * n)
        return replace(
            tm,
            t0=tm.t0 + i * n / tm.fs,
            eta=tm.eta[:, sl],
            dws_phi=tm.dws_phi[:, sl],
            dws_eta=tm.dws_eta[:, sl],
            ltt=tm.ltt[:, sl],
        )

    window = TelemetryWindow(duration=86400.0)
    for i in range(4):
        if i == 2:
            window.add_gap(i, tm.t0 + i * n / tm.fs, tm.fs, n)
        else:
            window.add(i, hour(i))
    joined = window.joined("window")
    assert np.abs(joined.ltt - tm.ltt).max() < 1e-8  # [s]
    ref, got = compute_tdi(tm).data, compute_tdi(joined).data
    scale = np.nanstd(ref[:, n : 2 * n])
    for span in (slice(1000, 2 * n - 400), slice(3 * n + 400, 4 * n - 100)):  # clear of the TDI's reach
        assert np.isfinite(got[:, span]).all()
        assert np.abs(got[:, span] - ref[:, span]).max() < 1e-6 * scale

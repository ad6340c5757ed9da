"""Light travel times across a gap (:func:`ttlcore.io.telemetry.bridged_ltt`) and NaN light
travel times in our telemetry files, against lisaorbits' Keplerian orbit (an independent
orbit model): the delays the pipeline gives a span without readouts, and those it reads
where a file has none, miss the orbit's by nanoseconds."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from ttlcore.errors import TelemetryError
from ttlcore.io.telemetry import Telemetry, bridged_ltt, read_ttl_telemetry, write_telemetry

FS = 4.0


@pytest.fixture(scope="module")
def orbit_ltt() -> np.ndarray:
    """lisaorbits' Keplerian light travel times (6, n) [s], 7 h at 4 Hz from day 10."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import lisaorbits

        t = 10 * 86400 + np.arange(0, 7 * 3600, 1 / FS)
        return np.ascontiguousarray(lisaorbits.KeplerianOrbits().compute_ltt(t).T)


def test_a_gap_is_bridged_within_nanoseconds_of_the_orbit(orbit_ltt):
    # 2 h missing in the middle, 20 min at either end: the straight line between the valid
    # samples, and the valid stretches' trends beyond them, against the orbit.  The arms'
    # delays curve at ~1.3e-15 s/s^2 here: a chord of T = 2 h misses by ~a T^2 / 8 = 8 ns
    # (measured 7.6 ns); the trend of the last hour, extended 20 min, by 3.4 ns
    n = orbit_ltt.shape[1]
    missing = np.zeros(n, dtype=bool)
    hole, head, tail = slice(3 * 14400, 5 * 14400), slice(0, 4800), slice(n - 4800, n)
    for span in (hole, head, tail):
        missing[span] = True
    got = bridged_ltt(np.where(missing, np.nan, orbit_ltt), missing)
    err = np.abs(got - orbit_ltt)
    assert np.isfinite(got).all()
    assert err[:, hole].max() < 1e-8  # [s]
    assert max(err[:, head].max(), err[:, tail].max()) < 5e-9  # [s]
    np.testing.assert_array_equal(got[:, ~missing], orbit_ltt[:, ~missing])  # the valid ones untouched
    # held, as the fitter's window held them, the hole's last sample missed by 24 us
    held_step = np.abs(orbit_ltt[:, hole.stop] - orbit_ltt[:, hole.start - 1]).max()
    assert held_step > 1e-5
    with pytest.raises(ValueError, match="every sample is missing"):
        bridged_ltt(orbit_ltt, np.ones(n, dtype=bool))


def test_nan_light_travel_times_in_our_file_are_bridged_and_a_link_without_any_refused(orbit_ltt, tmp_path):
    n = 4 * 14400
    ltt = orbit_ltt[:, :n].copy()
    ltt[1, 20000:27200] = np.nan  # 30 min of link 23's delays missing
    zeros = np.zeros((6, n))
    path = write_telemetry(
        tmp_path / "day.h5", Telemetry(t0=0.0, fs=FS, eta=zeros, dws_phi=zeros, dws_eta=zeros, ltt=ltt)
    )
    tm = read_ttl_telemetry(path)
    assert np.isfinite(tm.ltt).all()
    assert np.abs(tm.ltt - orbit_ltt[:, :n]).max() < 1e-9  # [s]
    np.testing.assert_array_equal(np.delete(tm.ltt, 1, axis=0), np.delete(orbit_ltt[:, :n], 1, axis=0))
    assert not tm.missing().any()  # the readouts are all there: no gap
    ltt[4] = np.nan
    bad = write_telemetry(
        tmp_path / "bad.h5", Telemetry(t0=0.0, fs=FS, eta=zeros, dws_phi=zeros, dws_eta=zeros, ltt=ltt)
    )
    with pytest.raises(TelemetryError, match=r"bad.h5 \[ltt\].*link 32"):
        read_ttl_telemetry(bad)

"""A NaN gap costs the fit what its data held, no more (issue 20): the spectra of a segment
with a gap inside are tapered into the gap (``GAP_TAPER``) and weigh by their effective
samples (:func:`ttlcore.estimate.fit.effective_samples`); data without a gap inside a
segment is analysed exactly as before."""

from __future__ import annotations

import numpy as np
import pytest

from ttlcore.estimate.fit import (
    GAP_TAPER,
    FitSettings,
    effective_samples,
    fit_tdi,
    gap_taper,
    spectra_of_segment,
    window,
)
from ttlcore.estimate.spectra import segment_fft
from ttlcore.sim.simulator import SimulationConfig, simulate
from ttlcore.tdi.data import compute_tdi

FS = 2.0
N = 7200  # one hour at 2 Hz
BAND = (3e-3, 0.9)


def series(seed=0, p=24):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((3, N)), rng.standard_normal((3, p, N))


def previous_spectra(data, regs, ok, window_name):
    """What spectra_of_segment computed before the effective-samples weight."""
    w = window(window_name, N) * (gap_taper(ok, int(round(GAP_TAPER * FS))) if not ok.all() else 1.0)
    f, D = segment_fft(np.where(ok, data, 0.0), FS, w)
    _, RR = segment_fft(np.where(ok, regs, 0.0), FS, w)
    sel = (f >= BAND[0]) & (f <= BAND[1])
    return D[:, sel].T, np.moveaxis(RR[:, :, sel], 2, 0)


@pytest.mark.parametrize("window_name", ["rect", "tukey:0.1"])
def test_segments_without_a_gap_inside_are_unchanged(window_name):
    """Whole segments, and segments whose invalid samples are at their ends (the TDI delays
    at the start of the data, the decimation filter), get the spectra they always got: bit
    for bit, so ``ttl analyze`` and the rolling fit are unchanged on data without gaps."""
    data, regs = series()
    for lead, trail in ((0, 0), (150, 0), (0, 40), (150, 40)):
        d, r = data.copy(), regs.copy()
        d[:, :lead] = np.nan
        r[:, 3, N - trail :] = np.nan
        ok = np.isfinite(d).all(axis=0) & np.isfinite(r).all(axis=(0, 1))
        sp = spectra_of_segment(d, r, 0.0, FS, BAND, window_name)
        want_d, want_r = previous_spectra(d, r, ok, window_name)
        np.testing.assert_array_equal(sp.d, want_d)
        np.testing.assert_array_equal(sp.R, want_r)


def test_a_gap_inside_weighs_by_the_effective_samples_left():
    """White regressors with 20 minutes cut out of the hour: the segment's normal matrix
    (sum over the band of R^H R) falls by the effective samples left, n_eff / n_eff0, and
    not by nothing (as it did: the PSD normalisation restored the full level)."""
    data, regs = series(1)
    full = spectra_of_segment(data, regs, 0.0, FS, BAND, "rect")
    d = data.copy()
    d[:, 3000:5400] = np.nan
    ok = np.isfinite(d).all(axis=0)
    gapped = spectra_of_segment(d, regs, 0.0, FS, BAND, "rect")
    w = gap_taper(ok, int(round(GAP_TAPER * FS)))
    expected = effective_samples(w) / N
    assert 0.4 < expected < 2 / 3  # the 20 min and two ramps of GAP_TAPER at half weight
    ratio = np.sum(np.abs(gapped.R) ** 2) / np.sum(np.abs(full.R) ** 2)
    # white noise: the band's power is the series' power whatever the window; 24 x 3 series
    # of ~6000 bins each: the ratio is known to ~1 %
    assert ratio == pytest.approx(expected, rel=0.03), (ratio, expected)
    assert gapped.valid_fraction == pytest.approx(ok.mean())


def test_a_gapped_fit_moves_by_what_the_lost_data_explains():
    """Six hours (1-h FFT segments), once whole and once with ten minutes of NaN in one eta
    at 2 h 25 min: ``ttl analyze``'s fit (:func:`fit_tdi`).

    * Every coefficient's variance grows, by at least the gap's share of the data (600 s of
      6 h: 2.8 %) and at most three times that (the gap, the TDI delays either side, the two
      tapers of ``GAP_TAPER`` at half weight: 7.6 %).  Before, the gapped segment weighed as
      a whole one: variance ratios 0.98-1.00.
    * For nested data the difference of the two estimates has the variance of what was lost,
      ``sigma_gap^2 - sigma_clean^2``: the differences over it are ~N(0, 1) when the gapped
      fit is as good as its data allows and says what it lost.  Their RMS over the 24
      coefficients must stay below 2.5: measured 2.1, 2.1, 1.5 (seeds 1, 2, 3; leakage of
      the red noise through the taper edges adds scatter the effective samples do not count;
      a 300-s taper gave 2.5-14, a 1800-s one 1.4-1.9), and 5.7-14 before.
    """
    cfg = SimulationConfig(duration=6 * 3600.0, orbit="unequal", seed=1)
    tm, _ = simulate(cfg)
    settings = FitSettings(segment_duration=3600.0)
    clean, _ = fit_tdi(compute_tdi(tm), settings)
    a = int((2 * 3600 + 25 * 60) * tm.fs)
    tm.eta[0, a : a + int(600 * tm.fs)] = np.nan
    gap, _ = fit_tdi(compute_tdi(tm), settings)
    ratio = gap.sigma**2 / clean.sigma**2
    share = 600 / (6 * 3600)
    assert ratio.min() > 1 + share / 2 and 1 + share < np.median(ratio) < 1 + 3 * share, ratio
    z = (gap.coefficients - clean.coefficients) / np.sqrt(gap.sigma**2 - clean.sigma**2)
    assert np.sqrt(np.mean(z**2)) < 2.5, z

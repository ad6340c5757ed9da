"""Adequacy statistics: p-values, band tables, the instrument noise model, the Bayes factor."""

import numpy as np
import pytest
from scipy import stats

from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.adequacy import (
    band_table,
    describe_failures,
    describe_time_failures,
    instrument_noise_csd,
    merged_band_edges,
    p_value,
)
from ttlcore.diagnose.evidence import log_bayes_factor
from ttlcore.estimate.fit import model_csd
from ttlcore.tdi.regressors import regressor_responses

LTT = np.array([8.425, 8.372, 8.322, 8.322, 8.372, 8.322])


def test_p_value_against_scipy_with_tolerance_and_correlation():
    # without tolerance and correlation: the plain chi^2 tail
    assert p_value(1100.0, 1000.0, 1.0, 0.0) == pytest.approx(stats.chi2.sf(1100, 1000))
    # kappa: chi2/kappa with dof/kappa degrees of freedom; tolerance scales the statistic
    assert p_value(1100.0, 1000.0, 2.0, 0.1) == pytest.approx(stats.chi2.sf(1100 / 2.2, 500))
    assert p_value(1000.0, 1000.0, 1.0, 0.05) > 0.5


def test_band_table_on_gaussian_noise_of_known_csd():
    # complex Gaussian spectra with unit whitened covariance: chi2/dof = 1 within its
    # statistical scatter sqrt(2/dof), p-values not small, no failure
    rng = np.random.default_rng(1)
    S, m = 4, 20000
    wr = (rng.standard_normal((S, m, 3)) + 1j * rng.standard_normal((S, m, 3))) / np.sqrt(2)
    edges = np.array([0.0, 0.25, 0.5, 1.0])
    f = np.linspace(0, 1, m, endpoint=False)
    bidx = np.searchsorted(edges, f, side="right") - 1
    tab = band_table(wr, bidx, edges)
    # chi2 = 2 sum |wr|^2 has mean 2 * 3 * bins (= dof)
    assert np.allclose(tab.chi2_dof, 1.0, atol=4 * np.sqrt(2 / tab.dof.min()))
    assert not tab.fails.any()
    assert describe_failures(tab) == []
    # 20 % excess in one band and channel A: fails there, named with the channel
    wr[:, bidx == 2, 0] *= np.sqrt(1.6)
    tab = band_table(wr, bidx, edges)
    assert list(tab.fails) == [False, False, True]
    text = describe_failures(tab)
    assert len(text) == 1 and "in A" in text[0] and "0.5 Hz" in text[0]


def test_time_failure_text():
    t0 = 0.0
    starts = np.arange(6) * 3600.0
    assert describe_time_failures(starts, starts + 3600, [0, 0, 0, 0, 1, 1], t0) == ["fails after 4.0 h"]
    assert describe_time_failures(starts, starts + 3600, [1, 0, 0, 0, 0, 0], t0) == ["fails before 1.0 h"]
    assert describe_time_failures(starts, starts + 3600, [0, 1, 1, 0, 0, 0], t0) == ["fails between 1.0 h and 3.0 h"]
    assert describe_time_failures(starts, starts + 3600, [0] * 6, t0) == []


def test_instrument_noise_model_adds_the_dws_term_of_each_channel():
    f = np.geomspace(3e-3, 0.8, 200)
    base = model_csd(f, LTT)
    assert np.array_equal(instrument_noise_csd(f, LTT), base)
    # one coefficient: |C T|^2 S_dws on the diagonal, computed independently here
    C = np.zeros(24)
    k = COEFFICIENT_NAMES.index("23.eta.tx")
    C[k] = 2.3e-3
    a = 70e-9 / 335
    got = instrument_noise_csd(f, LTT, C, a) - base
    T = regressor_responses(f, LTT)[:, :, k]
    expected = np.abs(T * C[k]) ** 2 * ((2 * np.pi * f * a) ** 2)[:, None]
    # (the difference of two CSDs: rounding of the larger base term, 1e-16 of it, remains)
    tol = 1e-12 * np.real(np.einsum("mii->mi", base))
    assert np.all(np.abs(np.real(np.einsum("mii->mi", got)) - expected) <= 1e-9 * expected + tol)
    # rx and tx of the same MOSA add coherently (same DWS readout)
    C2 = C.copy()
    k2 = COEFFICIENT_NAMES.index("23.eta.rx")
    C2[k2] = 1e-3
    g = regressor_responses(f, LTT)[:, :, [k, k2]] @ C2[[k, k2]]
    exp2 = np.abs(g) ** 2 * ((2 * np.pi * f * a) ** 2)[:, None]
    got2 = np.real(np.einsum("mii->mi", instrument_noise_csd(f, LTT, C2, a) - base))
    assert np.all(np.abs(got2 - exp2) <= 1e-9 * exp2 + tol)


def test_log_bayes_factor_against_direct_integration():
    # one parameter: B = int N(beta; b, 1/A) N(b; 0, s^2) db / N(beta; 0, 1/A), by quadrature
    A, beta, s = np.array([[4.0]]), np.array([1.3]), 0.7
    x = np.linspace(-10, 10, 200001)
    like = np.exp(-0.5 * A[0, 0] * (x - beta[0]) ** 2)
    prior = np.exp(-0.5 * x**2 / s**2) / np.sqrt(2 * np.pi * s**2)
    num = np.trapezoid(like * prior, x)
    den = np.exp(-0.5 * A[0, 0] * beta[0] ** 2)
    assert log_bayes_factor(A, beta, np.array([s])) == pytest.approx(np.log(num / den), rel=1e-8)
    # two correlated parameters: Monte-Carlo-free check through the Gaussian identity
    A2 = np.array([[3.0, 1.0], [1.0, 2.0]])
    b2 = np.array([0.5, -1.0])
    s2 = np.array([0.3, 2.0])
    D = np.diag(s2**2)

    # evidence ratio = N(b; 0, A^-1 + D) / N(b; 0, A^-1)
    def lognorm(v, cov):
        return -0.5 * (v @ np.linalg.solve(cov, v) + np.linalg.slogdet(2 * np.pi * cov)[1])

    Ai = np.linalg.inv(A2)
    assert log_bayes_factor(A2, b2, s2) == pytest.approx(lognorm(b2, Ai + D) - lognorm(b2, Ai), rel=1e-10)


def test_band_merging_reaches_the_minimum_dof():
    f = np.linspace(3e-3, 0.8, 5000)
    edges = np.geomspace(3e-3, 0.8 * (1 + 1e-9), 9)
    out = merged_band_edges(f, edges, 24, 2000)
    counts = np.histogram(f, bins=out)[0] * 24
    assert counts.min() >= 2000 and out[0] == edges[0] and out[-1] == edges[-1]
    assert len(out) < len(edges)


def test_third_octave_bands_localise_a_narrow_excess_and_merge_thin_bands():
    from ttlcore.diagnose.adequacy import third_octave_edges, third_octave_table

    edges = third_octave_edges((3e-3, 0.8))
    # a third of an octave apart, covering the band exactly
    assert np.allclose(edges[1:-1] / edges[:-2], 2 ** (1 / 3)) and edges[0] == 3e-3
    assert edges[-1] == pytest.approx(0.8) and edges[-2] < 0.8
    rng = np.random.default_rng(2)
    S = 4
    f = np.arange(int(3e-3 / 2e-5), int(0.8 / 2e-5)) * 2e-5  # a 50000 s segment's bins
    wr = (rng.standard_normal((S, f.size, 3)) + 1j * rng.standard_normal((S, f.size, 3))) / np.sqrt(2)
    sel = (f >= 0.2) & (f < 0.25)  # 10 % excess in E between 0.2 and 0.25 Hz
    wr[:, sel, 1] *= np.sqrt(1.3)
    tab = third_octave_table(wr, f, (3e-3, 0.8), min_dof=2000)
    dof = np.histogram(f, bins=tab.edges)[0] * 6 * S
    assert dof.min() >= 2000  # thin low-frequency bands merged
    assert len(tab.edges) > 20  # third-octave above ~10 mHz: finer than the 8 default bands
    failing = np.flatnonzero(tab.fails)
    assert failing.size >= 1
    for g in failing:  # every failing band overlaps the excess
        assert tab.edges[g] < 0.25 and tab.edges[g + 1] > 0.2
    assert tab.channel_fails()[failing].any(axis=0).tolist() == [False, True, False]

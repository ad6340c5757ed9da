"""Lagrange fractional delays against pytdi's implementation and analytic signals."""

import numpy as np
import pytest
from pytdi.dsp import timeshift as pytdi_timeshift

from ttlcore.tdi.interpolation import delay, lagrange_weights, timeshift


def test_weights_sum_to_one_and_reproduce_polynomials():
    # Lagrange interpolation of order N is exact for polynomials of degree <= N:
    # the weights sum to 1 and reproduce the first moment (a property, not a copy of the code).
    eps = np.linspace(0, 0.999, 37)
    w = lagrange_weights(eps, 31)
    offsets = np.arange(-15, 17)
    assert np.allclose(w.sum(axis=0), 1.0, atol=1e-12)
    assert np.allclose((offsets[:, None] * w).sum(axis=0), eps, atol=1e-9)


def test_integer_shift_is_exact():
    x = np.random.default_rng(0).standard_normal(500)
    y = timeshift(x, -7.0, order=31)
    assert np.array_equal(y[40:-40], x[33:-47])


def test_time_varying_shift_agrees_with_pytdi():
    # pytdi's dsp.timeshift is the outside reference; both evaluate the same Lagrange
    # polynomial, so they differ by float64 rounding only (~1e-15 of the signal).
    rng = np.random.default_rng(1)
    n = 50_000
    x = rng.standard_normal(n)
    shift = -8.33 * 4 + 2e-3 * np.sin(2 * np.pi * np.arange(n) / 2e4)
    ours = timeshift(x, shift, order=31)
    ref = pytdi_timeshift(x, shift, 31)
    valid = ~np.isnan(ours)
    assert valid.sum() > n - 60
    assert np.max(np.abs(ours[valid] - ref[valid])) < 1e-13


def test_delay_of_band_limited_sinusoid_matches_analytic():
    # D sin(2 pi f t) = sin(2 pi f (t - tau)): order-31 Lagrange at f/fs = 0.1 is accurate
    # to ~1e-14 (interpolation error ~ (pi f/fs)^32 scaled), far below the 1e-12 asked here.
    fs, f = 4.0, 0.4
    t = np.arange(4000) / fs
    tau = 8.3 + 1e-4 * t
    y = delay(np.sin(2 * np.pi * f * t), tau, fs, order=31)
    ok = ~np.isnan(y)
    assert np.max(np.abs(y[ok] - np.sin(2 * np.pi * f * (t[ok] - tau[ok])))) < 1e-12


def test_history_offset_equals_full_delay():
    rng = np.random.default_rng(2)
    x = rng.standard_normal(3000)
    tau = np.full(2900, 8.4)
    full = delay(x, np.full(3000, 8.4), 4.0)[100:]
    with_history = delay(x, tau, 4.0, history=100)
    assert np.allclose(full[~np.isnan(full)], with_history[~np.isnan(full)], rtol=0, atol=1e-15)


def test_even_order_rejected():
    with pytest.raises(ValueError, match="odd"):
        timeshift(np.zeros(10), 0.5, order=4)


@pytest.mark.parametrize("shift", [-2.37, 12.5001, -0.999999, 3.0])
def test_a_constant_shift_is_one_stencil_with_the_same_result(shift):
    # a scalar shift keeps one stencil broadcast over the samples (no weights per sample: 88 MB
    # for a day at 4 Hz and order 31); the result equals the shift given per sample exactly,
    # and agrees with pytdi's constant timeshift to float64 rounding
    rng = np.random.default_rng(2)
    x = rng.standard_normal((3, 2, 40_000))
    y = timeshift(x, shift, order=31)
    assert np.array_equal(y, timeshift(x, np.full(x.shape[-1], shift), order=31), equal_nan=True)
    ref = pytdi_timeshift(x[1, 0], shift, order=31)
    ok = np.isfinite(y[1, 0])
    assert np.allclose(y[1, 0][ok], ref[ok], rtol=0, atol=1e-12)

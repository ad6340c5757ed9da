"""The rolling fitter equals the batch analysis on the same span; it tracks drifts and steps."""

import numpy as np
import pytest

from ttlcore.conventions import DAY
from ttlcore.fit import FitSettings, fit_tdi
from ttlcore.rolling import RollingFit, StreamingDecimator
from ttlcore.simulator import SimulationConfig, simulate
from ttlcore.tdi_data import TDIStream, compute_tdi, lowpass_taps

HOUR = 3600.0


def test_streaming_decimator_equals_batch_filter():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((2, 10_000))
    x[:, :37] = np.nan
    h = lowpass_taps(4.0)
    dec = StreamingDecimator(h, 2)
    pieces = np.concatenate([dec.push(x[:, a:b]) for a, b in ((0, 3001), (3001, 3002), (3002, 7777), (7777, 10_000))], axis=-1)
    from ttlcore.tdi_data import TDIData

    td = TDIData(t0=0.0, fs=4.0, channels=("A", "E", "T"), data=np.vstack([x, x[:1]]), regressors=np.zeros((3, 1, 10_000)), names=("c",))
    batch = td.decimated(2).data[:2]
    np.testing.assert_allclose(pieces, batch, rtol=0, atol=1e-12, equal_nan=True)


@pytest.mark.parametrize("orbit", ["keplerian"])
def test_rolling_window_over_a_day_equals_batch_analysis(orbit):
    # Telemetry fed hour by hour through the streaming TDI and the rolling fitter; when the
    # window covers exactly the simulated day, the result equals the batch fit of that day
    # with the same settings (1-h FFT segments) to 1e-9 relative.
    tm, _ = simulate(SimulationConfig(duration=DAY, orbit=orbit, seed=3))
    settings = FitSettings(segment_duration=HOUR)
    batch, _ = fit_tdi(compute_tdi(tm), settings)
    stream, rolling = TDIStream(), RollingFit(settings, window_duration=DAY)
    results = [rolling.push(stream.push(tm.slice(k * 14400, (k + 1) * 14400))) for k in range(24)]
    assert all(r is not None for r in results)
    last = results[-1]
    assert last.n_segments == batch.n_segments == 24
    scale = np.max(np.abs(batch.coefficients))
    assert np.max(np.abs(last.coefficients - batch.coefficients)) < 1e-9 * scale
    assert np.max(np.abs(last.covariance - batch.covariance)) < 1e-9 * np.max(np.abs(batch.covariance))
    assert abs(last.chi2 - batch.chi2) < 1e-9 * batch.chi2

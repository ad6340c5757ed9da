"""The time-domain prediction of a fitted model (ttlcore.diagnose.prediction) against the
TDI of the signal the simulator injected: an independent check of what the live subtractor
takes away for effects beyond the linear TTL.

The days hold jitter, TTL coupling and a small secondary noise, and no DWS readout noise,
so that the DWS readouts are the true angular velocities: the injected signal and the
prediction are then the same function of the same series, and differ only by the fitted
parameters' statistical error and the interpolation of the delays (both order-31 Lagrange,
the simulator's taps and TDI's nested ones).  The injections come from the simulator's own
path (``EffectInjection``) and, for the frequency-dependent coupling, from the blind-test
plugin, which filters in its own code (tests/ttlcore/diagnose/blind_effects.py).
"""

from pathlib import Path

import numpy as np
import pytest

from ttlcore.diagnose.diagnoser import DiagnoseSettings, refit
from ttlcore.diagnose.prediction import effect_predictions, fit_residual
from ttlcore.effects import injection_from_spec, tdi_in_blocks
from ttlcore.sim.simulator import NoiseSwitches, SimulationConfig, simulate

BLIND = str(Path(__file__).with_name("blind_effects.py"))
NOISES = NoiseSwitches.parse("none,ttl,sc_jitter,mosa_jitter,oms")


#: The comparison band [Hz]: the fit's (what the parameters are estimated from) below the
#: data's anti-alias edge; above 1 Hz the simulator's delay taps and TDI's nested ones part.
BAND = (3e-3, 0.9)


def band_rms(x: np.ndarray, fs: float) -> np.ndarray:
    """RMS per channel of ``x`` (3, n) in :data:`BAND` (Parseval over the band's FFT bins)."""
    X = np.fft.rfft(x, axis=-1)
    f = np.fft.rfftfreq(x.shape[-1], 1 / fs)
    sel = (f >= BAND[0]) & (f <= BAND[1])
    return np.sqrt(np.sum(np.abs(X[:, sel]) ** 2, axis=-1))


def _day(inject: str, orbit: str = "keplerian", duration: float = 2 * 3600.0):
    inj = injection_from_spec(inject, (BLIND,))
    tm, truth = simulate(
        SimulationConfig(duration=duration, orbit=orbit, seed=5, noises=NOISES, injections=(inj,)), chunk_size=10**7
    )
    return tm, truth[f"injections/{inj.name}"]


@pytest.mark.parametrize(
    "inject, model, orbit",
    [
        # a witness two light travel times away (the live-loop issue's ghost), injected by the blind
        # plugin (which delays by twice the mean arm: exact with equal arms)
        ("blind-witness:source=12.eta,link=23,delay=2,gain=2e-3", "witness:source=12.eta,link=23,delay=2", "equal"),
        # a first-order low-pass on a witness, injected by the blind plugin's own FFT filter
        (
            "blind-lowpass:source=13.eta,link=31,delay=1,fc=0.05,gain=4e-3",
            "fd-coupling:source=13.eta,link=31,delay=1,filter=pole1,fc=0.05",
            "keplerian",
        ),
        # a DWS timing offset on spacecraft 1 (the simulator's exact shift): the shifted witnesses
        ("timing-offset:sc1.d1=0.2", "timing-offset:offset.sc1=0.2", "keplerian"),
    ],
)
def test_prediction_equals_the_tdi_of_the_injected_signal(inject, model, orbit):
    tm, injected = _day(inject, orbit)
    r = refit(tm, ["linear-ttl", model], settings=DiagnoseSettings(dws_asd=0.0))
    fit = r.fit
    ((spec, predicted),) = effect_predictions(fit).items()
    assert spec.split(":")[0] == model.split(":")[0]
    truth, _ = tdi_in_blocks(tm.ltt, tm.fs, (), injected, order=31, delay_order=fit.data.context.settings.delay_order)
    assert np.isfinite(predicted).all()  # zero where it cannot be computed
    ok = np.isfinite(truth).all(axis=0)
    assert ok.mean() > 0.95
    # the samples the shift's and the filter's stencils leave out are the data's first and last
    # few; 400 samples more at each end leave the filters' start-up out (3 s for fc 0.05 Hz)
    inner = np.flatnonzero(ok)[[0, -1]]
    sl = slice(inner[0] + 400, inner[1] - 400)
    scale = band_rms(truth[:, sl], tm.fs)
    err = band_rms(predicted[:, sl] - truth[:, sl], tm.fs)
    seen = scale > 1e-3 * scale.max()  # X2 does not see link 23
    # the fitted parameters' statistical error: the witness gain to 1 % (one sigma here), the
    # 24 linear coefficients that the offset shifts to a few per cent in X2 (measured 1-4 %)
    assert np.all(err[seen] < 0.05 * scale[seen]), (err / scale, spec)


def test_fit_residual_is_the_data_less_the_whole_model():
    """fit_residual = d - sum C_k R_k - prediction; with the effect injected, the whole
    model's residual is the secondary noise, the linear model's is not."""
    tm, _ = _day("blind-witness:source=12.eta,link=23,delay=2,gain=1e-2", "equal")
    settings = DiagnoseSettings(dws_asd=0.0)
    whole = refit(tm, ["linear-ttl", "witness:source=12.eta,link=23,delay=2"], settings=settings).fit
    linear = refit(tm, ["linear-ttl"], settings=settings).fit
    t0, fs, r_whole, pred = fit_residual(whole)
    _, _, r_linear, none = fit_residual(linear)
    assert none == {} and list(pred) == ["witness:source=12.eta,link=23,delay=2"]
    assert t0 == tm.t0 and fs == tm.fs and r_whole.shape == (3, tm.size)
    ok = np.flatnonzero(np.isfinite(r_whole).all(axis=0) & np.isfinite(r_linear).all(axis=0))
    sl = slice(ok[0], ok[-1] + 1)
    lin, both = band_rms(r_linear[:, sl], fs), band_rms(r_whole[:, sl], fs)
    # Y2 and Z2 carry link 23: the linear model leaves the effect in; X2 does not see it
    assert np.all(lin[1:] > 2 * both[1:]), (lin, both)
    assert lin[0] == pytest.approx(both[0], rel=0.01)

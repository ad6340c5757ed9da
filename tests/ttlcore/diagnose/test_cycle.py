"""A coupling that varies periodically over hours (``vary=cycle``, a thermal cycle): the
period is a searched parameter like any other (issue 10 items 3 and 4).

Injected: the DWS eta of MOSA 23 coupled into link 31 with a coefficient
``a sin(2 pi t / P) + b cos(2 pi t / P)``, ``P`` = 2 h, ``a`` = 6 mm/rad, ``b`` = -3 mm/rad,
through the simulator's own injection of the witness effect (the columns evaluated on the
true angular velocities).  The diagnosis sees only the telemetry.
"""

import numpy as np
import pytest

from ttlcore.diagnose.diagnoser import refit
from ttlcore.diagnose.whitened import whiten_telemetry
from ttlcore.effects import injection_from_spec, make_effects
from ttlcore.sim.simulator import SimulationConfig, simulate

PERIOD = 7200.0  # s
SIN, COS = 6e-3, -3e-3  # m/rad
MODEL = "witness:source=23.eta,link=31,vary=cycle,t_ref=0"


@pytest.fixture(scope="module")
def cycle_data():
    spec = f"witness:source=23.eta,link=31,vary=cycle,period={PERIOD:g},t_ref=0,sin={SIN},cos={COS}"
    tm, _ = simulate(
        SimulationConfig(duration=3 * 3600.0, orbit="keplerian", seed=5, injections=(injection_from_spec(spec),)),
        chunk_size=3 * 3600 * 4,
    )
    return whiten_telemetry(tm)


def test_cycle_columns_are_named_and_the_period_is_searched():
    effect = make_effects([MODEL])[0]
    assert effect.unresolved() == ["period"]
    at = effect.with_options(period=PERIOD)
    assert at.column_names() == ["witness.23.eta>31~cycle@2h.sin", "witness.23.eta>31~cycle@2h.cos"]
    with pytest.raises(Exception, match="vary"):
        make_effects(["witness:source=23.eta,vary=wobble"])[0].column_names()


def test_cycle_period_found_and_the_model_passes(cycle_data):
    out = refit(cycle_data, ["linear-ttl", MODEL])
    (found,) = out.to_json()["model"]["searched"].values()
    # the period: the search locates it on modulated TDI (2 pi 70 s / P ~ 6 % error on the
    # columns) and scores it exactly; it is within 1 % of the truth (0.4 % measured)
    assert found["estimates"]["period"] == pytest.approx(PERIOD, rel=0.01)
    lo, hi = found["intervals"]["period"]
    assert lo < found["estimates"]["period"] < hi
    assert max(out.change.bands_before) > 2  # the cycle is well above the noise
    assert not out.model.adequacy.fails, out.change.bands_after
    values, sigma = out.model.coefficients.values, out.model.coefficients.sigma
    (sin_name,) = [n for n in values if n.endswith(".sin")]
    (cos_name,) = [n for n in values if n.endswith(".cos")]
    # amplitude and phase are linear: within 5 sigma plus what the period's error mixes
    # between sine and cosine by the end of the data (2 pi 3 h / P x 0.4 % ~ 0.04 rad)
    for name, truth in ((sin_name, SIN), (cos_name, COS)):
        assert abs(values[name] - truth) < 5 * sigma[name] + 0.05 * np.hypot(SIN, COS), (name, values[name])


def test_cycle_with_a_wrong_fixed_period_fails(cycle_data):
    wrong = refit(cycle_data, ["linear-ttl", MODEL + ",period=4000"])
    assert wrong.model.adequacy.fails
    assert np.min(wrong.change.bands_after) > 1.5

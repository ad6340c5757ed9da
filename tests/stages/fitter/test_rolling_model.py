"""Unit tests of :mod:`stages.fitter.rolling_model`: the columns an extended model adds to the
rolling fit (real effects and TDI on synthetic telemetry; no bus in it)."""

import numpy as np
import pytest
from ttl_testutil import noise_telemetry

from stages.fitter.rolling_model import RollingModel, dropped_columns, rolling_outputs
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.estimate.fit import FitResult
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.data import TDIStream

WITNESS = "witness:source=12.eta,link=23,delay=2"
FS = 4.0


def telemetry(t0: float, seconds: float, seed: int) -> Telemetry:
    return noise_telemetry(t0, seconds, FS, seed)


def test_which_models_the_rolling_fit_carries():
    assert RollingModel("refit", None).column_effects(["linear-ttl", WITNESS]) is None
    rolling = RollingModel("rolling", None)
    assert rolling.column_effects(["linear-ttl"]) is None
    (effect,) = rolling.column_effects(["linear-ttl", WITNESS])
    assert effect.spec() == WITNESS and rolling.gates == []
    # a gate is left out of the fit, not a column
    effects = rolling.column_effects(["linear-ttl", WITNESS, "gate:start=100,stop=200"])
    assert [e.spec() for e in effects] == [WITNESS] and rolling.gates == [(100.0, 200.0)]
    # back to the 24 alone: nothing of the model before is kept
    assert rolling.column_effects(["linear-ttl"]) is None and rolling.gates == []
    # a model whose columns need the coefficients (linearised shifts): refitted on the window
    assert rolling.column_effects(["linear-ttl", "timing-offset"]) is None


def test_with_columns_appends_the_models_columns_to_the_24():
    rolling = RollingModel("rolling", None)
    rolling.column_effects(["linear-ttl", WITNESS])
    history = [telemetry(600.0 * k, 600.0, k) for k in range(4)]  # 2400 s before: more than needed
    tm = telemetry(2400.0, 600.0, 9)
    stream = TDIStream()
    for prev in history:
        stream.push(prev)
    td = stream.push(tm)
    extended, owners, xyz = rolling.with_columns(td, history, tm)
    (names,) = owners.values()
    assert list(owners) == [WITNESS] and len(names) >= 1
    assert xyz.shape == (3, len(names), tm.size)
    assert extended.names == tuple(td.names) + tuple(names)
    assert extended.regressors.shape == (3, len(td.names) + len(names), tm.size)
    np.testing.assert_array_equal(extended.regressors[:, len(td.names) :], xyz)
    assert np.isfinite(xyz).all() and np.any(xyz != 0)
    assert set(rolling.priors) >= set(names) and rolling.eiv
    # the columns come from COLUMN_HISTORY of telemetry before the segment: more changes nothing
    _, _, again = rolling.with_columns(td, history[1:], tm)
    np.testing.assert_allclose(again, xyz, rtol=1e-12, atol=0)


def test_rolling_outputs_split_the_fit_into_coefficients_and_model_parts():
    names = tuple(COEFFICIENT_NAMES) + ("w0",)
    p = len(names)
    coefficients = np.arange(1, p + 1, dtype=float) * 1e-4
    res = FitResult(
        names=names,
        coefficients=coefficients,
        covariance=np.diag(np.full(p, 4e-10)),
        chi2=1.0,
        dof=1.0,
        band=(0.01, 0.1),
        method="gls",
    )
    stream = TDIStream()
    td = stream.push(telemetry(0.0, 600.0, 1))
    xyz = np.ones((3, 1, td.data.shape[-1]))
    xyz[0, 0, :5] = np.nan  # not computable there: no contribution
    arrays, meta = rolling_outputs(res, td, {WITNESS: ("w0",)}, xyz)
    np.testing.assert_array_equal(arrays["coefficients"], coefficients[:24])
    np.testing.assert_allclose(arrays["sigma"], np.full(24, 2e-5))
    assert arrays["covariance"].shape == (24, 24)
    assert arrays["model_parts"].shape == (1, 3, td.data.shape[-1])
    assert np.all(arrays["model_parts"][0, 0, :5] == 0.0)
    assert arrays["model_parts"][0, 1, 0] == pytest.approx(coefficients[-1])
    assert meta == {
        "extra_parameters": {"w0": [coefficients[-1], 2e-5]},
        "model_parts": [WITNESS],
        "model_update": "rolling",
    }


def test_a_change_that_only_removes_effects_drops_their_columns():
    glitch, step = "glitch:t=900s,tm=12,beta=10s", "witness:source=12.eta,link=23,vary=step,t_step=500s"
    old = {WITNESS: ("w.a",), glitch: ("g.dv",), step: ("s.a", "s.b")}
    names = COEFFICIENT_NAMES + ("w.a", "g.dv", "s.a", "s.b")
    # the glitch gone, the others as they were: its column only
    assert dropped_columns(old, {WITNESS: ("w.a",), step: ("s.a", "s.b")}, names, names[:25] + names[26:]) == ["g.dv"]
    # back to the 24: every column
    assert dropped_columns(old, {}, names, COEFFICIENT_NAMES) == ["w.a", "g.dv", "s.a", "s.b"]
    # an effect added, or one whose columns changed (a coupling settled into the plain one,
    # another corner): rebuilt, nothing dropped
    assert dropped_columns(old, {**old, "drift": ("d.a",)}, names, names + ("d.a",)) == []
    assert dropped_columns(old, {WITNESS: ("w.a",), step: ("s.x",)}, names, COEFFICIENT_NAMES + ("w.a", "s.x")) == []
    # the names given are not the rolling fit's without the columns gone (another order)
    assert dropped_columns(old, {WITNESS: ("w.a",)}, names, ("w.a",) + COEFFICIENT_NAMES) == []

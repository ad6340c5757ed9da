"""Model effects: parsing, plugins, injections against independent formulas, and the
diagnosis columns against the injected signals through TDI."""

import numpy as np
import pytest

from ttlcore.conventions import COEFFICIENT_NAMES, LINKS, MOSAS, C
from ttlcore.effects import (
    EFFECTS,
    available_effects,
    columns_tdi,
    effect_input_from_telemetry,
    injection_from_spec,
    parse_effect_spec,
    tdi_in_blocks,
)
from ttlcore.effects.filters import derivative
from ttlcore.errors import ConfigError
from ttlcore.estimate.fit import FitSettings, fit_tdi
from ttlcore.sim.coefficients import make_coefficients
from ttlcore.sim.injection import injection_from_description
from ttlcore.sim.simulator import NoiseSwitches, SimulationConfig, simulate
from ttlcore.tdi.combinations import MICHELSON, build
from ttlcore.tdi.data import TDIData, compute_tdi
from ttlcore.tdi.interpolation import timeshift

#: jitter and TTL only (no readout noise): the DWS readouts are the true velocities
QUIET = dict(orbit="equal", seed=7, noises=NoiseSwitches.parse("none,ttl,sc_jitter,mosa_jitter"))


def test_named_effects_and_parsing():
    assert {"linear-ttl", "drift", "step", "cross-coupling", "timing-offset", "second-order", "ltt-error"} <= set(
        EFFECTS
    )
    eff, values = parse_effect_spec("drift:mosas=12+13,12.phi.rx=2e-3")
    assert eff.mosas == ("12", "13") and values == {"drift.12.phi.rx": 2e-3}
    eff, values = parse_effect_spec("timing-offset:sc1.d1=0.05")
    assert values == {"timing-offset.sc1.d1": 0.05}
    assert len(parse_effect_spec("cross-coupling:sides=tx,all=1e-3")[1]) == 12
    with pytest.raises(ConfigError, match="unobservable"):
        parse_effect_spec("cross-coupling:sides=rx+tx")
    with pytest.raises(ConfigError, match="unknown effect 'nope'"):
        parse_effect_spec("nope")
    with pytest.raises(ConfigError, match="unknown column"):
        parse_effect_spec("drift:99.phi.rx=1")
    with pytest.raises(ConfigError, match="mosas"):
        parse_effect_spec("drift:mosas=45")
    with pytest.raises(ConfigError, match="no parameter value"):
        injection_from_spec("drift")


def test_injection_description_round_trip():
    inj = injection_from_spec("second-order:mosas=12,quad.12.phiphi.rx=300")
    again = injection_from_description(inj.describe())
    assert again.describe() == inj.describe()
    cfg = SimulationConfig(duration=100.0, injections=(inj,))
    assert SimulationConfig.from_dict(cfg.to_dict()).injections[0].describe() == inj.describe()


@pytest.mark.parametrize("kind", ["drift", "step"])
def test_drift_and_step_injections_equal_the_simulators_own_coefficient_model(kind):
    # independent path: the simulator's CoefficientModel.with_drift / with_step forms the
    # same physics inside its TTL term (rx and delayed tx)
    rates = {"12.phi.rx": 3e-3, "21.eta.tx": -2e-3, "31.phi.tx": 1e-3}
    if kind == "drift":
        coeffs = make_coefficients("paper").with_drift(rates)  # m/rad per day
        spec = "drift:t_ref=0," + ",".join(f"{k}={v}" for k, v in rates.items())
    else:
        coeffs = make_coefficients("paper").with_step(700.0, rates)
        spec = "step:t_step=700," + ",".join(f"{k}={v}" for k, v in rates.items())
    a, _ = simulate(SimulationConfig(duration=1500.0, coefficients=coeffs, **QUIET), chunk_size=1100)
    b, tb = simulate(
        SimulationConfig(duration=1500.0, injections=(injection_from_spec(spec),), **QUIET), chunk_size=1100
    )
    scale = np.max(np.abs(tb[f"injections/{kind}"]))
    assert scale > 0
    # the sums differ by rounding only (the simulator adds the terms in another order)
    np.testing.assert_allclose(b.eta, a.eta, rtol=0, atol=1e-9 * scale)


def test_timing_offset_injection_against_a_shifted_ttl():
    delta = 0.05
    base_cfg = SimulationConfig(duration=2000.0, **QUIET)
    tm, truth = simulate(
        SimulationConfig(duration=2000.0, injections=(injection_from_spec(f"timing-offset:sc1.d1={delta}"),), **QUIET),
        chunk_size=100000,
    )
    inj = truth["injections/timing-offset"]
    # independent: rx terms of the MOSAs of SC 1 read at t + delta (whole series, no chunks)
    c = base_cfg.coefficients.values(np.zeros(1))[:, 0]
    expected = np.zeros(6)
    for m in ("12", "13"):
        k = MOSAS.index(m)
        x = sum(c[COEFFICIENT_NAMES.index(f"{m}.{a}.rx")] * truth[f"angular_velocity/{a}"][k] for a in ("phi", "eta"))
        shifted = timeshift(x, delta * tm.fs)
        d = -(shifted - x) / C
        sl = slice(100, -100)
        # link m carries the rx term of MOSA m and the tx terms of MOSAs 21 / 31 (SC 2, 3: no shift)
        np.testing.assert_allclose(inj[LINKS.index(m), sl], d[sl], rtol=0, atol=1e-6 * np.nanmax(np.abs(d)))
        expected[k] = np.nanstd(d)
    # links 23 and 32 see neither rx nor tx terms of SC 1 ... but 21 and 31 see its tx terms
    assert np.all(inj[LINKS.index("23")] == 0) and np.all(inj[LINKS.index("32")] == 0)
    assert np.std(inj[LINKS.index("21")]) > 0.1 * expected.max()


def test_timing_offset_injection_is_invisible_to_chunking():
    # the simulator hands injections the samples after each chunk (ChunkContext.*_ahead):
    # reading the angles 0.04 s ahead uses centred stencils at the chunk ends too, so
    # 1000-sample chunks give the one-piece result to rounding
    spec = "timing-offset:sc2.d1=-0.04"
    a = simulate(
        SimulationConfig(duration=2000.0, injections=(injection_from_spec(spec),), **QUIET), chunk_size=100000
    )[1]
    b = simulate(SimulationConfig(duration=2000.0, injections=(injection_from_spec(spec),), **QUIET), chunk_size=1000)[
        1
    ]
    rms = np.std(a["injections/timing-offset"])
    assert rms > 0
    np.testing.assert_allclose(b["injections/timing-offset"], a["injections/timing-offset"], rtol=0, atol=1e-9 * rms)


def test_second_order_injection_against_truth_angles_and_chunk_invariance():
    K = 4e5
    spec = f"second-order:mosas=13,terms=phiphi,quad.13.phiphi.rx={K}"
    a, ta = simulate(
        SimulationConfig(duration=2000.0, injections=(injection_from_spec(spec),), **QUIET), chunk_size=700
    )
    b, tb = simulate(
        SimulationConfig(duration=2000.0, injections=(injection_from_spec(spec),), **QUIET), chunk_size=5000
    )
    np.testing.assert_allclose(
        ta["injections/second-order"],
        tb["injections/second-order"],
        rtol=0,
        atol=1e-9 * np.max(np.abs(tb["injections/second-order"])),
    )
    k = MOSAS.index("13")
    phi, phidot = ta["angles/phi"][k], ta["angular_velocity/phi"][k]
    expected = -2 * K * phi * phidot / C  # d/dt (K phi^2) = 2 K phi phi'
    np.testing.assert_allclose(ta["injections/second-order"][LINKS.index("13")], expected, rtol=1e-9, atol=1e-30)


def test_ltt_error_injection_against_a_wrongly_delayed_tx_term():
    eps = 0.1
    tm, truth = simulate(
        SimulationConfig(duration=2000.0, injections=(injection_from_spec(f"ltt-error:12.d1={eps}"),), **QUIET),
        chunk_size=100000,
    )
    c = make_coefficients("paper").values(np.zeros(1))[:, 0]
    k21 = MOSAS.index("21")
    src = sum(c[COEFFICIENT_NAMES.index(f"21.{a}.tx")] * truth[f"angular_velocity/{a}"][k21] for a in ("phi", "eta"))
    tau = tm.ltt[LINKS.index("12")]
    wrong = timeshift(src, -(tau + eps) * tm.fs)
    right = timeshift(src, -tau * tm.fs)
    expected = -(wrong - right) / C
    got = truth["injections/ltt-error"][LINKS.index("12")]
    sl = slice(100, -100)
    np.testing.assert_allclose(got[sl], expected[sl], rtol=0, atol=1e-6 * np.nanmax(np.abs(expected)))
    assert np.all(truth["injections/ltt-error"][np.arange(6) != LINKS.index("12")] == 0)


@pytest.mark.parametrize(
    "spec",
    [
        "drift:t_ref=0,all=5e-3",
        "cross-coupling:sides=tx,all=1e-3",
        "second-order:sides=rx+tx,quad.12.phieta.rx=3e5,quad.32.etaeta.tx=-2e5",
    ],
)
def test_effect_columns_through_tdi_reproduce_the_injected_signal(spec):
    # with jitter only and no readout noise, the TDI of the injected signal equals the
    # effect's columns (built from the DWS readouts) through TDI times the injected values:
    # an independent check of the column definitions, their placement and the TDI path
    inj = injection_from_spec(spec)
    tm, truth = simulate(
        SimulationConfig(
            duration=1200.0,
            noises=NoiseSwitches.parse("none,sc_jitter,mosa_jitter"),
            orbit="unequal",
            seed=3,
            injections=(inj,),
        )
    )
    assert np.allclose(tm.eta, truth[f"injections/{inj.name}"], atol=0)
    cols = inj.effect.columns(effect_input_from_telemetry(tm))
    built = build(MICHELSON, tm.ltt, tm.fs)
    tdi_cols = columns_tdi(cols, built)
    model = np.einsum("k,ckn->cn", np.array([inj.values.get(c.name, 0.0) for c in cols]), tdi_cols)
    data = np.stack([b(tm.eta) for b in built])
    ok = np.isfinite(data).all(axis=0) & np.isfinite(model).all(axis=0)
    assert ok.sum() > 0.8 * tm.size
    scale = np.max(np.abs(data[:, ok]))
    # the simulator delays with its own taps, TDI with its nested ones: both order-31 Lagrange
    np.testing.assert_allclose(model[:, ok], data[:, ok], rtol=0, atol=1e-6 * scale)


def test_tdi_in_blocks_equals_one_block():
    # the diagnosis computes TDI in blocks, each with the history its delays reach back to:
    # the result must be the one-block TDI (same taps, same samples) to rounding, NaN alike
    inj = injection_from_spec("cross-coupling:sides=tx,all=1e-3")
    tm, _ = simulate(SimulationConfig(duration=1800.0, orbit="keplerian", seed=4, injections=(inj,)))
    cols = inj.effect.columns(effect_input_from_telemetry(tm))
    built = build(MICHELSON, tm.ltt, tm.fs)
    whole_cols = columns_tdi(cols, built)
    whole_data = np.stack([b(tm.eta) for b in built])
    data, blocks = tdi_in_blocks(tm.ltt, tm.fs, cols, tm.eta, order=31, delay_order=5, block=1000)
    np.testing.assert_array_equal(np.isnan(blocks), np.isnan(whole_cols))
    np.testing.assert_array_equal(np.isnan(data), np.isnan(whole_data))
    ok = np.isfinite(whole_data).all(axis=0) & np.isfinite(whole_cols).all(axis=(0, 1))
    assert ok.sum() > 0.9 * tm.size
    np.testing.assert_allclose(
        blocks[..., ok], whole_cols[..., ok], rtol=0, atol=1e-12 * np.abs(whole_cols[..., ok]).max()
    )
    np.testing.assert_allclose(data[:, ok], whole_data[:, ok], rtol=0, atol=1e-12 * np.abs(whole_data[:, ok]).max())


def test_derivative_is_accurate_in_band():
    fs = 4.0
    t = np.arange(4000) / fs
    for f in (0.01, 0.3, 0.9):
        x = np.sin(2 * np.pi * f * t)
        d1 = derivative(x, fs, 1)[20:-20]
        d2 = derivative(x, fs, 2)[20:-20]
        w = 2 * np.pi * f
        # 25-point central differences at 4 Hz: relative error below 1e-5 up to 0.9 Hz
        # (measured 9e-6 at 0.9 Hz), negligible against the effects they build
        np.testing.assert_allclose(d1, w * np.cos(w * t[20:-20]), atol=2e-5 * w)
        np.testing.assert_allclose(d2, -(w**2) * x[20:-20], atol=1e-4 * w**2)


def test_fit_tdi_with_extra_regressors_recovers_a_drift():
    # noise-free TTL with a drift: the 24 + 24 fit recovers both exactly; the result for
    # the 24-coefficient case is unchanged by the extension (bit-for-bit, other tests)
    rates = {"12.phi.rx": 0.4, "23.eta.tx": -0.3}
    spec = "drift:t_ref=1800," + ",".join(f"{k}={v}" for k, v in rates.items())
    inj = injection_from_spec(spec)
    tm, truth = simulate(
        SimulationConfig(
            duration=3600.0, noises=NoiseSwitches.parse("none,ttl,sc_jitter,mosa_jitter"), seed=4, injections=(inj,)
        )
    )
    td = compute_tdi(tm)
    cols = inj.effect.columns(effect_input_from_telemetry(tm))
    built = build(MICHELSON, tm.ltt, tm.fs)
    extra = TDIData(
        t0=td.t0,
        fs=td.fs,
        channels=td.channels,
        data=np.zeros_like(td.data),
        regressors=columns_tdi(cols, built),
        names=tuple(c.name for c in cols),
        ltt_mean=td.ltt_mean,
    )
    res, _ = fit_tdi(td, FitSettings(dws_asd=0.0, segment_duration=1200.0, eiv=False), extra=extra)
    assert res.names[:24] == COEFFICIENT_NAMES and len(res.names) == 48
    c_true = make_coefficients("paper").values(np.zeros(1))[:, 0]
    np.testing.assert_allclose(res.coefficients[:24], c_true, rtol=0, atol=1e-6 * 2.3e-3)
    got = dict(zip(res.names, res.coefficients))
    for k, v in rates.items():
        assert got[f"drift.{k}"] == pytest.approx(v, rel=1e-3)


def test_plugin_module_by_path(tmp_path):
    path = tmp_path / "myeffect.py"
    path.write_text(PLUGIN)
    effects = available_effects([str(path)])
    assert "stray-12-on-23" in effects and "drift" in effects
    eff, values = parse_effect_spec("stray-12-on-23:k.phi=1e-3", [str(path)])
    assert values == {"stray-12-on-23.k.phi": 1e-3}
    inj = eff.injection(values)
    again = injection_from_description(inj.describe())  # rebuilt from the stored path
    assert again.describe() == inj.describe()
    bad = tmp_path / "empty.py"
    bad.write_text("x = 1\n")
    with pytest.raises(ConfigError, match="defines no effect"):
        available_effects([str(bad)])


PLUGIN = '''
from ttlcore.effects import Column, Effect, Part


class StrayLight(Effect):
    """DWS of MOSA 12 leaking into link 23 (a made-up path for the tests)."""

    name = "stray-12-on-23"
    title = "stray light from MOSA 12 into link 23"
    physics = "Light scattered from MOSA 12 reaches the receiver of link 23."
    parameters = {}

    def columns(self, data):
        return [Column(f"{self.name}.k.{a}", [Part("23", data.witness("12", a))], "m/rad", 1e-3)
                for a in ("phi", "eta")]


EFFECTS = [StrayLight]
'''


def test_rational_basis_spans_the_resonance_the_first_order_path_and_a_constant():
    # pole2: the resonance 1 / (1 - (f/f0)^2 + i f / (f0 q)) is b0; the constant coupling is
    # b0 + b1 / q + b2; pole1: the low-pass 1 / (1 + i f / fc) is b0, the constant b0 + b1
    from ttlcore.effects.filters import rational_basis

    f = np.geomspace(1e-3, 1.0, 200)
    f0, q = 0.08, 15.0
    b = rational_basis("pole2", f, f0, q)
    np.testing.assert_allclose(b[0], 1 / (1 - (f / f0) ** 2 + 1j * f / (f0 * q)), rtol=1e-12)
    np.testing.assert_allclose(b[0] + b[1] / q + b[2], 1.0, rtol=1e-12)
    p = rational_basis("pole1", f, 0.03)
    np.testing.assert_allclose(p[0], 1 / (1 + 1j * f / 0.03), rtol=1e-12)
    np.testing.assert_allclose(p[0] + p[1], 1.0, rtol=1e-12)


def test_fd_coupling_declares_its_searched_poles_and_holds_given_ones():
    from ttlcore.effects import make_effects

    searched, held = make_effects(
        ["fd-coupling:source=12.phi,link=23,delay=1", "fd-coupling:mosas=12,filter=pole1,fc=0.05"]
    )
    assert searched.unresolved() == ["f0", "q"] and held.unresolved() == []
    assert searched.column_names() == ["fd.12.phi>23+1L.b0", "fd.12.phi>23+1L.b1", "fd.12.phi>23+1L.b2"]
    # the rx placement of MOSA 12 is that of the linear coefficients 12.phi.rx and 12.eta.rx:
    # their constant coupling is the coefficient's, so the basis drops a column there
    assert held.column_names() == ["fd.12.phi>12.b0", "fd.12.eta>12.b0"]
    kept = held.with_options(flat="keep")
    assert kept.column_names() == ["fd.12.phi>12.b0", "fd.12.phi>12.b1", "fd.12.eta>12.b0", "fd.12.eta>12.b1"]
    # tx of MOSA 13: link 31 after one delay; delay 2 or a time variation keep the full basis
    (on_tx,) = make_effects(["fd-coupling:source=13.eta,link=31,delay=1"])
    assert on_tx.column_names() == ["fd.13.eta>31+1L.b0", "fd.13.eta>31+1L.b1"]
    assert on_tx.with_options(delay=2).column_names()[-1].endswith("+2L.b2")
    assert len(on_tx.with_options(vary="drift").column_names()) == 3
    assert searched.with_options(f0=0.1, q=5).spec() == "fd-coupling:source=12.phi,link=23,delay=1,f0=0.1Hz,q=5"


def test_fd_coupling_responses_share_the_basis_per_frequency_array():
    # the columns' responses compute the basis once per frequency array they are called
    # with in turn; another array (or the same values in a new array) gets its own basis
    from ttlcore.effects import make_effects
    from ttlcore.effects.filters import rational_basis

    (eff,) = make_effects(["fd-coupling:source=12.phi,link=23,delay=1,f0=0.08,q=15"])
    resp = eff.response_functions()
    f1, f2 = np.geomspace(1e-3, 1.0, 50), np.linspace(0.01, 0.9, 70)
    for f in (f1, f2, f1.copy(), f1):
        ref = rational_basis("pole2", f, 0.08, 15.0)
        for j, r in enumerate(resp):
            np.testing.assert_array_equal(r(f), ref[j])
    (one,) = make_effects(["fd-coupling:mosas=12,filter=pole1,fc=0.05"])
    r1 = one.response_functions()
    assert len(r1) == 2
    np.testing.assert_array_equal(r1[1](f2), rational_basis("pole1", f2, 0.05)[1])

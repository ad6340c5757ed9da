"""The pure column builders of the diagnosis (ttlcore.diagnose.columns) and the normal
equations they give (ttlcore.diagnose.model_fit), each against an independent construction:

- an effect's whitened columns against its time-domain columns
  (:func:`ttlcore.diagnose.prediction.column_regressors`, the subtractor's path) decimated,
  transformed and whitened here by hand;
- re-whitening under another noise model against whitening from scratch (a CSD scaled by
  ``a`` scales the whitened spectra by ``a^-1/2``, exactly);
- the Gram matrix of the real interleaved layout against ``Re sum conj(a) b`` in complex;
- :func:`assemble` as a selection (values, order, no copy for the whole set).
- the input-rate regressors built again from the telemetry against ``compute_tdi`` of the
  whole stretch, and the derivative columns from them against those from kept regressors.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from ttlcore.diagnose.candidates import SHARED_SETS
from ttlcore.diagnose.columns import (
    ColumnStore,
    assemble,
    derivative_columns,
    effect_columns,
    empty_set,
    rewhitened,
    ttl_columns,
)
from ttlcore.diagnose.model_fit import gram, normal_equations, rhs
from ttlcore.diagnose.prediction import column_regressors
from ttlcore.diagnose.settings import DiagnoseSettings
from ttlcore.diagnose.whitened import whiten_tdi, whiten_telemetry
from ttlcore.effects import make_effects
from ttlcore.sim.simulator import SimulationConfig, simulate
from ttlcore.tdi.data import compute_tdi


@pytest.fixture(scope="module")
def data():
    tm, _ = simulate(SimulationConfig(duration=2 * 3600, orbit="keplerian", seed=5))
    return whiten_telemetry(tm, DiagnoseSettings(noise_model="fixed"))


def test_effect_columns_equal_the_time_domain_columns_whitened_by_hand(data):
    (witness,) = make_effects(["witness:source=12.eta,link=23,delay=2"])
    cs = effect_columns(data, witness, cache=False)
    s = data.context.settings
    names, xyz, eiv = column_regressors(data.context.tm, witness, order=s.order, delay_order=s.delay_order)
    assert cs.names == names
    # a plain witness of 12.eta carries that channel's readout noise, placed as the columns are
    assert [p[:3] for p in eiv[names[0]]] == [((m, a), link, tuple(extra)) for (m, a), link, extra, _ in cs.eiv[0]]
    # the same TDI, decimated with the data's filter, FFT'd on the data's segments and
    # whitened with L^H: the diagnosis' path, rebuilt from its documented steps
    by_hand = data.noise.whiten(data.grid.spectra(data.grid.decimate(xyz)))  # (S, m, 3, k)
    np.testing.assert_allclose(cs.w, by_hand, rtol=0, atol=1e-9 * np.max(np.abs(by_hand)))


def test_rewhitening_under_a_scaled_noise_model_scales_the_columns(data):
    cs = ttl_columns(data)
    scaled = data.with_noise(4.0 * data.noise.csd)
    moved = rewhitened(cs, data.noise.Lh, scaled)
    assert moved.noise_key == scaled.noise.key != cs.noise_key
    # S -> 4 S: L^H -> L^H / 2, the whitened spectra halve
    np.testing.assert_allclose(moved.x, cs.x / 2, rtol=1e-12, atol=1e-12 * np.max(np.abs(cs.x)))


def test_gram_is_the_complex_inner_product(data):
    cs = ttl_columns(data).select(["12.phi.tx", "23.eta.rx", "31.phi.rx"])
    N = gram(data, cs, cs)  # (S, G, p, p)
    b = rhs(data, cs)
    w = cs.w  # (S, m, 3, p) complex
    for g, (lo, hi) in enumerate(data.grid.slices):
        direct = np.real(np.einsum("smci,smcj->sij", np.conj(w[:, lo:hi]), w[:, lo:hi]))
        np.testing.assert_allclose(N[:, g], direct, rtol=1e-10, atol=1e-12 * np.max(np.abs(direct)))
        rhs_direct = np.real(np.einsum("smci,smc->si", np.conj(w[:, lo:hi]), data.noise.wd[:, lo:hi]))
        np.testing.assert_allclose(b[:, g], rhs_direct, rtol=1e-10, atol=1e-12 * np.max(np.abs(rhs_direct)))
    neq = normal_equations(data, cs)
    assert (
        neq.N.shape == (data.grid.G, 3, 3) and neq.dof_per_band().sum() == 6 * len(data.grid.starts) * data.grid.f.size
    )


def test_assemble_selects_and_keeps_a_whole_set(data):
    cs = ttl_columns(data)
    assert assemble(cs.names, cs) is cs
    pick = assemble(["31.eta.tx", "12.phi.rx"], cs)
    assert pick.names == ("31.eta.tx", "12.phi.rx")
    np.testing.assert_array_equal(pick.x[0], cs.x[cs.names.index("31.eta.tx")])
    with pytest.raises(Exception, match="not built"):
        assemble(["no.such.column"], cs)


def test_the_store_releases_what_a_phase_stored_and_keeps_the_rest():
    # the diagnosis drops the candidates' columns after their phase (ColumnStore.release_since):
    # what was stored before stays, under its family too; what came after is gone
    data = SimpleNamespace(noise=SimpleNamespace(Lh=np.eye(3)[None], key="k"))
    store = ColumnStore()
    store.put(("regressors",), data, empty_set("k"))
    store.put(("model", "C0"), data, empty_set("k"), family=("model",))
    mark = store.mark()
    store.put(("candidate", "a"), data, empty_set("k"))
    store.put(("trial", "C1"), data, empty_set("k"), family=("trial",))
    store.release_since(mark)
    assert store.get(("regressors",), data) is not None
    assert store.get(("model", "C0"), data) is not None
    assert store.get(("candidate", "a"), data) is None
    assert store.get(("trial", "C1"), data) is None
    # a family whose entry was dropped starts again; the kept family still drops its old entry
    store.put(("model", "C1"), data, empty_set("k"), family=("model",))
    assert store.get(("model", "C0"), data) is None
    # one candidate scored at a time (CandidatePool, one thread): its own sets go, those the
    # candidates share (by the first item of their key) stay
    mark = store.mark()
    store.put(("derivatives",), data, empty_set("k"))
    store.put(("approx", "drift", ()), data, empty_set("k"))
    store.release_since(mark, keep=SHARED_SETS)
    assert store.get(("derivatives",), data) is not None and store.get(("approx", "drift", ()), data) is None


def test_input_rate_regressors_are_built_again_from_the_telemetry_not_kept(data):
    # whiten_telemetry keeps no input-rate regressors (a day's 24 at 4 Hz: 199 MB); those
    # asked for are built again from the telemetry. Against compute_tdi, the TDI of the whole
    # stretch in one call of the engine (its own witness construction and part layout): the
    # same interpolation of the same samples, so equal to rounding (1e-12 of the largest value)
    td = data.tdi.td_in
    assert td.names == () and td.regressors.shape == (3, 0, td.size)
    names = ("12.phi.rx", "31.eta.tx", "23.phi.tx")
    got = data.tdi.input_regressors(names)
    ref = compute_tdi(data.context.tm, names=names).to_aet().regressors
    ok = np.isfinite(ref).all(axis=(0, 1))
    assert ok.sum() > 0.9 * td.size and np.isfinite(got[..., ok]).all()
    np.testing.assert_allclose(got[..., ok], ref[..., ok], rtol=0, atol=1e-12 * np.abs(ref[..., ok]).max())
    with pytest.raises(KeyError, match="not a TTL regressor"):
        data.tdi.input_regressors(["12.phi.rx", "dws-x"])


def test_derivative_columns_from_rebuilt_regressors_equal_those_from_kept_ones(data):
    # the same whitened data built from the kept TDI (whiten_tdi of compute_tdi: the regressors
    # held, as before they were rebuilt): the derivative columns agree to rounding
    tm = data.context.tm
    held = whiten_tdi(compute_tdi(tm).to_aet(), data.context.settings, tm=tm)
    assert held.tdi.rebuild is None and held.tdi.td_in.regressors.shape[1] == 24
    a, b = derivative_columns(data).x, derivative_columns(held).x
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * np.abs(b).max())


def test_a_weighted_sum_of_regressors_is_one_tdi_equal_to_the_sum_of_their_tdi(data):
    # TDI is linear: the TDI of the weighted witnesses (one column, what a shifted effect's
    # unshifted group needs) equals the weighted sum of the regressors' TDI built one by one,
    # to rounding (1e-12 of the largest value: the same interpolation of the same samples);
    # the held path (td_in keeps the regressors) is the plain weighted sum
    tm = data.context.tm
    names = ("12.phi.rx", "12.eta.rx", "21.phi.tx", "21.eta.tx")  # parts on two links, one shared
    w = np.array([1.3e-3, -2.1e-3, 0.7e-3, 2.5e-3])
    ref = np.einsum("k,ckn->cn", w, data.tdi.input_regressors(names))
    got = data.tdi.input_combination(names, w)
    ok = np.isfinite(ref).all(axis=0)
    assert ok.sum() > 0.9 * ref.shape[1] and np.array_equal(np.isfinite(got), np.isfinite(ref))
    np.testing.assert_allclose(got[:, ok], ref[:, ok], rtol=0, atol=1e-12 * np.abs(ref[:, ok]).max())
    held = whiten_tdi(compute_tdi(tm).to_aet(), data.context.settings, tm=tm)
    got_held = held.tdi.input_combination(names, w)
    np.testing.assert_allclose(got_held[:, ok], ref[:, ok], rtol=0, atol=1e-9 * np.abs(ref[:, ok]).max())
    with pytest.raises(KeyError, match="not a TTL regressor"):
        data.tdi.input_combination(["12.phi.rx", "dws-x"], [1.0, 1.0])

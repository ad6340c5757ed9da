"""Witness search: the injected path is the top witness, in the band where it acts."""

import numpy as np

from ttlcore.diagnose.fitting import fit_model
from ttlcore.diagnose.whitened import whiten_telemetry
from ttlcore.diagnose.witnesses import witness_search
from ttlcore.effects import Column, Effect, Part
from ttlcore.sim.simulator import SimulationConfig, simulate


class _Leak(Effect):
    """DWS eta of MOSA 13 leaking into link 23, undelayed: not a named effect."""

    name = "test-leak"
    parameters = {}

    def columns(self, data):
        return [Column("test-leak.k", [Part("23", data.witness("13", "eta"))], "m/rad", 1e-3)]


def test_injected_path_is_the_top_witness():
    inj = _Leak().injection({"test-leak.k": 6e-3})
    tm, _ = simulate(SimulationConfig(duration=2 * 3600.0, orbit="keplerian", seed=8, injections=(inj,)))
    dg = whiten_telemetry(tm)
    model = fit_model(dg, ["linear-ttl"], time_table=False)
    w = witness_search(tm, dg, model)
    assert w["n_witnesses"] > 500  # 6 x 2 channels x (6 links x 5 placements + time + steps) + products
    assert w["overall"][0]["name"] == "dws 13.eta on 23", w["overall"][:3]
    # it explains far more than a witness unrelated to the residual (about one per band)
    assert w["overall"][0]["delta_chi2"] > 100
    # per band: top in the bands where the leak dominates the excess (high frequencies)
    assert w["bands"][-1]["top"][0]["name"] == "dws 13.eta on 23"
    assert 0 < w["bands"][-1]["top"][0]["coherence"] <= 1
    curves = w["coherence_spectra"]["curves"]
    assert "dws 13.eta on 23" in curves
    vals = np.array([v for v in curves["dws 13.eta on 23"] if v is not None])
    assert np.all((vals >= 0) & (vals <= 1 + 1e-9))


def test_no_witness_stands_out_without_an_effect():
    tm, _ = simulate(SimulationConfig(duration=2 * 3600.0, orbit="keplerian", seed=9))
    dg = whiten_telemetry(tm)
    model = fit_model(dg, ["linear-ttl"], time_table=False)
    w = witness_search(tm, dg, model)
    # delta chi2 of an unrelated witness is chi^2_1-like per band: the largest of ~4000
    # (540 witnesses x bands, correlated) stays below ~25 (p ~ 6e-7 each)
    best = max(t["delta_chi2"] for b in w["bands"] for t in b["top"])
    assert best < 25, w["overall"][:3]


def test_every_library_witness_is_an_effect_spelled_as_the_report_prints_it():
    # the report prints each witness's spec (witness_spec); --effects parses it back into
    # one column of the witness effect, whatever the channel, link, delay or derivative
    from ttlcore.conventions import ANGLES, LINKS, MOSAS
    from ttlcore.diagnose.witnesses import witness_spec
    from ttlcore.effects import make_effects, split_effects

    specs = [
        witness_spec(f"{m}.{a}", link, n, d)
        for m in MOSAS
        for a in ANGLES
        for link in LINKS
        for n in (0, 1, 2)
        for d in (False, True)
        if not (d and n == 2)
    ]
    specs += [
        witness_spec(f"{m}.{p}", link, n)
        for m in MOSAS
        for p in ("phiphi", "etaeta", "phieta")
        for link, n in ((m, 0), (m[::-1], 1))
    ]
    for spec in specs:
        (effect,) = make_effects(split_effects(spec))
        assert effect.cli_spec() == spec
        assert len(effect.column_names()) == 1


def test_step_witnesses_transform_only_the_segments_their_step_falls_in(monkeypatch):
    # a step witness H(t - t_s) w equals w's own spectra after t_s and zero before: only the
    # segment(s) t_s falls in are transformed, and the library's spectra are those of the
    # switched series transformed whole
    import ttlcore.diagnose.witnesses as witnesses

    tm, _ = simulate(SimulationConfig(duration=2 * 3600.0, orbit="keplerian", seed=9))
    dg = whiten_telemetry(tm)
    calls = []
    fft = witnesses.segment_fft

    def counted(*args, **kwargs):
        calls.append(1)
        return fft(*args, **kwargs)

    monkeypatch.setattr(witnesses, "segment_fft", counted)
    _, raw = witnesses.witness_library(tm, dg)
    monkeypatch.setattr(witnesses, "segment_fft", fft)
    S = len(dg.grid.seg_t0)
    steps = [k for k in raw if k.startswith("step ")]
    assert len(steps) == 12 * (2 * S - 1)
    # 42 whole series (12 channels, their time witnesses and 18 products) of S segments each,
    # and at most two segments per step (not S: 126 x S transforms before)
    assert len(calls) <= (len(raw) - len(steps)) * S + 2 * len(steps) < len(raw) * S
    t = tm.t0 + np.arange(tm.size) / tm.fs
    whole = witnesses._spectra_on_segments(tm, dg, t)
    g = dg.grid
    for ts in [*g.seg_t0[1:], *(t0 + g.seg_duration / 2 for t0 in g.seg_t0)]:
        for m, a in (("12", "phi"), ("31", "eta")):
            vel = np.nan_to_num(np.asarray(tm.dws_phi if a == "phi" else tm.dws_eta))
            w = -vel[witnesses.MOSAS.index(m)] / witnesses.C
            np.testing.assert_array_equal(raw[f"step {ts:.0f} {m}.{a}"], whole((t >= ts) * w))

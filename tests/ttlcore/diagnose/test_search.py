"""The exact refinement of a filter's search and when it is skipped
(ttlcore.diagnose.search._refine_exact, REFINE_MARGIN).

The search of a coupling's poles locates the optimum with fast products over frequency
bins, then refines it with the columns the fit uses (the witness filtered in time: 0.15 s a
point for a day).  That refinement is skipped for a candidate whose exact evidence at the
fast optimum is far below significance: here the refinement's own worth is measured on a
coupled witness and an uncoupled one (the blind plugin injects the coupling, its own FFT
filter: tests/ttlcore/diagnose/blind_effects.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ttlcore.diagnose import search
from ttlcore.diagnose.candidates import score
from ttlcore.diagnose.fitting import fit_model
from ttlcore.diagnose.settings import DiagnoseSettings
from ttlcore.diagnose.whitened import whiten_telemetry
from ttlcore.effects import injection_from_spec, make_effects
from ttlcore.sim.simulator import SimulationConfig, simulate

BLIND = str(Path(__file__).with_name("blind_effects.py"))
FC_TRUE = 0.05  # Hz
COUPLED = "source=13.eta,link=31,delay=1"


def _peak(x):
    """A profile with its peak at (0.3, -0.2): delta chi^2 40 there, log B = delta chi^2 / 2 - 10."""
    d = 40.0 - 1e3 * ((x[0] - 0.3) ** 2 + (x[1] + 0.2) ** 2)
    return d, d / 2 - 10.0


def test_the_refinement_finds_the_exact_peak_unless_it_is_below_the_floor():
    lo, hi, start = np.array([-1.0, -1.0]), np.array([1.0, 1.0]), np.array([0.31, -0.21])
    calls = []

    def exact(x):
        calls.append(tuple(x))
        return _peak(x)

    x, dchi2, lbf, n = search._refine_exact(exact, start, lo, hi)
    assert np.allclose(x, [0.3, -0.2], atol=2e-3) and dchi2 == pytest.approx(40.0, abs=0.05), (x, dchi2)
    assert n == len(set(calls)) > 10 and lbf == pytest.approx(dchi2 / 2 - 10.0)
    calls.clear()
    # the start's log B is 39.8 / 2 - 10 = 9.9: not worth refining below 10
    x, dchi2, lbf, n = search._refine_exact(exact, start, lo, hi, worth=lambda x, lbf: lbf >= 10.0)
    assert n == 1 and len(calls) == 1 and np.array_equal(x, start)
    assert (dchi2, lbf) == _peak(start)


@pytest.fixture(scope="module")
def coupled_model():
    inj = injection_from_spec(f"blind-lowpass:{COUPLED},fc={FC_TRUE},gain=8e-3", (BLIND,))
    config = SimulationConfig(duration=6 * 3600.0, orbit="keplerian", seed=43, injections=(inj,))
    tm, _ = simulate(config, chunk_size=10**7)  # the blind filter takes one chunk
    data = whiten_telemetry(tm, DiagnoseSettings())
    return fit_model(data, make_effects(["linear-ttl"]))


def _searched(model, spec: str, monkeypatch) -> tuple[dict, int]:
    """The candidate ``spec`` scored against ``model``: its search's JSON and log B, and how
    many exact evaluations it took."""
    n = [0]
    evaluate = search._Spectral.evaluate

    def counted(self, cols, idx, exact=False):
        n[0] += bool(exact)
        return evaluate(self, cols, idx, exact)

    monkeypatch.setattr(search._Spectral, "evaluate", counted)
    ev, extra = score(model, make_effects([spec])[0], model.ttl_coefficients())
    return {"lbf_best": extra["log_bayes_factor_at_best"], "lbf": ev.log_bayes_factor, **extra["search"]}, n[0]


def test_a_coupled_witness_is_refined_and_an_uncoupled_one_is_not(coupled_model, monkeypatch):
    threshold = coupled_model.data.context.settings.log_bf_threshold
    found, n = _searched(coupled_model, f"fd-coupling:{COUPLED},filter=pole1", monkeypatch)
    assert n > 1 and found["lbf_best"] > threshold
    # the corner of 6 h of a coupling 8e-3 strong (test_reshape.py: 0.0505 Hz on seed 41)
    assert found["estimates"]["fc"] == pytest.approx(FC_TRUE, rel=0.1)
    # a resonance on a witness of another spacecraft, not coupled: the marginal log B at the
    # fast optimum is far below the threshold, and refining it does not make it significant
    uncoupled = "fd-coupling:source=21.phi,link=12"
    skipped, n = _searched(coupled_model, uncoupled, monkeypatch)
    margin = search.REFINE_MARGIN
    assert n == 1 and skipped["lbf"] < threshold - margin, skipped
    monkeypatch.setattr(search, "REFINE_MARGIN", np.inf)  # always refined
    refined, n = _searched(coupled_model, uncoupled, monkeypatch)
    assert n > 1 and refined["lbf"] < threshold, refined
    # what the refinement is worth there (measured: log B at the optimum -12.5 -> -5.5 at
    # q = 300, the marginal -12.5 -> -14.3): inside the margin
    assert refined["lbf"] - skipped["lbf"] < margin and refined["lbf_best"] - skipped["lbf_best"] < margin


def test_an_insignificant_step_time_is_not_refined_below_the_coarse_grid(coupled_model):
    # no step in these data: the coarse grid's marginal log B (the candidate's evidence) is
    # below the threshold, and a candidate's search stops there - with the same evidence
    from ttlcore.diagnose.step_search import step_time_search
    from ttlcore.effects.step import Step

    threshold = coupled_model.data.context.settings.log_bf_threshold
    refined = step_time_search(coupled_model, Step())
    screened = step_time_search(coupled_model, Step(), screen=True)
    assert screened.log_bayes_factor == refined.log_bayes_factor < threshold
    assert screened.n_evaluations < refined.n_evaluations / 2, (screened.n_evaluations, refined.n_evaluations)
    # the coarse grid's best time: the refinement searches within a coarse step of it (and
    # the echoes four light travel times, ~35 s, further)
    step = coupled_model.data.context.settings.step_grid
    assert abs(screened.estimates["t_step"] - refined.estimates["t_step"]) <= step + 60.0


@pytest.mark.parametrize(
    "spec", [f"fd-coupling:{COUPLED},f0=0.04,q=3", "fd-coupling:source=21.phi,link=12,filter=pole1,fc=0.3,vary=drift"]
)
def test_the_fast_products_are_the_evidence_of_the_columns_filtered_bin_by_bin(coupled_model, spec):
    # the search's fast path (_Spectral.evaluate) sums per-bin products of each base column
    # once for all its filters; the reference here builds each filtered column on the bins
    # (the base's whitened spectra times the response, its readout noise likewise, as
    # columns.filtered_columns does) and takes the evidence of adding them to the model
    # (evidence.added_evidence).  Equal but for the order of the sums: 1e-9 relative.
    from ttlcore.diagnose.columns import ColumnSet, base_column
    from ttlcore.diagnose.evidence import added_evidence
    from ttlcore.effects.column_tdi import effect_input_from_telemetry
    from ttlcore.effects.columns import names_only_input

    model = coupled_model
    data = model.data
    effect = make_effects([spec])[0]
    cols = effect.columns(effect_input_from_telemetry(data.context.tm))
    sp = search._Spectral(model, cols)
    idx = [sp.base_names.index(base_column(data, c).names[0]) for c in cols]
    assert len(cols) > 1 and len(set(idx)) < len(idx)  # the columns share bases
    fast = sp.evaluate(effect.columns(names_only_input()), idx)
    x, eiv = [], []
    for c in cols:
        base = base_column(data, c)
        resp = np.asarray(c.response(data.grid.f), complex)
        x.append(base.w[..., 0] * resp[None, :, None])
        eiv.append(tuple((ch, link, extra, resp) for ch, link, extra, *_ in base.eiv[0]))
    cs = ColumnSet(
        tuple(c.name for c in cols),
        np.stack(x).view(np.float64),
        data.noise.key,
        tuple(c.unit for c in cols),
        tuple(c.prior_scale for c in cols),
        tuple(eiv),
        tuple(base_column(data, c).modulation[0] for c in cols),
    )
    ref = added_evidence(model, cs)
    assert fast[0] == pytest.approx(ref.delta_chi2, rel=1e-9, abs=1e-6), (fast, ref)
    assert fast[1] == pytest.approx(ref.log_bayes_factor, rel=1e-9, abs=1e-6), (fast, ref)

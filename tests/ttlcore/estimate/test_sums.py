"""The per-band sums of the GLS fit (ttlcore.estimate.sums): the batched per-segment sums and
the errors-in-variables term taken once per set of weights give the numbers of one plain
product per band and segment (the definition), to rounding."""

import numpy as np

from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.estimate.fit import (
    FitSettings,
    SegmentSpectra,
    accumulate,
    default_band_edges,
    eiv_responses,
    fit_spectra,
    model_csd,
    score_matrix,
)
from ttlcore.estimate.whitening import inverse_csd, whitener

LTT = np.full(6, 8.3)


def _spectra(n_seg=4, seed=5):
    rng = np.random.default_rng(seed)
    f = np.arange(20, 3240) / 3600.0
    P = len(COEFFICIENT_NAMES)
    out = []
    for s in range(n_seg):
        R = rng.standard_normal((f.size, 3, P)) + 1j * rng.standard_normal((f.size, 3, P))
        C = rng.standard_normal(P)
        d = R @ C + 0.3 * (rng.standard_normal((f.size, 3)) + 1j * rng.standard_normal((f.size, 3)))
        out.append(SegmentSpectra(3600.0 * s, 3600.0, f, d, R))
    return out


def _by_definition(sp, W, edges, T, dws_psd):
    """N, b, dd, E per band of one segment: one complex product per band, as defined."""
    L = np.linalg.cholesky(W)
    Lh = np.conj(np.swapaxes(L, -1, -2))
    wd, wR = np.einsum("mij,mj->mi", Lh, sp.d), np.einsum("mij,mjp->mip", Lh, sp.R)
    G, P = len(edges) - 1, sp.R.shape[-1]
    N, b, dd, E = np.zeros((G, P, P)), np.zeros((G, P)), np.zeros(G), np.zeros((G, P, P))
    band = np.clip(np.searchsorted(edges, sp.f, side="right") - 1, 0, G - 1)
    for g in range(G):
        sel = band == g
        z, y = wR[sel].reshape(-1, P), wd[sel].reshape(-1)
        N[g], b[g], dd[g] = np.real(z.conj().T @ z), np.real(z.conj().T @ y), np.real(np.vdot(y, y))
        for idx, Tk in T:
            wT = np.einsum("mij,mjq->miq", Lh[sel], Tk[sel]) * np.sqrt(dws_psd[sel])[:, None, None]
            z = wT.reshape(-1, len(idx))
            E[g][np.ix_(idx, idx)] += np.real(z.conj().T @ z)
    return N, b, dd, E


def test_accumulate_with_the_eiv_term_taken_once_equals_the_definition():
    spectra = _spectra(n_seg=3)
    f = spectra[0].f
    W = inverse_csd(model_csd(f, LTT))
    edges = default_band_edges()
    T = eiv_responses(f, LTT, COEFFICIENT_NAMES)
    dws_psd = (2 * np.pi * f * 2e-10) ** 2
    prepared = whitener(W, T, dws_psd)
    for sp in spectra:  # summed one by one with the same weights: the term kept on `prepared`
        neq = accumulate([sp], W, edges, COEFFICIENT_NAMES, prepared=prepared)
        N, b, dd, E = _by_definition(sp, W, edges, T, dws_psd)
        assert np.allclose(neq.N, N, rtol=1e-12, atol=1e-12 * np.abs(N).max())
        assert np.allclose(neq.b, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
        assert np.allclose(neq.dd, dd, rtol=1e-12)
        assert np.abs(E).max() > 0
        assert np.allclose(neq.E, E, rtol=1e-12, atol=1e-12 * np.abs(E).max())
    assert len(prepared.cache) == 1
    # the stack at once: the sum of the segments, E counted once per segment
    total = accumulate(spectra, W, edges, COEFFICIENT_NAMES, T, dws_psd)
    assert np.allclose(total.E, 3 * E, rtol=1e-12, atol=1e-12 * np.abs(E).max())


def test_per_segment_sums_of_a_fit_equal_each_segment_summed_alone():
    spectra = _spectra()
    s = FitSettings(segment_duration=3600.0, dws_asd=2e-10)
    res, internals = fit_spectra(spectra, LTT, s, COEFFICIENT_NAMES, per_segment=True)
    sums = internals["segment_sums"]
    assert len(sums) == len(spectra)
    keep = internals["notch"]
    W, kept = internals["weights"], internals["whitener"]
    for sp, (neq, M) in zip(spectra, sums):
        sp = SegmentSpectra(sp.t0, sp.duration, sp.f[keep], sp.d[keep], sp.R[keep])
        alone = accumulate(
            [sp], W, internals["band_edges"], COEFFICIENT_NAMES, internals["eiv_response"], internals["dws_psd"]
        )
        for a, b in ((neq.N, alone.N), (neq.b, alone.b), (neq.dd, alone.dd), (neq.E, alone.E)):
            assert np.allclose(a, b, rtol=1e-11, atol=1e-11 * np.abs(b).max())
        assert np.array_equal(neq.nbins, alone.nbins)
        M_alone = score_matrix([sp], W, res.coefficients, Lh=kept.Lh)
        assert np.allclose(M, M_alone, rtol=1e-10, atol=1e-10 * np.abs(M_alone).max())
    # they add up to the window's sums
    summed = sums[0][0]
    for neq, _ in sums[1:]:
        summed = summed + neq
    window = internals["normal_equations"]
    assert np.allclose(summed.N, window.N, rtol=1e-11, atol=1e-11 * np.abs(window.N).max())
    assert np.allclose(summed.E, window.E, rtol=1e-11, atol=1e-11 * np.abs(window.E).max())

"""A noise model of A, E, T with a few physical parameters, fitted by maximum Whittle likelihood.

The fixed instrument noise model (:func:`ttlcore.diagnose.adequacy.instrument_noise_csd`) pushes the
paper's secondary-noise levels (paper appendix, "Jitters and noises used in our analysis")
through the TDI responses.  Outside data (lisainstrument, the mission) need not have exactly
those levels nor their exact structure, and a 5 % error of the noise level is then the whole
tolerance of the adequacy test.  Here the secondary-noise CSD is a sum of a few physical
components, each the CSD of an independent noise of fixed spectral shape pushed through the
exact TDI responses of static (mean) arms (:func:`ttlcore.tdi.combinations.link_responses`), times a free
PSD scale factor ``a_k`` (1 = the paper's level):

    S(f; a) = sum_k a_k B_k(f) + S_dws(f),

- ``oms.ij`` (six parameters, one per link): the readout-type noises of ``eta_ij``
  (science-interferometer readout, backlink, telescope; shape of
  :func:`ttlcore.sim.noise_models.secondary_single_link`), entering link ``ij`` only,
  ``B = h_ij h_ij^H S_oms``;
- ``tm.ij`` (six, one per test mass): the acceleration noise of the test mass of MOSA
  ``ij``, entering ``eta_ij`` directly and ``eta_ji`` delayed by ``D_ji``,
  ``B = g g^H S_acc`` with ``g = h_ij + h_ji exp(-2 pi i f tau_ji)`` (docs/physics.md,
  test-mass noise in TDI);
- ``local`` (one): a readout noise with the OMS spectral shape but the test-mass placement
  (``g`` above): the test-mass and reference interferometers' readout noise, which the
  intermediate variables carry into ``eta_ij`` and, delayed, ``eta_ji`` (the placement the
  per-link OMS term of the paper's analytic PSD ignores; 0 in the fixed model); this is the
  term that moves T against A and E at low frequency.

``h_ij`` is the response of A, E, T to link ``ij``.  ``S_dws`` is the DWS readout noise
through the fitted TTL coefficients (held fixed here: the linear fit determines it).  Every
``B_k`` is regularised as :func:`ttlcore.estimate.fit.model_csd` does (a 1 % floor on the smoothed
diagonal), so that with every ``a_k = 1`` (``local`` = 0) the model *is* the fixed one.

The parameters are fitted to the residual spectra of a linear model by maximum Whittle
likelihood over all segments and bins at once (never bin by bin):

    -log L(a) = sum_f [ n_s log det S(f; a) + tr(S^-1(f; a) P(f)) ],   P = sum_s r_s r_s^H,

with a bounded quasi-Newton search (levels stay positive) on the score
``g_k = sum_f n_s tr(S^-1 B_k) - tr(S^-1 B_k S^-1 P)`` and Fisher matrix
``F_kl = n_s sum_f tr(S^-1 B_k S^-1 B_l)``.  Neighbouring bins of a tapered segment are
correlated, so the covariance of ``a`` is ``kappa F^-1`` (``kappa`` of
:func:`ttlcore.estimate.fit.variance_factor`).  :func:`profile_noise_model` alternates this with the
linear fit of the diagnosis (:func:`ttlcore.diagnose.fitting.fit_model`) until the levels move by
less than a tenth of their sigma.  The fitted parameters count against the degrees of freedom of the
adequacy test like the linear ones.

Why it cannot absorb a missing effect: every component has a fixed broadband spectral shape
and a fixed A/E/T structure set by the TDI responses, and only an overall level is free.
An unmodelled effect is narrower in frequency, or has another channel structure, so
the levels that best describe the whole band leave it as excess in its own bands (tested
with injected effects).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy import optimize

from ..conventions import LINKS, displacement_to_ffd_asd
from ..estimate.gls import inverse
from ..estimate.spectra import smooth_csd
from ..sim import noise_models
from ..tdi.combinations import AET_MATRIX, MICHELSON, link_responses
from .fitting import fit_model
from .outliers import bin_runs, narrowband_excess, outlying_segments, residual_periodogram

log = logging.getLogger(__name__)

#: Parameter names of the default parameterisation, in order.
PARAMETERS: tuple[str, ...] = ("oms", "tm_acc", "tm_rise", "floor")
#: A finer parameterisation: one OMS level per link.
PER_LINK: tuple[str, ...] = tuple(f"oms.{k}" for k in LINKS) + ("tm_acc", "tm_rise", "floor")
#: Fixed-model values: the paper's levels, the floor of :func:`ttlcore.estimate.fit.regularise`.
NOMINAL: dict = {"oms": 1.0, "tm": 1.0, "tm_acc": 1.0, "tm_rise": 1.0, "local": 0.0, "floor": 1e-2}
#: Half-width [bins] of the smoothing of the floor's shape (as :func:`ttlcore.estimate.fit.regularise`).
FLOOR_HALF_WIDTH = 10
#: Lower bound of a PSD scale factor during the fit (levels stay positive).
MIN_LEVEL = 1e-5
#: Allowed range of each component's PSD scale: the prior knowledge of the instrument's
#: noise levels.  The readout (OMS) level is bounded tightly (+-5 % in PSD, 2.5 % in ASD):
#: a TTL-type residual (a drift, a step, a wrong coupling) has nearly the OMS shape and
#: TDI structure (DWS in velocity, like OMS in fractional frequency, both ~f), so only
#: this knowledge keeps the level from absorbing it (measured: a drift giving chi2/dof 13
#: under the fixed model pulls a free OMS level to 14.4).  The test-mass levels, which act
#: below ~10 mHz only, and the floor may move more.
BOUNDS: dict = {
    "oms": (0.95, 1.05),
    "tm_acc": (0.25, 4.0),
    "tm_rise": (MIN_LEVEL, 4.0),
    "local": (MIN_LEVEL, 1.0),
    "floor": (MIN_LEVEL, 0.02),
}


def local_readout_psd(f) -> np.ndarray:
    """Unit PSD [1/Hz] of the ``local`` component: the OMS-type displacement ASD of one
    ``eta`` variable (:data:`ttlcore.sim.noise_models.OMS_LINK`, 2 mHz corner) in fractional
    frequency."""
    f = np.asarray(f, dtype=float)
    return displacement_to_ffd_asd(noise_models.oms_displacement(f, noise_models.OMS_LINK), f) ** 2


def basis_csds(f, ltt_mean, names=PARAMETERS) -> np.ndarray:
    """The components ``B_k(f)`` of the module docstring, shape (K, m, 3, 3) (A, E, T), each
    regularised like :func:`ttlcore.estimate.fit.model_csd`.

    Parameters
    ----------
    f : ndarray (m,)
        Frequencies [Hz].
    ltt_mean : array_like (6,)
        Mean light travel times [s], LINKS order.
    names : sequence of str
        Components (``oms.ij``, ``tm.ij``, ``local``, or ``oms``/``tm`` for all links at once).
    """
    f = np.asarray(f, dtype=float)
    ltt = np.asarray(ltt_mean, dtype=float)
    s_oms, s_acc = noise_models.secondary_single_link(f)
    h = np.stack([link_responses(c, f, ltt) for c in MICHELSON])  # (3 XYZ, 6 links, m)
    h = np.einsum("ia,alm->lmi", AET_MATRIX, h)  # (6 links, m, 3 AET)
    rev = [LINKS.index(k[::-1]) for k in LINKS]
    g = np.stack([h[k] + h[rev[k]] * np.exp(-2j * np.pi * f * ltt[rev[k]])[:, None] for k in range(6)])
    oms = np.einsum("lmi,lmj->lmij", h, h.conj()) * s_oms[None, :, None, None]
    tmass = np.einsum("lmi,lmj->lmij", g, g.conj())
    acc = tmass * s_acc[None, :, None, None]
    # the test-mass PSD split into its acceleration part and its high-frequency rise
    # ``(f / 8 mHz)^4`` (noise_models.test_mass): two shapes, one level each
    rise = (f / noise_models.TM_FBREAK) ** 4
    acc_lo = acc / (1 + rise)[None, :, None, None]
    acc_hi = acc - acc_lo
    loc = tmass.sum(axis=0) * local_readout_psd(f)[:, None, None]
    nominal_diag = np.real(np.einsum("mii->mi", oms.sum(axis=0) + acc.sum(axis=0)))
    floor = np.zeros((f.size, 3, 3), dtype=complex)
    idx = np.arange(3)
    floor[:, idx, idx] = smooth_csd(nominal_diag[:, :, None], FLOOR_HALF_WIDTH)[:, :, 0]
    out = []
    for n in names:
        kind, _, link = n.partition(".")
        if kind == "oms":
            b = oms[LINKS.index(link)] if link else oms.sum(axis=0)
        elif kind == "tm":
            b = acc[LINKS.index(link)] if link else acc.sum(axis=0)
        elif kind in ("tm_acc", "tm_rise"):
            src = acc_lo if kind == "tm_acc" else acc_hi
            b = src[LINKS.index(link)] if link else src.sum(axis=0)
        elif kind == "local":
            b = loc
        elif kind == "floor":
            b = floor
        else:
            raise ValueError(f"unknown noise-model component {n!r}; known: oms[.ij], tm[.ij], local, floor")
        out.append(b)
    return np.stack(out)


@functools.lru_cache(maxsize=4)  # a run's few grids (a day's: ~10 MB each)
def basis_on_grid(f_bytes: bytes, ltt_mean: tuple[float, ...], names: tuple[str, ...]) -> np.ndarray:
    """:func:`basis_csds` on the frequencies ``np.frombuffer(f_bytes)`` [Hz], read-only, cached."""
    b = basis_csds(np.frombuffer(f_bytes, dtype=float), ltt_mean, names)
    b.flags.writeable = False
    return b


@dataclass(frozen=True)
class NoiseModel:
    """Secondary-noise model of A, E, T with fitted PSD scale factors (module docstring).

    Attributes
    ----------
    ltt_mean : tuple
        Mean light travel times [s] (six, LINKS order).
    names : tuple of str
        Components.
    levels : tuple of float
        PSD scale factors (1 = the paper's level; ``local`` in units of one ``eta``'s OMS).
    covariance : tuple of tuple, or None
        Covariance of ``levels`` (``kappa F^-1``), None for a model that was not fitted.
    log_likelihood : float or None
        Whittle log-likelihood at ``levels`` (up to a constant).
    n_segments, n_bins : int
        Segments and bins the fit used.
    iterations, converged : int, bool
        Of the likelihood maximisation.
    at_bound : tuple of str
        Components whose level stopped at a bound of its allowed range (:data:`BOUNDS`): the
        data ask for more (or less) noise of that shape than the instrument is known to have.
    """

    ltt_mean: tuple[float, ...]
    names: tuple[str, ...] = PARAMETERS
    levels: tuple[float, ...] = tuple(NOMINAL[p.split(".")[0]] for p in PARAMETERS)
    covariance: tuple[tuple[float, ...], ...] | None = None
    log_likelihood: float | None = None
    n_segments: int = 0
    n_bins: int = 0
    iterations: int = 0
    converged: bool = True
    at_bound: tuple[str, ...] = ()
    #: start times [s] of the segments left out of the fit as outliers (:func:`outlying_segments`)
    excluded_segments: tuple[float, ...] = ()
    #: analysis bins [Hz] left out of the fit as narrowband excess (:func:`narrowband_excess`),
    #: as ``((f_lo, f_hi), ...)`` runs
    excluded_bands: tuple[tuple[float, float], ...] = ()

    @classmethod
    def nominal(cls, ltt_mean, names=PARAMETERS) -> NoiseModel:
        """The fixed model (the paper's levels) in this parameterisation."""
        return cls(tuple(map(float, ltt_mean)), tuple(names), tuple(NOMINAL[n.split(".")[0]] for n in names))

    @property
    def n_parameters(self) -> int:
        return len(self.names)

    @property
    def sigma(self) -> np.ndarray:
        """Fisher standard deviations of the levels (NaN if not fitted)."""
        if self.covariance is None:
            return np.full(len(self.names), np.nan)
        return np.sqrt(np.diag(np.asarray(self.covariance)))

    def basis(self, f) -> np.ndarray:
        """:func:`basis_csds` on ``f`` (read-only; computed once per grid, :func:`basis_on_grid`)."""
        return basis_on_grid(np.ascontiguousarray(f, dtype=float).tobytes(), self.ltt_mean, self.names)

    def csd(self, f) -> np.ndarray:
        """Secondary-noise CSD (m, 3, 3) of A, E, T [1/Hz] (without the DWS term)."""
        return np.einsum("k,kmij->mij", np.asarray(self.levels, dtype=float), self.basis(f))

    def to_json(self) -> dict:
        sig = self.sigma
        return {
            "parameters": {
                n: {"psd_scale": float(v), "sigma": float(s) if np.isfinite(s) else None}
                for n, v, s in zip(self.names, self.levels, sig)
            },
            "n_parameters": self.n_parameters,
            "log_likelihood": self.log_likelihood,
            "iterations": self.iterations,
            "converged": self.converged,
            "at_bound": list(self.at_bound),
            "excluded_segments": [float(t) for t in self.excluded_segments],
            "excluded_bands": [[float(a), float(b)] for a, b in self.excluded_bands],
            "bounds": {n: list(BOUNDS[n.split(".")[0]]) for n in self.names},
        }


def whittle_terms(levels, B, P, n_segments, fixed=None):
    """-log L, score and Fisher matrix of the module docstring at ``levels``.

    Parameters
    ----------
    levels : ndarray (K,)
    B : ndarray (K, m, 3, 3)
        Components.
    P : ndarray (m, 3, 3)
        Sum over segments of the residual outer products ``r r^H``.
    n_segments : int
    fixed : ndarray (m, 3, 3), optional
        A fixed additive term (the DWS noise).
    """
    S = np.einsum("k,kmij->mij", levels, B)
    if fixed is not None:
        S = S + fixed
    Si = np.linalg.inv(S)
    SiB = np.einsum("mij,kmjl->kmil", Si, B)  # (K, m, 3, 3)
    SiP = Si @ P
    _, logdet = np.linalg.slogdet(S)
    nll = float(np.sum(n_segments * logdet + np.real(np.einsum("mii->m", SiP))))
    tr_SiB = np.real(np.einsum("kmii->k", SiB))
    tr_SiBSiP = np.real(np.einsum("kmij,mji->k", SiB, SiP))
    grad = n_segments * tr_SiB - tr_SiBSiP
    F = n_segments * np.real(np.einsum("kmij,lmji->kl", SiB, SiB))
    return nll, grad, F


#: a noise-model fit whose levels are this close to the optimum (in their sigmas) has
#: converged, whatever its optimiser says (:func:`newton_distance`)
NEWTON_TOL_SIGMA = 0.05


def newton_distance(levels, grad, F, limits) -> float:
    """Largest ``|delta_k| / sigma_k`` of the Newton step ``delta = -F^-1 g`` over the levels
    not held at a bound (a level at its bound with the score pushing outward stays there),
    with ``sigma_k = sqrt((F^-1)_kk)``: how far, in its own sigmas, the likelihood's maximum
    still is."""
    levels, grad = np.asarray(levels, dtype=float), np.asarray(grad, dtype=float)
    held = np.array(
        [
            (hi is not None and v >= hi * (1 - 1e-6) and g < 0) or (v <= lo * (1 + 1e-6) and g > 0)
            for v, g, (lo, hi) in zip(levels, grad, limits)
        ],
        dtype=bool,
    )
    free = ~held
    if not free.any():
        return 0.0
    Ff = np.asarray(F, dtype=float)[np.ix_(free, free)]
    try:
        cov = np.linalg.inv(Ff)
    except np.linalg.LinAlgError:
        return float("inf")
    step = cov @ grad[free]
    sig = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    return float(np.max(np.abs(step) / sig))


def fit_noise_model(
    f,
    P,
    n_segments,
    ltt_mean,
    *,
    names=PARAMETERS,
    fixed=None,
    start=None,
    kappa: float = 1.0,
    max_iter: int = 200,
    tol: float = 1e-4,
    bounded: bool = True,
    keep=None,
) -> NoiseModel:
    """Maximum Whittle likelihood levels of the components for residual spectra.

    Parameters
    ----------
    f : ndarray (m,)
        Frequencies [Hz] (the analysis bins: notches and band already applied).
    P : ndarray (m, 3, 3)
        ``sum_s r_s r_s^H`` of the residual A, E, T spectra of the ``n_segments`` segments,
        normalised so that ``E[r r^H]`` is the one-sided CSD.
    n_segments : int
    ltt_mean : array_like (6,)
        Mean light travel times [s].
    names : sequence of str
        Components (default :data:`PARAMETERS`).
    fixed : ndarray (m, 3, 3), optional
        Fixed additive CSD (the DWS readout noise through the fitted coefficients).
    start : NoiseModel, optional
        Starting levels (default: nominal).
    kappa : float
        Variance factor of the tapered segments (scales the covariance).
    bounded : bool
        Keep each level within its :data:`BOUNDS` (default); False: only positive.
    keep : ndarray (m,) of bool, optional
        The bins the likelihood sums over (default all): the components are computed on
        all of ``f`` (their smoothing spans neighbouring bins) and then restricted.
    max_iter, tol : int, float
        Iterations of the bounded quasi-Newton search (L-BFGS-B, analytic score, variables
        scaled by their Fisher sigmas at the start) and its tolerance on the scaled score.

    Returns
    -------
    NoiseModel
        With ``covariance = kappa F^-1`` at the optimum.
    """
    f = np.asarray(f, dtype=float)
    names = tuple(names)
    model = start if start is not None and tuple(start.names) == names else NoiseModel.nominal(ltt_mean, names)
    B = model.basis(f)
    if keep is not None:
        keep = np.asarray(keep, dtype=bool)
        B, P = B[:, keep], P[keep]
        fixed = None if fixed is None else fixed[keep]
    lim = [BOUNDS[n.split(".")[0]] if bounded else (MIN_LEVEL, None) for n in names]
    a0 = np.maximum(np.asarray(model.levels, dtype=float), 10 * MIN_LEVEL)
    a0 = np.array([np.clip(v, lo, np.inf if hi is None else hi) for v, (lo, hi) in zip(a0, lim)])
    nll0, _, F = whittle_terms(a0, B, P, n_segments, fixed)
    # scaled variables x = (a - a0) / sigma0: the problem is then near-isotropic
    scale = 1.0 / np.sqrt(np.maximum(np.diag(F), 1e-300))

    def objective(x):
        nll, g, _ = whittle_terms(a0 + scale * x, B, P, n_segments, fixed)
        return nll - nll0, g * scale

    bounds = [((lo - v) / sc, None if hi is None else (hi - v) / sc) for v, sc, (lo, hi) in zip(a0, scale, lim)]
    res = optimize.minimize(
        objective,
        np.zeros(len(a0)),
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"maxiter": max_iter, "gtol": tol, "ftol": 1e-12},
    )
    a = a0 + scale * res.x
    nll, grad, F = whittle_terms(a, B, P, n_segments, fixed)
    converged, it = bool(res.success), int(res.nit)
    if not converged:
        # L-BFGS-B stops "ABNORMAL" when its line search meets the rounding of a likelihood
        # summed over ~1e5 bins: at the optimum, not short of it.  What matters is how far
        # the levels are from the optimum in their own sigmas: the Newton step F^-1 g
        # (free levels only), with F the Fisher matrix.  Within 0.05 sigma the fit has
        # converged for every use made of it.
        distance = newton_distance(a, grad, F, lim)
        converged = distance < NEWTON_TOL_SIGMA
        if converged:
            log.debug("noise-model fit: %s after %d iterations, %.2g sigma from the optimum", res.message, it, distance)
        else:
            log.warning(
                "noise-model fit stopped after %d iterations (%s), %.2g sigma from the optimum: "
                "the noise levels are approximate",
                it,
                res.message,
                distance,
            )
    cov = kappa * inverse(F)  # a level no bin informs (every bin of its shape left out): infinite variance
    cov = 0.5 * (cov + cov.T)
    at_bound = tuple(
        n
        for n, v, (lo, hi) in zip(names, a, lim)
        if (hi is not None and v >= hi * (1 - 1e-6)) or (lo > MIN_LEVEL and v <= lo * (1 + 1e-6))
    )
    return NoiseModel(
        tuple(map(float, ltt_mean)),
        names,
        tuple(map(float, a)),
        tuple(map(tuple, cov)),
        -nll,
        int(n_segments),
        int(P.shape[0]),  # the bins the likelihood summed over
        it,
        converged,
        at_bound,
    )


def profile_noise_model(
    data, effects, *, names=PARAMETERS, passes: int = 4, first=None, robust: bool = True, time_table: bool = True
):
    """Profile the noise levels with the linear fit of a diagnosis (module docstring).

    Alternates the linear fit of ``effects`` under the current noise model and
    :func:`fit_noise_model` on its residual, until the levels move by less than a tenth of
    their sigma (at most ``passes`` times); the DWS term of the noise model stays the one
    the diagnosis derives from the fitted coefficients.  ``data`` is left as it is: the
    returned fit's ``data`` (:class:`ttlcore.diagnose.whitened.WhitenedData`) is whitened
    with the fitted model, its ``noise_parameters`` set (counted in the degrees of freedom
    of its adequacy tests).

    Parameters
    ----------
    data : WhitenedData
    effects : list of Effect
        The model whose residual is described.
    names : sequence of str
        Noise-model components (:data:`PARAMETERS`).
    passes : int
        Maximum alternations.
    first : ModelFit, optional
        The fit of ``effects`` on ``data``, if already done.
    robust : bool
        Leave the segments whose residual is an outlier against the others
        (:func:`outlying_segments`: a merger, loud glitches) out of the levels' fit, so that
        a transient changes nothing outside it (default); the levels' ``excluded_segments``
        name them.

    Returns
    -------
    (NoiseModel, ModelFit)
        The fitted noise model and the final fit of ``effects`` under it.
    """
    fitted = data.noise.parameters  # the levels the data are whitened with, if fitted
    nm = fitted if fitted is not None and fitted.names == tuple(names) else NoiseModel.nominal(data.tdi.ltt_mean, names)
    fit = first if first is not None else fit_model(data, effects, time_table=False)
    first = None  # only ``fit`` holds it: the first pass's replacement frees it
    for k in range(max(1, passes)):
        d = fit.data
        grid, noise = d.grid, d.noise
        dof = np.array([6.0 * (b - a) for a, b in grid.slices])
        out = (
            outlying_segments(fit.chi2_seg_band, dof, grid.kappa, d.context.settings.tolerance)
            if robust
            else np.zeros(len(grid.starts), dtype=bool)
        )
        P = residual_periodogram(fit.residual_w, noise.Lh, ~out)
        secondary = noise.parameters.csd(grid.f) if noise.parameters is not None else nm.csd(grid.f)
        dws = noise.csd - secondary
        n_kept = int((~out).sum())
        narrow = narrowband_excess(grid.f, P, noise.csd, n_kept, grid.kappa) if robust else np.zeros(grid.f.size, bool)
        use = ~narrow
        new = fit_noise_model(
            grid.f,
            P,
            n_kept,
            d.tdi.ltt_mean,
            names=names,
            fixed=dws,
            start=nm,
            kappa=grid.kappa,
            keep=use if narrow.any() else None,
        )
        new = replace(
            new,
            excluded_segments=tuple(float(t) for t in np.asarray(grid.seg_t0)[out]),
            excluded_bands=bin_runs(grid.f, narrow),
        )
        if narrow.any():
            log.info(
                "noise model pass %d: %d of %d bins left out as narrowband excess (%s)",
                k + 1,
                int(narrow.sum()),
                narrow.size,
                ", ".join(f"{a * 1e3:.3g}-{b * 1e3:.3g} mHz" for a, b in new.excluded_bands[:6]),
            )
        if out.any():
            log.info(
                "noise model pass %d: segments starting at %s h left out as outliers",
                k + 1,
                [round(float(t) / 3600, 2) for t in np.asarray(grid.seg_t0)[out]],
            )
        moved = np.abs(np.subtract(new.levels, nm.levels)) / np.maximum(new.sigma, 1e-300)
        nm = new
        fit = None  # the previous pass's fit is not kept while the next is made
        fit = fit_model(d.with_noise(nm.csd(grid.f) + dws, noise_parameters=nm), effects, time_table=False)
        log.info(
            "noise model pass %d: levels %s (moved %.2g sigma)",
            k + 1,
            dict(zip(nm.names, np.round(nm.levels, 4))),
            float(np.max(moved)),
        )
        if np.all(moved < 0.1):
            break
    last = fit.data
    fit = None  # nor the last pass's fit (its columns and their series) while the final one is made
    return nm, fit_model(last, effects, time_table=time_table)


def noise_model_json(model: NoiseModel | None) -> dict:
    """The ``adequacy.noise_model`` entry of a diagnosis report."""
    if model is None:
        return {
            "kind": "fixed",
            "description": "analytic secondary noises of A, E, T for the mean arms (paper appendix levels) + DWS "
            "readout noise through the fitted linear coefficients; not re-estimated from the residual",
        }
    return {
        "kind": "fitted",
        "description": "secondary-noise components of fixed shape and TDI structure with fitted levels (maximum "
        "Whittle likelihood, profiled with the linear fit; docs/diagnostics.md) + DWS readout noise "
        "through the fitted linear coefficients",
        **model.to_json(),
    }

"""A model fitted to whitened data: generalised least squares with errors in variables.

Everything here is the linear-Gaussian model of :mod:`ttlcore.estimate.fit` in the frequency
domain, A, E, T jointly, with the noise CSD held at the noise model of the
:class:`~ttlcore.diagnose.whitened.WhitenedData` - never re-estimated from the residual - so
that chi^2 values of different models are comparable and an unmodelled effect shows as
excess instead of being absorbed:

    Q(theta) = theta^T (N - E) theta - 2 theta^T b + dd,    chi2 = 2 Q,

with ``N = Re sum R^H S^-1 R``, ``b = Re sum R^H S^-1 d``, ``dd = sum d^H S^-1 d`` over the
bins of each band and segment (:func:`gram`), ``E`` the errors-in-variables term of the
columns (:func:`ttlcore.diagnose.columns.eiv`), solved by the engine every fit in ttlcore
shares (:func:`ttlcore.estimate.gls.solve`).  :func:`solve` is pure: whitened data and
columns in, a :class:`ModelFit` out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import COEFFICIENT_NAMES
from ..estimate.gls import NormalEquations, sandwich, set_apart
from ..estimate.gls import solve as gls_solve
from .adequacy import band_table
from .columns import ColumnSet, eiv, read_only

if TYPE_CHECKING:
    from ..effects.base import Effect
    from .adequacy import BandTable
    from .whitened import WhitenedData


def gram_x(XA: np.ndarray, XB: np.ndarray, slices) -> np.ndarray:
    """``Re sum conj(A) B`` per segment and band from real layouts (p, S, m, 6) and
    (q, S, m, 6) -> (S, G, p, q).

    One product per segment and band on views of the layouts: a band's bins of one segment
    are contiguous in each column, so no column is copied (a batched product over the
    segments copied each band of both layouts: a day's model with its transients, ~30
    columns, 100 MB a side, at the peak of a live diagnosis)."""
    p, S = XA.shape[:2]
    q = XB.shape[0]
    out = np.zeros((S, len(slices), p, q))
    for g, (a, b) in enumerate(slices):
        if b <= a:
            continue
        for s in range(S):
            out[s, g] = XA[:, s, a:b].reshape(p, -1) @ XB[:, s, a:b].reshape(q, -1).T
    return out


def as_real(w: np.ndarray) -> np.ndarray:
    """(S, m, 3, p) complex -> (p, S, m, 6) float (real and imaginary parts interleaved)."""
    return np.ascontiguousarray(np.moveaxis(w, -1, 0)).view(np.float64)


def gram(data, A: ColumnSet, B: ColumnSet) -> np.ndarray:
    """``N`` per segment and band (S, G, p, q) of two column sets."""
    return gram_x(A.x, B.x, data.grid.slices)


def rhs(data, A: ColumnSet) -> np.ndarray:
    """``b`` per segment and band, (S, G, p)."""
    return gram_x(A.x, data.noise.wd[None].view(np.float64), data.grid.slices)[..., 0]


def parameter_name(column: str) -> str:
    """The parameter a column's coefficient is: for the shifted TTL witnesses of
    :func:`ttlcore.diagnose.columns.shifted_columns` (``"21.phi.tx@ltt-error.12"``) the
    linear coefficient before the ``@``; any other column is its own parameter (an ``@``
    in a time-varying witness's label, ``witness.12.phi>12~cycle@2h.sin``, stays)."""
    head, sep, _ = column.partition("@")
    return head if sep and head in COEFFICIENT_NAMES else column


def total_offset(column: str, value: float, expansion: dict) -> float:
    """The parameter of a shifted-witness effect's ``<effect>.<group>.d1`` column is the
    offset beyond its expansion point (:attr:`ModelFit.expansion`): the offset is their
    sum.  Other columns: ``value``."""
    return float(value) + (float(expansion.get(column[:-3], 0.0)) if column.endswith(".d1") else 0.0)


@dataclass(frozen=True, eq=False)
class ModelFit:
    """A model fitted under the noise model of its data.

    Attributes
    ----------
    effects : tuple of Effect
        The effects, searched parameters filled in.
    columns : ColumnSet
        Its whitened columns (the 24 TTL names first when present).
    data : WhitenedData
        The data (and noise model) it was fitted on.
    theta : ndarray (P,)
        GLS estimates (column units: m/rad for TTL).
    covariance : ndarray (P, P)
        ``kappa (2 (N - E))^-1``: the model-based covariance, right where the noise model is
        (the searches' and the evidences' covariance).  The sigmas a report gives are the
        robust ones (:attr:`robust_covariance`, :attr:`robust_sigma`).
    chi2_seg_band : ndarray (S, G)
        chi^2 per segment and band against the noise model (plain ``N``: the residual's
        DWS-noise part is in the noise model).
    bands : :class:`ttlcore.diagnose.adequacy.BandTable`
    q_min : float
        ``Q`` at the optimum on the EIV-corrected likelihood (for evidences).
    residual_w : ndarray (S, m, 3)
        Whitened residual.
    normal : tuple
        Per-segment, per-band normal equations ``(N (S, G, P, P), b (S, G, P))``.
    eiv_term : ndarray (G, P, P)
        Errors-in-variables term of the columns.
    expansion : dict
        ``"effect.group" -> delta_0``: expansion points of shifted-witness effects (the
        fitted offset is ``delta_0`` plus the group's ``d1`` coefficient).
    searches : dict
        Searched nonlinear parameters of the effects: effect spec -> search JSON.
    time_table : dict or None
        Adequacy in time slices (:func:`ttlcore.diagnose.fitting.time_adequacy`).
    """

    effects: tuple[Effect, ...]
    columns: ColumnSet
    data: WhitenedData
    theta: np.ndarray
    covariance: np.ndarray
    chi2_seg_band: np.ndarray
    bands: BandTable
    q_min: float
    residual_w: np.ndarray = field(repr=False)
    normal: tuple[np.ndarray, np.ndarray] = field(repr=False)
    eiv_term: np.ndarray = field(repr=False)
    expansion: dict[str, float] = field(default_factory=dict)
    searches: dict[str, dict] = field(default_factory=dict)
    time_table: dict | None = None

    def __post_init__(self):
        read_only(self.theta, self.covariance, self.chi2_seg_band, self.residual_w, self.eiv_term, *(self.normal or ()))

    @property
    def names(self) -> tuple[str, ...]:
        return self.columns.names

    @property
    def dof_band(self) -> np.ndarray:
        return self.bands.dof

    @property
    def dd(self) -> np.ndarray:
        return self.data.noise.dd

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.abs(np.diag(self.covariance)))

    @cached_property
    def robust_covariance(self) -> np.ndarray:
        """The sandwich covariance of the estimate, honest where the noise model is not.

        ``kappa (N - E)^-1 M (N - E)^-1`` with ``M = sum_{s,f} Re(u) Re(u)^T`` over the
        bins of the bands and the segments, ``u = X^H r`` the per-bin scores of the whitened
        columns ``X`` against the whitened residual ``r`` (the robust covariance of the batch
        fit, :func:`ttlcore.estimate.fit.sandwich_covariance`, on the diagnosis' spectra).
        Where the residual is the noise model's, ``E[M] = (N - E) / 2`` and it equals
        :attr:`covariance` (measured on a lisainstrument day: 1-2 % above it); where the
        residual holds more than the model's noise in some segments or bands (the tail of a
        glitch, a noise the model lacks), it grows with that excess, as the scatter of the
        estimate does.  Columns set apart by their prior keep an infinite variance.
        """
        x, wr = self.columns.x, self.residual_w.view(np.float64)  # (P, S, m, 6), (S, m, 6)
        grid = self.data.grid
        # a segment's scores count with its own variance factor (a gated segment's bins are
        # more correlated: ``GatedGrid.seg_variance``); 1 for every segment of ungated data
        per_segment = np.sqrt(grid.segment_kappa() / grid.kappa)
        M = np.zeros((x.shape[0], x.shape[0]))
        for a, b in grid.slices:
            if b > a:
                u = np.einsum("psmc,smc->psm", x[:, :, a:b], wr[:, a:b]) * per_segment[:, None]
                M += np.einsum("psm,qsm->pq", u, u)
        N = self.normal[0].sum(axis=(0, 1)) - self.eiv_term.sum(axis=0)
        cov = self.data.grid.kappa * sandwich(set_apart(N, np.asarray(self.columns.priors)), M)
        read_only(cov)
        return cov

    @property
    def robust_sigma(self) -> np.ndarray:
        """Standard deviations of :attr:`robust_covariance` (what reports give)."""
        return np.sqrt(np.abs(np.diag(self.robust_covariance)))

    @property
    def chi2(self) -> float:
        return float(self.chi2_seg_band.sum())

    @property
    def dof(self) -> float:
        return float(self.dof_band.sum())

    @property
    def chi2_dof(self) -> float:
        return self.chi2 / self.dof

    @property
    def parameter_names(self) -> tuple:
        """The physical parameter of each column: a linear coefficient whose witness a
        shifted-witness effect moved (column ``"21.phi.tx@ltt-error.12"``) is still
        ``"21.phi.tx"``."""
        return tuple(parameter_name(n) for n in self.names)

    def ttl_coefficients(self) -> np.ndarray:
        """The 24 linear coefficients (NaN for those not in the model)."""
        return self._ttl(self.theta)

    def ttl_sigma(self) -> np.ndarray:
        """The robust sigmas of the 24 linear coefficients (NaN for those not in the model)."""
        return self._ttl(self.robust_sigma)

    def _ttl(self, values) -> np.ndarray:
        out = np.full(len(COEFFICIENT_NAMES), np.nan)
        names = self.parameter_names
        for k, n in enumerate(COEFFICIENT_NAMES):
            if n in names:
                out[k] = values[names.index(n)]
        return out

    def offsets(self) -> dict:
        """``"effect.group" -> (offset [s], sigma [s])`` of the shifted-witness effects."""
        return {
            n[:-3]: (total_offset(n, v, self.expansion), float(s))
            for n, v, s in zip(self.names, self.theta, self.robust_sigma)
            if n.endswith(".d1")
        }


def solve(data, columns: ColumnSet, effects=(), expansion=None) -> ModelFit:
    """The GLS fit of ``columns`` to ``data`` (errors in variables removed from the normal
    matrix), with its adequacy per band."""
    N = gram(data, columns, columns)  # (S, G, P, P)
    b = rhs(data, columns)
    dd = data.noise.dd
    E = eiv(data, columns)
    theta, cov = gls_solve(normal_equations(data, columns, N, b, E), prior_scale=np.asarray(columns.priors))
    cov = data.grid.kappa * cov + segment_variance(cov, N, data.grid.segment_kappa() - data.grid.kappa)
    btot = b.sum(axis=(0, 1))
    chi2_sg = 2 * (np.einsum("p,sgpq,q->sg", theta, N, theta) - 2 * b @ theta + dd)
    wr = data.noise.wd - np.tensordot(theta, columns.x.view(complex), axes=(0, 0))  # no (S, m, 3, P) copy
    n_noise = 0 if data.noise.parameters is None else data.noise.parameters.n_parameters
    s = data.context.settings
    bands = band_table(
        wr, data.grid.band_index, data.grid.edges, len(columns) + n_noise, data.grid.kappa, s.tolerance, s.alpha
    )
    q_min = float(dd.sum() - btot @ theta)
    return ModelFit(
        tuple(effects),
        columns,
        data,
        theta,
        cov,
        chi2_sg,
        bands,
        q_min,
        residual_w=wr,
        normal=(N, b),
        eiv_term=E,
        expansion=dict(expansion or {}),
    )


def segment_variance(cov: np.ndarray, N: np.ndarray, excess: np.ndarray) -> np.ndarray:
    """The variance the segments whose variance factor exceeds the grid's add to the
    model-based covariance: ``Cov (2 sum_s dk_s N_s) Cov`` with ``Cov = (2 (N - E))^-1`` the
    plain one (``cov``), ``N_s`` segment ``s``'s normal matrix summed over the bands (``N``:
    (S, G, P, P)) and ``dk_s`` its excess factor (``excess`` (S,)).  The estimate's statistic
    is ``b = sum_s b_s`` with ``Var(b_s) = kappa_s N_s / 2``; all zeros (ungated data: zero
    excess) where every ``kappa_s`` is the grid's.  Parameters without information (infinite
    variance) are left as they are."""
    P = cov.shape[0]
    if not np.any(excess):
        return np.zeros((P, P))
    live = np.isfinite(np.diag(cov))
    K = np.einsum("s,sgpq->pq", excess, N)
    out = np.zeros((P, P))
    block = np.ix_(live, live)
    out[block] = 2.0 * cov[block] @ K[block] @ cov[block]
    return 0.5 * (out + out.T)


def normal_equations(data, columns: ColumnSet, N=None, b=None, E=None) -> NormalEquations:
    """The window's :class:`~ttlcore.estimate.gls.NormalEquations` of ``columns`` (summed over
    segments, per band): what the engine solves.  ``N`` (S, G, P, P), ``b`` (S, G, P) and
    ``E`` (G, P, P) when already computed."""
    N = gram(data, columns, columns) if N is None else N
    b = rhs(data, columns) if b is None else b
    E = eiv(data, columns) if E is None else E
    nbins = np.array([(hi - lo) * N.shape[0] for lo, hi in data.grid.slices])
    return NormalEquations(
        columns.names, data.grid.edges, N.sum(axis=0), b.sum(axis=0), data.noise.dd.sum(axis=0), E, nbins
    )


def normal_solution(data, columns: ColumnSet) -> tuple[dict, dict]:
    """``(theta, sigma)`` of the GLS fit of ``columns`` (column -> value), nothing else."""
    theta, cov = gls_solve(normal_equations(data, columns), prior_scale=np.asarray(columns.priors))
    sig = np.sqrt(np.abs(np.diag(cov)) * data.grid.kappa)
    return dict(zip(columns.names, theta)), dict(zip(columns.names, sig))

"""The time offsets of the shifted-witness effects ``timing-offset`` and ``ltt-error``
searched (:func:`offset_search`): a shift is a phase of the whitened spectra, a grid of
spacing ``1 / (8 f_max)`` over ``+-shift_span`` and Brent's method, groups in turn; each
group's interval from the curvature of its profile, the marginal evidence by the Laplace
rule (:mod:`ttlcore.diagnose.search`)."""

from __future__ import annotations

import logging
import math

import numpy as np
from scipy import special
from scipy.optimize import minimize_scalar

from ..effects.shifted import OFFSET_OPTION
from ..errors import ConfigError
from .model_fit import ModelFit
from .search_result import SearchResult, search_ranges

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------
# Time offsets of the shifted-witness effects
# ---------------------------------------------------------------------------


def offset_search(model: ModelFit, effect, passes: int = 4) -> SearchResult:
    """Profile-likelihood search of the open offsets of a shifted-witness effect.

    The exact model of ``timing-offset`` and ``ltt-error`` replaces the witnesses of the
    coefficients of group ``g`` (:meth:`~ttlcore.effects.shifted._Linearised.shifted_members`) by
    the same witnesses shifted by ``s delta_g`` (``s`` =
    :attr:`~ttlcore.effects.shifted._Linearised.d1_sign`).  A shift is the phase
    ``exp(2 pi i f s delta_g)`` of the whitened spectra (TDI commutes with it up to the
    arms' rate of change, ~1e-8; the segment taper changes by ``delta / T`` ~ 1e-4), so
    the chi^2 profiled over the linear parameters ``theta`` of the model's columns,

        Q(delta) = dd - b(delta)^T [N(delta) - E]^-1 b(delta),     chi2 = 2 Q / kappa,

    is cheap to evaluate for many offsets.  Each open group's offset (option
    ``offset.<group>`` unset, :meth:`~ttlcore.effects.shifted._Linearised.open_offsets`) is
    scanned on a grid of spacing ``1 / (8 f_max)`` over its range
    (:func:`search_ranges`: ``+-settings.shift_span``) with the other groups held, the best
    point refined by bounded Brent minimisation; groups are visited in turn (coordinate
    descent) until no offset moves by more than 1 ms, at most ``passes`` rounds.  Groups
    whose offset is given are held at it.

    Then, per open group with the others held at their estimates (one group at a time: a
    conditional interval, which the groups' weak correlation makes close to the marginal
    one), the 1-sigma interval from the curvature of the profile at the optimum,
    ``sigma^2 = kappa / Q''`` (a central difference with a step of about sigma); and the
    evidence: at the optimum, ``log B = delta_chi2 / 2 - 1/2 [log det(N - E)(delta) - log
    det(N - E)(0)]`` against the open offsets at zero (the shifted model has the same
    linear parameters as the unshifted one, flat prior on them), marginalised over a
    uniform prior on each open offset's range by Laplace's rule,
    ``+ sum_g [1/2 log 2 pi + log sigma_g - log(high_g - low_g)]`` (the groups' profile
    integrated on the grid where its curvature is not positive), never above the value at
    the optimum.

    Parameters
    ----------
    model : ModelFit
        The model without the effect; its columns must hold the shifted coefficients'
        (its normal equations and errors-in-variables term are the unshifted ones).
    effect : ttlcore.effects.shifted._Linearised
        ``timing-offset``, ``ltt-error`` or a plugin with the same interface.

    Returns
    -------
    SearchResult
        ``effect`` with the open offsets set to the estimates (6 significant digits);
        ``estimates``, ``intervals``: option ``offset.<group>`` -> offset [s] at the profile
        optimum, and its 1-sigma interval; ``gains``: option -> chi^2 gain (over ``kappa``)
        of the group's offset against zero, the others at their optimum; ``delta_chi2``:
        the joint gain of the open offsets against zero; ``theta``: column -> linear
        parameter at the optimum.

    Raises ConfigError when the effect has no open offset or the model lacks the columns.
    """
    data = model.data
    grid = data.grid
    names = list(model.columns.names)
    option, members, held, searched = _offset_groups(effect, names)
    ranges = search_ranges(data, effect)
    prob = _OffsetProfiles(model, members, 2 * np.pi * grid.f * float(effect.d1_sign))
    delta = {g: held.get(g, 0.0) for g in members}
    step = 1.0 / (8.0 * grid.f[-1])
    bounds = {g: ranges[option[g]][:2] for g in searched}
    gain, theta, moved, profiles = _descend(prob, searched, bounds, delta, step, passes, grid.kappa)
    # the gains (if the last pass moved an offset) and the curvature, each group with the
    # others at their estimates
    sigma = {}
    for g in searched:
        q = prob.profile(g, delta)
        if moved >= 1e-3:
            (q0, q1), th = q(np.array([0.0, delta[g]]))
            gain[g], theta = 2.0 * (q0 - q1) / grid.kappa, th[1]
        sigma[g] = _offset_sigma(q, delta[g], grid.kappa, step)
    # the joint gain and the evidence against the open offsets at zero (the given ones held)
    dchi2, lbf_best = _joint_gain(prob, held, delta, grid.kappa)
    marg = _marginal_evidence(lbf_best, sigma, bounds, profiles, grid.kappa)
    log.debug("offset search %s: %s", effect.name, {g: round(v, 4) for g, v in delta.items()})
    est = {option[g]: float(delta[g]) for g in searched}
    found = effect.with_options(**{k: float(f"{v:.6g}") for k, v in est.items()})
    intervals = {option[g]: (delta[g] - sigma[g], delta[g] + sigma[g]) for g in searched if np.isfinite(sigma[g])}
    return SearchResult(
        found,
        est,
        intervals,
        float(dchi2),
        float(lbf_best),
        marg,
        prob.n_eval,
        gains={option[g]: float(v) for g, v in gain.items()},
        theta=dict(zip(names, theta)) if theta is not None else {},
    )


def _offset_groups(effect, names: list[str]) -> tuple[dict, dict, dict, list]:
    """The offset groups of ``effect`` against the model's column ``names``.

    Returns
    -------
    option : dict
        Group -> its option name ``offset.<group>``.
    members : dict
        Group -> the indices in ``names`` of its shifted columns (groups whose columns the
        model holds, all of them).
    held : dict
        Group -> its given offset [s] (of the groups in ``members``).
    searched : list
        The open groups in ``members``, in the effect's order.

    Raises ConfigError when the effect has no open offset or the model lacks the columns.
    """
    option = {g: f"{OFFSET_OPTION}{g}" for g in effect.shifted_members()}
    open_groups = effect.open_offsets()
    if not open_groups:
        raise ConfigError(f"effect {effect.name!r}: every offset is given; nothing to search")
    members = {
        g: [names.index(n) for n in mem] for g, mem in effect.shifted_members().items() if all(n in names for n in mem)
    }
    held = {g: v for g, v in effect.fixed_offsets().items() if g in members}
    searched = [g for g in open_groups if g in members]
    if not searched:
        raise ConfigError(f"effect {effect.name!r}: the model lacks the linear-ttl columns its offsets shift")
    return option, members, held, searched


class _OffsetProfiles:
    """The normal equations of a model whose groups of columns are shifted in time, at any
    offsets, and the profile ``Q`` of one group's offset (:func:`offset_search`).

    A shift is a phase per bin and column: the normal equations at any offsets are
    phase-weighted sums over bins of the products of each group's columns with all the
    columns and the data, taken once here; at zero offsets they are the model's.

    Parameters
    ----------
    model : ModelFit
        The model (its whitened columns, data, normal equations and errors-in-variables term).
    members : dict
        Group -> indices of its shifted columns.
    w : numpy.ndarray
        Per frequency bin, the phase [rad] per second of offset, ``2 pi f s``.

    Attributes
    ----------
    n_eval : int
        The offsets at which a profile was evaluated so far.
    """

    def __init__(self, model: ModelFit, members: dict, w: np.ndarray):
        data = model.data
        self.members, self.w = members, w
        self.P = P = len(model.columns.names)
        X = model.columns.w  # (S, m, 3, P)
        S, m = X.shape[:2]
        self.m = m
        X = np.ascontiguousarray(X.transpose(1, 0, 2, 3)).reshape(m, S * 3, P)
        d = np.ascontiguousarray(data.noise.wd.transpose(1, 0, 2)).reshape(m, S * 3)
        self.E = model.eiv_term.sum(axis=0)
        self.dd = float(data.noise.dd.sum())
        self.n_eval = 0
        self.N0 = model.normal[0].sum(axis=(0, 1))
        self.b0 = model.normal[1].sum(axis=(0, 1))
        self.QX, self.Qd = {}, {}
        for g, J in members.items():
            XJh = np.ascontiguousarray(np.swapaxes(X[:, :, J], 1, 2).conj())  # (m, |J|, S 3)
            self.QX[g] = np.matmul(XJh, X)  # (m, |J|, P)
            self.Qd[g] = np.matmul(XJh, d[:, :, None])[..., 0]  # (m, |J|)
        # the columns' classes: 0 unshifted, 1 + i the i-th group's
        self.groups = list(members)
        self.cls = np.zeros(P, dtype=int)
        for i, g in enumerate(self.groups):
            self.cls[members[g]] = i + 1

    def phases(self, col: np.ndarray) -> np.ndarray:
        """``exp(i w c)`` per bin and class (m, 1 + groups) at the offsets ``col`` [s]."""
        return np.exp(1j * np.outer(self.w, np.r_[0.0, [col[self.members[g][0]] for g in self.groups]]))

    def normal_at(self, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(N, b)`` with the columns shifted by ``col`` [s] (the groups' columns only)."""
        N, b = self.N0.copy(), self.b0.copy()
        if not col.any():
            return N, b
        T = self.phases(col)
        for i, (h, J) in enumerate(self.members.items()):
            rel = T * T[:, i + 1].conj()[:, None]  # exp(i w (c_u - c_h))
            rows = np.einsum("mjp,mp->jp", self.QX[h], rel[:, self.cls]).real
            N[J, :] = rows
            N[:, J] = rows.T
            b[J] = (T[:, i + 1].conj() @ self.Qd[h]).real
        return N, b

    def columns_at(self, offsets: dict) -> np.ndarray:
        """Per column, the offset [s] of its group in ``offsets`` (0 for unshifted columns)."""
        col = np.zeros(self.P)
        for h, idx in self.members.items():
            col[idx] = offsets[h]
        return col

    def profile(self, g, delta: dict):
        """``q(x) -> (Q, theta)``: Q(delta_g) on an array of offsets ``x`` [s], the other
        groups at ``delta``, and the linear parameters at each."""
        J, P, m, w, QX = self.members[g], self.P, self.m, self.w, self.QX
        R = [i for i in range(P) if i not in J]
        col = self.columns_at({h: (0.0 if h == g else delta[h]) for h in self.members})
        N, b = self.normal_at(col)
        N = N - self.E
        ph = self.phases(col)[:, self.cls[R]]  # exp(i w c_R)
        Q = np.concatenate([(QX[g][:, :, R] * ph[:, None, :]).reshape(m, -1), self.Qd[g]], axis=1)  # (m, |J| (|R| + 1))
        QQ = np.concatenate([Q.real, Q.imag], axis=0)  # Re(exp(-i x w) Q) = cos(x w) Re Q + sin(x w) Im Q
        del Q

        def q(x):
            x = np.atleast_1d(np.asarray(x, dtype=float))
            self.n_eval += x.size
            xw = np.outer(x, w)
            A = np.concatenate([np.cos(xw), np.sin(xw)], axis=1) @ QQ  # (K, |J| (|R| + 1))
            NJR = A[:, : len(J) * len(R)].reshape(-1, len(J), len(R))
            Nk = np.broadcast_to(N, (x.size, P, P)).copy()
            bk = np.broadcast_to(b, (x.size, P)).copy()
            Nk[:, np.ix_(J, R)[0], np.ix_(J, R)[1]] = NJR
            Nk[:, np.ix_(R, J)[0], np.ix_(R, J)[1]] = np.swapaxes(NJR, 1, 2)
            bk[:, J] = A[:, len(J) * len(R) :]
            th = np.linalg.solve(Nk, bk[..., None])[..., 0]
            return self.dd - np.einsum("kp,kp->k", bk, th), th

        return q


def _descend(prob: _OffsetProfiles, searched: list, bounds: dict, delta: dict, step: float, passes: int, kappa: float):
    """Coordinate descent over the open groups' offsets (updating ``delta`` [s] in place).

    Each group in turn, the others held: its profile on a grid of spacing ``step`` [s] over
    ``bounds[g]``, the best point refined by bounded Brent minimisation; until no offset
    moves by 1 ms or more, at most ``passes`` rounds.

    Returns
    -------
    gain : dict
        Group -> chi^2 gain of its offset against zero, the others as they were then.
    theta : numpy.ndarray or None
        The linear parameters at the last group's optimum.
    moved : float
        The largest move [s] of an offset in the last pass.
    profiles : dict
        Group -> its profile ``Q`` on its grid in the last pass.
    """
    grids = {g: np.arange(bounds[g][0], bounds[g][1] + 0.5 * step, step) for g in searched}
    gain, theta, moved = {}, None, np.inf
    profiles: dict = {}
    for _ in range(passes):
        moved = 0.0
        for g in searched:
            q = prob.profile(g, delta)
            Qg, _ = q(grids[g])
            profiles[g] = Qg
            x0 = float(grids[g][int(np.argmin(Qg))])
            lo, hi = bounds[g]
            res = minimize_scalar(
                lambda x, q=q: float(q(x)[0][0]),
                bounds=(max(x0 - step, lo), min(x0 + step, hi)),
                method="bounded",
                options={"xatol": 1e-4},
            )
            best = float(res.x) if res.fun <= Qg.min() else x0
            moved = max(moved, abs(best - delta[g]))
            delta[g] = best
            (q0, q1), th = q(np.array([0.0, best]))
            gain[g], theta = 2.0 * (q0 - q1) / kappa, th[1]
        if moved < 1e-3:  # the gains of this pass hold: no other offset moved since
            break
    return gain, theta, moved, profiles


def _joint_gain(prob: _OffsetProfiles, held: dict, delta: dict, kappa: float) -> tuple:
    """The joint chi^2 gain of the offsets ``delta`` against the open ones at zero (the given
    ones ``held``), and the log Bayes factor at the optimum (with the change of ``log det(N - E)``)."""
    logdet, q_at = [], []
    for offsets in ({g: held.get(g, 0.0) for g in prob.members}, delta):
        N, b = prob.normal_at(prob.columns_at(offsets))
        N = N - prob.E
        q_at.append(prob.dd - b @ np.linalg.solve(N, b))
        logdet.append(np.linalg.slogdet(N)[1])
    dchi2 = 2.0 * (q_at[0] - q_at[1]) / kappa
    return dchi2, 0.5 * dchi2 - 0.5 * (logdet[1] - logdet[0])


def _marginal_evidence(lbf_best: float, sigma: dict, bounds: dict, profiles: dict, kappa: float) -> float:
    """The log Bayes factor ``lbf_best`` at the optimum marginalised over a uniform prior on
    each searched offset's range ``bounds`` by Laplace's rule (``sigma`` [s]), a flat or
    multimodal profile (NaN sigma) averaged over its grid; never above ``lbf_best``."""
    marg = lbf_best
    for g in sigma:
        lo, hi = bounds[g]
        if np.isfinite(sigma[g]):
            marg += 0.5 * math.log(2 * math.pi) + math.log(sigma[g]) - math.log(hi - lo)
        else:  # a flat or multimodal profile: its likelihood averaged over the grid
            marg += float(special.logsumexp(-(profiles[g] - profiles[g].min()) / kappa) - math.log(profiles[g].size))
    return float(min(marg, lbf_best))


def _offset_sigma(q, x0: float, kappa: float, grid_step: float) -> float:
    """One sigma [s] of an offset from the curvature of the profile ``q`` (``Q``, chi^2 =
    ``2 Q / kappa``) at its optimum ``x0``: ``sigma^2 = kappa / Q''``, by a central
    difference with a step of a hundredth of the grid's, then again with a step of the
    sigma found (the profile is quadratic over a sigma; rounding in ``Q`` matters for much
    smaller steps).  NaN where the curvature is not positive (a flat profile)."""
    h = grid_step / 100.0
    sigma = float("nan")
    for _ in range(2):
        (qm, q0, qp), _ = q(np.array([x0 - h, x0, x0 + h]))
        curv = (qp - 2.0 * q0 + qm) / h**2
        if not curv > 0:
            return float("nan")
        sigma = math.sqrt(kappa / curv)
        h = min(max(sigma, 1e-7), grid_step)
    return sigma

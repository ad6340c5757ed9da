"""The time-domain prediction of a fitted model: what each effect adds to the TDI data.

The fit (:mod:`ttlcore.diagnose.model_fit`) works on whitened segment spectra; subtracting
the model from the data needs it back in time, on the telemetry's own samples and in the
channels the pipeline publishes (X2, Y2, Z2).  For a model fitted to telemetry
(:func:`ttlcore.diagnose.whitened.whiten_telemetry`) each effect beyond the linear TTL
contributes

- a column effect (drift, step, cross-coupling, second order, witness, fd-coupling,
  plugins): ``sum_k theta_k TDI(col_k)``, the exact TDI of the column's parts
  (:func:`ttlcore.effects.column_tdi.tdi_in_blocks`, the code path of the 24 regressors),
  filtered in time by the column's frequency response when it has one (an LTI filter
  commutes with TDI up to the arms' rate of change, ~1e-8, as the fit assumes);
- a shifted-witness effect (timing offset, light-travel-time error) of total offset
  ``delta_g`` per group: ``sum_k C_k [R_k(t + s delta_g) - R_k(t)]`` over the group's
  regressors ``R_k`` (``s`` the effect's ``d1_sign``), the exact shift the Taylor columns of
  the fit approximate, with the fitted linear coefficients ``C_k``.

The linear TTL itself is ``sum_k C_k R_k`` with the 24 coefficients
(:meth:`ttlcore.tdi.data.TDIData.model`), left to the caller, who has the regressors.  So
the residual of the whole model is ``d - sum_k C_k R_k - sum_e prediction_e``
(:func:`model_residual`).
"""

from __future__ import annotations

import logging

import numpy as np

from ..conventions import COEFFICIENT_NAMES
from ..effects.column_tdi import effect_input_from_telemetry, tdi_in_blocks
from ..effects.filters import filtered_many
from ..tdi.combinations import AET_MATRIX
from ..tdi.interpolation import timeshift

__all__ = ["column_regressors", "effect_predictions", "fit_residual", "model_residual", "xyz_regressors"]

log = logging.getLogger(__name__)


def xyz_regressors(data, names=COEFFICIENT_NAMES) -> np.ndarray:
    """The TTL regressors' X2, Y2, Z2 (3, k, n) on the telemetry samples of a
    :class:`~ttlcore.diagnose.whitened.WhitenedData`, the 24 in their order or those
    ``names`` (:meth:`~ttlcore.diagnose.whitened.MeasuredTDI.input_regressors` are A, E, T;
    the A, E, T matrix is orthogonal, so X, Y, Z are its transpose times A, E, T)."""
    return np.einsum("ac,akn->ckn", AET_MATRIX, data.tdi.input_regressors(names))


def effect_predictions(fit) -> dict[str, np.ndarray]:
    """What each effect of ``fit`` beyond ``linear-ttl`` adds to X2, Y2, Z2.

    Parameters
    ----------
    fit : ModelFit
        A model fitted to telemetry (``fit.data.context.tm`` set).

    Returns
    -------
    dict
        Effect spec (:meth:`Effect.spec`) -> (3, n) [fractional frequency] on the
        telemetry's samples; zero where it cannot be computed (the TDI delays or a shift's
        interpolation stencil reach beyond the data: the first ~70 s, where the data's TDI
        is not finite either, and the last few samples of a shift), so that a residual is
        the data less what is known of the model, and no consumer meets NaN in a fit.
    """
    data = fit.data
    tm = data.context.tm
    if tm is None:
        raise ValueError(
            "effect_predictions: the model was fitted to TDI outputs alone; the prediction of its "
            "effects needs the telemetry (DWS series)"
        )
    theta = dict(zip(fit.names, map(float, fit.theta)))
    out: dict[str, np.ndarray] = {}
    for effect in fit.effects:
        if effect.is_linear_ttl:
            continue
        if getattr(effect, "needs_coefficients", False):
            out[effect.spec()] = _shift_prediction(fit, effect, data)
        else:
            out[effect.spec()] = _column_prediction(effect, theta, data, tm)
    return {spec: np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0) for spec, x in out.items()}


def column_regressors(tm, effect, *, order: int, delay_order: int) -> tuple[tuple[str, ...], np.ndarray, dict]:
    """X2, Y2, Z2 of the columns of a column effect on the telemetry's own samples.

    Each column is the exact TDI of its parts (:func:`ttlcore.effects.column_tdi.tdi_in_blocks`,
    the code path of the 24 regressors), filtered in time by the column's frequency response
    when it has one (zero-padded linear convolution, :func:`ttlcore.effects.filters.filtered_many`;
    an LTI filter commutes with TDI up to the arms' rate of change, ~1e-8).  Columns sharing
    their parts (an fd-coupling's b0..b2) go through TDI once.

    Parameters
    ----------
    tm : Telemetry
        The telemetry (DWS, eta, light travel times).
    effect : Effect
        A column effect with its parameters set (not ``needs_coefficients``).
    order, delay_order : int
        Lagrange orders of the data and of the delay interpolation (the diagnosis settings').

    Returns
    -------
    names : tuple of str
        The effect's column names, in its order.
    xyz : ndarray (3, k, n)
        [fractional frequency per column unit]; NaN where not computable (the first ~70 s,
        which the TDI delays reach before).
    eiv : dict
        Column name -> the DWS readouts whose noise it carries, for the errors-in-variables
        term (:func:`ttlcore.estimate.fit.eiv_parts`): the parts of a plain witness
        ``-DWS/c`` (channel, link, delays, the column's response); columns of modulated or
        multiplied readouts carry none.
    """
    if getattr(effect, "needs_coefficients", False):
        raise ValueError(
            f"effect {effect.name!r} shifts the TDI regressors (a linearised effect): it has no "
            "columns of its own to compute from the telemetry"
        )
    cols = effect.columns(effect_input_from_telemetry(tm))
    groups: dict[str, list] = {}
    for c in cols:
        groups.setdefault(c.base or c.name, []).append(c)
    out: dict[str, np.ndarray] = {}
    for members in groups.values():
        _, xyz = tdi_in_blocks(tm.ltt, tm.fs, [members[0]], order=order, delay_order=delay_order)
        x = xyz[:, 0]  # (3, n)
        ok = np.isfinite(x).all(axis=0)
        for c in members:
            if c.response is None:
                out[c.name] = x
            else:
                y = np.stack([filtered_many(x[ch], tm.fs, [c.response])[0] for ch in range(3)])
                out[c.name] = np.where(ok, y, np.nan)
    names = tuple(c.name for c in cols)
    eiv = {
        c.name: tuple((p.channel, p.link, tuple(p.extra), c.response) for p in c.parts)
        for c in cols
        if c.parts and all(p.channel is not None and p.modulation is None for p in c.parts)
    }
    return names, np.stack([out[n] for n in names], axis=1), eiv


def _column_prediction(effect, theta: dict, data, tm) -> np.ndarray:
    """``sum_k theta_k TDI(col_k)`` (filtered by each column's response) of a column effect."""
    s = data.context.settings
    names, xyz, _ = column_regressors(tm, effect, order=s.order, delay_order=s.delay_order)
    total = np.zeros((3, tm.size))
    for k, name in enumerate(names):
        if name in theta:
            total += theta[name] * xyz[:, k]
    return total


def _shift_prediction(fit, effect, data) -> np.ndarray:
    """``sum_k C_k [R_k(t + s delta_g) - R_k(t)]`` over the groups of a shifted-witness effect."""
    C = fit.ttl_coefficients()
    offsets = fit.offsets()
    fs = float(data.tdi.td_in.fs)
    sign = float(effect.d1_sign)
    total = np.zeros((3, data.tdi.td_in.size))
    for group, members in effect.shifted_members().items():
        delta = offsets.get(f"{effect.name}.{group}", (0.0, 0.0))[0]
        if not delta:
            continue
        k = [COEFFICIENT_NAMES.index(m) for m in members]
        A = AET_MATRIX.T @ data.tdi.input_combination(members, C[k])  # X, Y, Z of sum_k C_k R_k
        total += timeshift(A, sign * delta * fs, order=data.context.settings.order) - A
    return total


def model_residual(
    data_xyz: np.ndarray, regressors_xyz: np.ndarray, coefficients: np.ndarray, predictions=()
) -> np.ndarray:
    """``d - sum_k C_k R_k - sum_e prediction_e``: the residual of the whole model (3, n).

    Parameters
    ----------
    data_xyz : ndarray (3, n)
        TDI of the data.
    regressors_xyz : ndarray (3, 24, n)
        TDI of the 24 regressors.
    coefficients : ndarray (24,)
        Linear coefficients [m/rad].
    predictions : iterable of ndarray (3, n)
        The other effects' predictions (:func:`effect_predictions`).
    """
    r = np.asarray(data_xyz, dtype=float) - np.einsum(
        "k,ckn->cn", np.asarray(coefficients, dtype=float), regressors_xyz
    )
    for p in predictions:
        r = r - p
    return r


def fit_residual(fit) -> tuple[float, float, np.ndarray, dict]:
    """The residual of the whole model ``fit`` on its own telemetry, in X2, Y2, Z2.

    Returns
    -------
    t0 : float
        Time of the first sample [s].
    fs : float
        Sampling rate [Hz] (the telemetry's).
    residual : ndarray (3, n)
        :func:`model_residual` of the data with the fit's 24 linear coefficients and its
        other effects' predictions.
    predictions : dict
        :func:`effect_predictions`.
    """
    td = fit.data.tdi.td_in
    C = fit.ttl_coefficients()
    if np.isnan(C).any():
        raise ValueError("fit_residual: the model does not hold the 24 linear coefficients (add linear-ttl)")
    predictions = effect_predictions(fit)
    d = np.einsum("ac,an->cn", AET_MATRIX, td.data)
    return float(td.t0), float(td.fs), model_residual(d, xyz_regressors(fit.data), C, predictions.values()), predictions

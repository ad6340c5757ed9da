"""Fit a model (a list of effects) to whitened data: one code path for the diagnosed
model, the candidates' trial models, the ``before`` model and the pipeline's refits.

:func:`fit_model` resolves the effects' searched parameters
(:func:`ttlcore.diagnose.glitches.effect_search` against the model of the other effects),
builds the columns (:mod:`ttlcore.diagnose.columns`), expands the shifted-witness effects
at their given or searched offsets (:func:`expand_linearised`, the same
:func:`~ttlcore.diagnose.search.profile_search` against the model's other columns), solves
(:func:`ttlcore.diagnose.model_fit.solve`), and for a model whose coefficients change in
time re-evaluates the DWS readout-noise term of the noise model with the model's own
coefficient history (the returned fit's ``data`` is then a new
:class:`~ttlcore.diagnose.whitened.WhitenedData`; the input is left as it is).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..conventions import COEFFICIENT_NAMES
from ..effects.base import Effect
from ..effects.registry import make_effects
from ..effects.shifted import OFFSET_OPTION
from ..errors import ConfigError
from ..estimate.fit import notch_mask, variance_factor
from ..estimate.spectra import segment_fft, window
from .adequacy import band_table, describe_time_failures, instrument_noise_csd, p_value
from .columns import (
    ColumnSet,
    assemble,
    effect_columns,
    empty_set,
    rewhitened,
    shifted_columns,
)
from .glitches import effect_search
from .model_fit import ModelFit, normal_solution, parameter_name, solve


def as_effects(data, effects) -> list:
    """Effect instances from specs or instances (plugins of ``data.context.effect_modules``)."""
    if all(isinstance(e, Effect) for e in effects):
        return list(effects)
    return make_effects(list(effects), data.context.effect_modules)


def fit_model(
    data, effects, coefficients_for_linearised=None, keep_series: bool = True, time_table: bool = True
) -> ModelFit:
    """Fit a model (list of effects or specs) to ``data`` under its noise model.

    A model whose coefficients change in time (drift, step) changes the readout noise the
    subtraction lets through: the DWS term of the noise model is then re-evaluated with the
    model's own coefficient history (time average of ``|sum C_k(t) T_k|^2``) and the model
    refitted once, on the new :class:`~ttlcore.diagnose.whitened.WhitenedData` (the fit's
    ``data``)."""
    effects = as_effects(data, effects)
    effects, searches = resolve(data, effects, coefficients_for_linearised)
    keep_series = keep_series and time_table  # the series serve the time-domain adequacy only
    fit = fit_resolved(data, effects, coefficients_for_linearised, keep_series)
    hist = coefficient_history(fit)
    if hist is not None and fit.data.tdi.dws_asd > 0:
        d = fit.data
        del fit  # not kept while the model is refitted (a day's columns are large)
        nm = d.noise.parameters
        d = d.with_noise(
            instrument_noise_csd(
                d.grid.f, d.tdi.ltt_mean, hist, d.tdi.dws_asd, secondary=None if nm is None else nm.csd(d.grid.f)
            )
        )
        fit = fit_resolved(d, effects, coefficients_for_linearised, keep_series)
    table = None
    if time_table and fit.columns.series is not None:
        table = time_adequacy(fit)
    # the fit keeps its whitened columns (evidence of candidates against it), not their series
    columns = replace(fit.columns, series=None) if fit.columns.series is not None else fit.columns
    # the searches before the fit and those of the offsets, made while building its columns
    return replace(fit, columns=columns, searches={**searches, **fit.searches}, time_table=table)


def resolve(data, effects, coefficients_for_linearised=None) -> tuple[list, dict]:
    """Effects with unset searched parameters (:attr:`ttlcore.effects.base.Effect.searched`)
    replaced by the same effect at the estimates of :func:`ttlcore.diagnose.glitches.effect_search`
    (:func:`ttlcore.diagnose.search.profile_search`, or a glitch's own search), profiled against the model of the other effects; returns the effects and the searches
    (``cli spec -> result``)."""
    out, searches = list(effects), {}
    for i, e in enumerate(effects):
        if not e.unresolved():
            continue
        rest = [x for x in out if x is not e and not x.unresolved()]
        base = fit_resolved(data, rest, coefficients_for_linearised, False)
        res = effect_search(base, e, base.ttl_coefficients())
        out[i] = res.effect
        searches[res.effect.cli_spec()] = res.to_json()
    return out, searches


def fit_resolved(data, effects, coefficients_for_linearised=None, keep_series: bool = False) -> ModelFit:
    """The fit of effects whose searched parameters are set (no search but that of the open
    offsets of shifted-witness effects, made with their columns, :func:`expand_linearised`;
    the noise model changed only if the linear fit that gives a linearised effect's
    coefficients drifts): the trial model of a candidate, the base model of a search.  Its
    ``searches`` hold the offsets' (effect spec -> search JSON)."""
    data, columns, expansion, searches = model_columns(data, effects, coefficients_for_linearised, keep_series)
    fit = solve(data, columns, effects, expansion)
    return replace(fit, searches=searches) if searches else fit


def model_columns(data, effects, coefficients=None, keep_series: bool = True) -> tuple:
    """The columns of a model: ``(data, ColumnSet, expansion points, offset searches)``.
    ``data`` is the input unless the linear fit that gives the coefficients of linearised
    effects changed the noise model (a drifting model).  ConfigError when a linearised
    effect's offset is given but the model cannot be expanded (``expansion_passes`` 0, or
    not all 24 linear coefficients in the model)."""
    sets: list[ColumnSet] = []
    names: list[str] = []
    plain = [e for e in effects if not e.needs_coefficients]
    # the store keeps a model's series (built once: the time-domain adequacy of a later fit
    # needs them); a fit copies them only when it keeps them
    for e in plain:
        cs = effect_columns(data, e, keep_series=True)
        sets.append(cs)
        names += [n for n in cs.names if n not in names]
    lin = [e for e in effects if e.needs_coefficients]
    expansion: dict = {}
    if lin:
        data, sets, C = _linear_coefficients(data, plain, sets, coefficients)
        first = list(names)
        for e in lin:  # their series (~400 MB a day through the derivatives) only when kept
            # the Taylor columns at zero do not depend on the given offsets (one cache entry)
            cs = effect_columns(data, e.without_offsets(), C, keep_series=keep_series)
            sets.append(cs)
            names += [n for n in cs.names if n not in names]
        if data.context.settings.expansion_passes and len(data.tdi.ttl_names) == 24:
            base = assemble(first, *sets, series=keep_series)
            columns, expansion, searches = expand_linearised(data, base, lin)
            if columns is not None:
                return data, columns, expansion, searches
            return data, assemble(names, *sets, series=keep_series), {}, searches
        given = [f"{e.name}:{OFFSET_OPTION}{g}" for e in lin for g, v in e.fixed_offsets().items() if v != 0.0]
        if given:
            why = (
                "expansion_passes is 0"
                if not data.context.settings.expansion_passes
                else "it lacks some of the 24 linear-ttl coefficients"
            )
            raise ConfigError(f"offsets given ({', '.join(given)}) but this model is not expanded at offsets ({why})")
    if not names:
        return data, empty_set(data.noise.key), expansion, {}
    return data, assemble(names, *sets, series=keep_series), expansion, {}


def _linear_coefficients(data, plain: list, sets: list, coefficients) -> tuple:
    """The 24 linear coefficients linearised effects are expanded with: ``coefficients``
    when given, else those of the model of the ``plain`` effects fitted to ``data``.

    Returns ``(data, sets, coefficients)``: the data and the plain effects' column sets
    ``sets`` whitened anew when that fit (a drifting model) changed the noise model.
    Raises ConfigError when the model lacks some of the 24 coefficients.
    """
    C = coefficients
    if C is None:
        part = fit_model(data, plain, keep_series=False, time_table=False)
        if part.data.noise.key != data.noise.key:  # a drifting model changed the noise model
            sets = [rewhitened(cs, data.noise.Lh, part.data) for cs in sets]
        data = part.data
        C = part.ttl_coefficients()
        if np.isnan(C).any():
            raise ConfigError(
                "linearised effects (timing-offset, ltt-error) need all 24 linear-ttl coefficients in the model"
            )
    return data, sets, C


def expand_linearised(data, first: ColumnSet, lin) -> tuple[ColumnSet | None, dict, dict]:
    """The exact model of the linearised effects at their offsets (given or searched), or
    None when the Taylor columns at zero are the model.

    The open offsets of each effect (``offset.<group>`` unset) are found by
    :func:`ttlcore.diagnose.search.profile_search` against the model of ``first`` (the other
    effects' columns; :func:`ttlcore.diagnose.offset_search.offset_search`: no Taylor expansion, so
    offsets with 2 pi f delta >> 1 at the top of the band are found), the given ones held.
    A group whose offset is given is expanded there (at zero: the Taylor columns); a
    searched one where its offset is clearly measured (delta chi^2 > 25) and large enough
    for the Taylor error to matter (2 pi f delta > 0.05 at the band's top).  The model
    holds an expanded group's TTL columns with their witnesses shifted by ``s delta_0``
    (exact, the linear coefficients fitted as before) and a ``d1`` column, the derivative
    there: its fitted coefficient is the remaining offset ``delta - delta_0``, moved into
    ``delta_0`` by Gauss-Newton passes until it is below a hundredth of its sigma (a given
    offset too: it chooses the expansion point, the fit still measures the offset).  Other
    groups keep the Taylor columns ``d1``, ``d2`` at zero.  A coefficient is shifted by
    one group only: given offsets first, then the searched ones in order.

    Returns
    -------
    (ColumnSet or None, dict, dict)
        The model's columns, the expansion points ``"effect.group" -> delta_0``, and the
        searches (the effect's ``--effects`` spec -> :meth:`SearchResult.to_json`).
    """
    shifts, moved_names = _given_shifts(lin)
    C, searches = _searched_shifts(data, first, lin, shifts, moved_names)
    if not moved_names:
        return None, {}, searches
    if C is None:
        C = _given_coefficients(data, first, lin, shifts)
    model, expansion, sets = first, dict[str, float](), [first]
    for _ in range(max(1, data.context.settings.expansion_passes)):
        model, expansion, sets, theta, sig = _expanded(data, first, lin, C, shifts)
        C = _ttl_vector(theta)
        step = {(e.name, g): theta[f"{e.name}.{g}.d1"] for e in lin for g in shifts[e.name]}
        if all(abs(v) < 0.01 * sig[f"{e}.{g}.d1"] for (e, g), v in step.items()):
            break
        for (e, g), v in step.items():
            shifts[e][g] += v
    if first.series is not None:  # with series (time-domain adequacy) when ``first`` has them
        model = assemble(model.names, *sets)
    return model, expansion, searches


def _given_shifts(lin) -> tuple[dict[str, dict], set[str]]:
    """The given non-zero offsets of the linearised effects ``lin`` (effect name -> group ->
    offset [s]) and the linear coefficients they shift; ConfigError when two shift the same."""
    shifts: dict[str, dict] = {e.name: {} for e in lin}
    moved_names = set[str]()
    for e in lin:  # the given offsets
        for g, d0 in e.fixed_offsets().items():
            members = set(e.shifted_members()[g])
            if d0 == 0.0:
                continue
            if moved_names & members:
                raise ConfigError(
                    f"{e.name}:{OFFSET_OPTION}{g}: another given offset shifts the same linear "
                    f"coefficients ({', '.join(sorted(moved_names & members))})"
                )
            moved_names |= members
            shifts[e.name][g] = d0
    return shifts, moved_names


def _searched_shifts(data, first: ColumnSet, lin, shifts: dict, moved_names: set) -> tuple:
    """The open offsets of the linearised effects searched against the model of ``first``;
    those clearly measured (delta chi^2 > 25) and large enough for the Taylor error to
    matter (2 pi f delta > 0.05 at the band's top) join ``shifts`` (and their coefficients
    ``moved_names``; both updated in place).

    Returns the linear coefficients at the first search's optimum (None without a search)
    and the searches (effect spec -> search JSON).
    """
    small = 0.05 / (2 * np.pi * data.context.settings.band[1])
    C, searches, base = None, {}, None
    for e in lin:
        if not e.open_offsets():
            continue
        if base is None:
            base = solve(data, first)
        found = effect_search(base, e)
        searches[e.cli_spec()] = found.to_json()
        if C is None:
            C = _ttl_vector(found.theta)
        for g, members in e.shifted_members().items():
            k = f"{OFFSET_OPTION}{g}"
            big = (
                k in found.estimates
                and found.gains[k] > 25.0
                and abs(found.estimates[k]) > small
                and not moved_names & set(members)
            )
            if big:
                moved_names |= set(members)
                shifts[e.name][g] = found.estimates[k]
    return C, searches


def _given_coefficients(data, first: ColumnSet, lin, shifts: dict) -> np.ndarray:
    """Every offset given: the linear coefficients at the given offsets (the model with the
    shifted TTL columns, which do not depend on C, and without the d1 columns); those of the
    unshifted model are biased by large offsets and misdirect the d1 steps."""
    names, sets = list(first.names), [first]
    for e in lin:
        repl, cs, _ = shifted_columns(data, e, np.zeros(len(COEFFICIENT_NAMES)), shifts[e.name])
        names = [repl.get(n, n) for n in names]
        sets.append(cs)
    return _ttl_vector(normal_solution(data, assemble(names, *sets, series=False))[0])


def _expanded(data, first: ColumnSet, lin, C: np.ndarray, shifts: dict) -> tuple:
    """The model expanded at the offsets ``shifts`` with the linear coefficients ``C``:
    ``(columns, expansion points, column sets, fitted parameters, their sigmas)``."""
    names, sets, expansion = list(first.names), [first], {}
    for e in lin:
        repl, cs, exp = shifted_columns(data, e, C, shifts[e.name])
        expansion.update(exp)
        names = [repl.get(n, n) for n in names] + [n for n in cs.names if "@" not in n]
        sets.append(cs)
    model = assemble(names, *sets, series=False)
    theta, sig = normal_solution(data, model)
    return model, expansion, sets, theta, sig


def _ttl_vector(values: dict) -> np.ndarray:
    """The 24 linear coefficients from a dict column -> value (shifted columns resolved)."""
    by = {parameter_name(n): v for n, v in values.items()}
    return np.array([by[n] for n in COEFFICIENT_NAMES])


def coefficient_history(model: ModelFit, n_t: int = 97) -> np.ndarray | None:
    """The model's linear coefficients on a time grid over the data, (24, n_t), when it
    holds drift or step columns (None otherwise)."""
    data = model.data
    vals = dict(zip(model.names, model.theta))
    modulating = [e for e in model.effects if e.modulates_coefficients]
    if not modulating:
        return None
    idx = np.flatnonzero(data.grid.mask)
    t = data.grid.t0 + np.linspace(idx[0], idx[-1], n_t) / data.grid.fs
    C = np.tile(model.ttl_coefficients()[:, None], (1, n_t))
    for effect in modulating:  # C(t) = C + sum of each effect's coefficients times its modulation
        mod, prefix, _ = effect.coefficient_modulation(t, 0.5 * (t[0] + t[-1]))
        for k, name in enumerate(COEFFICIENT_NAMES):
            C[k] += vals.get(f"{prefix}.{name}", 0.0) * mod
    return C


def time_adequacy(model: ModelFit) -> dict:
    """chi^2 of the residual in Hann-windowed slices of ``settings.time_segment`` against
    the same noise model (interpolated to the slice's frequency grid)."""
    data = model.data
    grid = data.grid
    s = data.context.settings
    if model.columns.series is None:
        raise ValueError("time_adequacy needs the columns' series (keep_series)")
    resid = data.tdi.data_series - np.einsum("p,cpn->cn", model.theta, model.columns.series)
    L = int(round(min(s.time_segment, grid.seg_duration) * grid.fs))
    idx = np.flatnonzero(grid.mask)
    lo, hi = idx[0], idx[-1] + 1
    f = np.fft.rfftfreq(L, 1 / grid.fs)
    sel = (f >= s.band[0]) & (f <= s.band[1])
    keep = np.zeros_like(sel)
    keep[sel] = notch_mask(f[sel], data.tdi.ltt_mean)
    fb = f[keep]
    csd = np.empty((fb.size, 3, 3), dtype=complex)
    for i in range(3):  # interpolate the model CSD (smooth) from the segment grid
        for j in range(3):
            csd[:, i, j] = np.interp(fb, grid.f, data.noise.csd[:, i, j].real) + 1j * np.interp(
                fb, grid.f, data.noise.csd[:, i, j].imag
            )
    Lh = np.conj(np.swapaxes(np.linalg.cholesky(np.linalg.inv(csd)), -1, -2))
    bidx = np.clip(np.searchsorted(grid.edges, fb, side="right") - 1, 0, grid.G - 1)
    win = window("hann", L)
    kappa = variance_factor("hann", 4096, 0.0)
    rows: list[dict] = []
    for s0 in range(lo, hi - L + 1, L):
        seg = resid[:, s0 : s0 + L]
        _, X = segment_fft(np.nan_to_num(seg), grid.fs, win, workers=None)
        wr = np.matmul(Lh, X[:, keep].T[..., None])[..., 0][None]
        tab = band_table(wr, bidx, grid.edges, 0, kappa, s.tolerance, s.alpha)
        chi2, dof = tab.chi2.sum(), tab.dof.sum()
        rows.append(
            {
                "t_start": grid.t0 + s0 / grid.fs,
                "t_stop": grid.t0 + (s0 + L) / grid.fs,
                "chi2": float(chi2),
                "dof": float(dof),
                "chi2_dof": float(chi2 / dof),
                "p_value": float(p_value(chi2, dof, kappa, s.tolerance)),
                "band_chi2_dof": [float(x) if np.isfinite(x) else None for x in tab.chi2_dof],
                "band_fails": [bool(x) for x in tab.fails],
            }
        )
    for r in rows:
        r["fails"] = bool(r["p_value"] < s.alpha) or any(r["band_fails"])
    summary = describe_time_failures(
        [r["t_start"] for r in rows], [r["t_stop"] for r in rows], [r["fails"] for r in rows], grid.t0_in
    )
    return {
        "segment_duration": L / grid.fs,
        "window": "hann",
        "variance_factor": kappa,
        "segments": rows,
        "summary": summary,
    }

"""Regressor columns of effects, whitened: pure functions of (effect, parameters, data).

A :class:`ColumnSet` is an immutable value: the names of some columns, their whitened
segment spectra (under the noise model of the :class:`~ttlcore.diagnose.whitened.WhitenedData`
they were built for), units and prior scales, their errors-in-variables description (the
DWS channels whose readout noise they carry, with placement and response) and optionally
their decimated series.  :func:`effect_columns` builds an effect's columns (the exact TDI of
its parts, :func:`ttlcore.effects.column_tdi.tdi_in_blocks`; or the modulated TDI regressors
for a quick ranking of ``drift`` and ``step``; or combinations of the time derivatives of
the TDI regressors for the linearised ``timing-offset`` and ``ltt-error``).

Columns are cached in a :class:`ColumnStore` under immutable keys: the effect's name and
options, the coefficients it was built with and the kind of construction.  An entry
whitened under another noise model is transformed to the current one (``L_new^H
(L_old^H)^-1`` per bin) when it is read.  A column set never changes once built, so trial
fits (candidates, searches) cannot change what a model sees.

The errors-in-variables term of a set of columns (:func:`eiv`) is the bias of the normal
matrix by the DWS readout noise the columns share (docs/diagnostics.md, "The loop").
"""

# size: the column builders of every kind of effect column (fixed, filtered, shifted, modulated)
# share one cache and one whitening path; split by kind they would import each other.

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..conventions import COEFFICIENT_NAMES, LINKS
from ..conventions import C as SPEED_OF_LIGHT
from ..effects.column_tdi import effect_input_from_telemetry, tdi_in_blocks
from ..effects.columns import Column, names_only_input
from ..effects.filters import derivative, filtered_many, readout_noise_factor
from ..effects.step import Step
from ..errors import ConfigError
from ..tdi.combinations import AET_MATRIX, MICHELSON, link_responses
from ..tdi.interpolation import timeshift
from ..tdi.regressors import placement

#: Unit and prior scale of the TTL regressor columns (m/rad; 2.3 mm/rad).
TTL_INFO = ("m/rad", 2.3e-3)


@dataclass(frozen=True, eq=False)
class ColumnSet:
    """Whitened regressor columns.

    Attributes
    ----------
    names : tuple of str
    x : ndarray (k, S, m, 6)
        Whitened segment spectra, real and imaginary parts interleaved (so that
        ``Re sum conj(a) b`` is a real dot product).
    noise_key : str
        Digest of the noise model they are whitened with.
    units, priors : tuple
        Unit and prior scale (standard deviation of the zero-mean Gaussian prior of the
        Bayes factor) of each column's parameter.
    eiv : tuple
        Per column, the DWS channels whose readout noise it carries:
        ``((mosa, angle), link, extra_delays, factor)`` with ``factor`` a time shift [s]
        (0: none) or a frequency response (m,) (filtered columns).
    modulation : tuple
        Per column, the slowly varying factor (decimated samples) multiplying its witness
        and so its readout noise (drift, step), or None.
    series : ndarray (3, k, n) or None
        Decimated A, E, T of the columns, when kept.
    """

    names: tuple[str, ...]
    x: np.ndarray
    noise_key: str
    units: tuple[str, ...]
    priors: tuple[float, ...]
    eiv: tuple[tuple, ...]
    modulation: tuple[np.ndarray | None, ...]
    series: np.ndarray | None = None

    def __post_init__(self):
        read_only(self.x, self.series)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def w(self) -> np.ndarray:
        """Whitened spectra (S, m, 3, k), complex."""
        return np.ascontiguousarray(np.moveaxis(self.x.view(complex), 0, -1))

    def column(self, name: str) -> np.ndarray:
        """One column's whitened spectra (S, m, 3)."""
        return self.x[self.names.index(name)].view(complex)

    def select(self, names, series: bool = True) -> ColumnSet:
        """The columns ``names`` (in that order)."""
        return assemble(names, self, series=series)


def read_only(*arrays) -> None:
    """Mark arrays read-only: a value's arrays cannot be changed in place by a later trial
    (the in-place update is an error instead of a silent change of another fit's input)."""
    for a in arrays:
        if isinstance(a, np.ndarray):
            a.flags.writeable = False


def empty_set(noise_key: str) -> ColumnSet:
    return ColumnSet((), np.zeros((0, 0, 0, 6)), noise_key, (), (), (), (), None)


def assemble(names, *sets: ColumnSet, series: bool = True) -> ColumnSet:
    """The columns ``names`` taken from ``sets`` (a name in several: the last set's), in
    the order of ``names``; series when every set has them and ``series`` is true (one set
    holding exactly ``names``: that set, no copy)."""
    names = tuple(names)
    if len(sets) == 1 and sets[0].names == names and (series or sets[0].series is None):
        return sets[0]
    where = {}
    for s in sets:
        for i, n in enumerate(s.names):
            where[n] = (s, i)
    missing = [n for n in names if n not in where]
    if missing:
        raise ConfigError(f"columns {missing[:3]} are not built")
    keys = {s.noise_key for s in sets if len(s)}
    if len(keys) > 1:
        raise ValueError("columns whitened with different noise models cannot be combined")
    picks = [where[n] for n in names]
    x = np.stack([s.x[i] for s, i in picks]) if picks else np.zeros((0, 0, 0, 6))
    have_series = series and all(s.series is not None for s, _ in picks)
    stacked = (
        np.stack([s.series[:, i] for s, i in picks if s.series is not None], axis=1) if picks and have_series else None
    )
    return ColumnSet(
        names,
        x,
        next(iter(keys)) if keys else "",
        tuple(s.units[i] for s, i in picks),
        tuple(s.priors[i] for s, i in picks),
        tuple(s.eiv[i] for s, i in picks),
        tuple(s.modulation[i] for s, i in picks),
        stacked,
    )


def concat(*sets: ColumnSet) -> ColumnSet:
    """The columns of ``sets`` one after the other (names must not repeat)."""
    names = [n for s in sets for n in s.names]
    if len(set(names)) != len(names):
        raise ValueError("repeated column names")
    return assemble(names, *sets)


def rewhitened(cs: ColumnSet, Lh_from: np.ndarray, data) -> ColumnSet:
    """``cs`` (whitened with ``Lh_from``) whitened with ``data``'s noise model instead:
    ``L_new^H (L_old^H)^-1`` per bin, no spectra recomputed."""
    if cs.noise_key == data.noise.key or not len(cs):
        return cs
    M = data.noise.Lh @ np.linalg.inv(Lh_from)
    w = cs.x.view(complex)
    x = np.empty_like(w)  # filled column by column: no list of copies beside the stack
    for k in range(len(cs)):
        x[k] = np.einsum("mij,smj->smi", M, w[k])
    return replace(cs, x=x.view(np.float64), noise_key=data.noise.key)


def _whitened_set(data, names, spectra, units, priors, eiv=None, modulation=None, series=None) -> ColumnSet:
    """A set from raw spectra (S, m, 3, k), whitened with ``data``'s noise model."""
    w = data.noise.whiten(spectra)
    # one contiguous copy, columns first (a list of per-column copies and their stack held a
    # day's 24 regressor columns, 78 MB, twice over beside ``w``)
    x = np.ascontiguousarray(np.moveaxis(w, -1, 0)).view(np.float64)
    del w
    k = len(names)
    return ColumnSet(
        tuple(names),
        x,
        data.noise.key,
        tuple(units),
        tuple(priors),
        tuple(eiv) if eiv is not None else ((),) * k,
        tuple(modulation) if modulation is not None else (None,) * k,
        series,
    )


class ColumnStore:
    """Cache of column sets (and readout-noise responses) of one diagnosis.

    Keys are immutable descriptions of what was built (see the module docstring); an entry
    whitened under another noise model is transformed to the one asked for, and replaced.
    Candidates scored in threads share a store: every method reads an entry once and
    returns what it read or built, so a concurrent put or eviction costs at most a
    recomputation, never a wrong or missing entry."""

    def __init__(self):
        # key -> (the Cholesky factor Lh it is whitened with, the columns)
        self._sets: dict[tuple, tuple[np.ndarray, ColumnSet]] = {}
        # (noise key, link, extra delays) -> whitened readout-noise response (m, 3)
        self._eiv: dict[tuple, np.ndarray] = {}
        # (combination, extra delays) -> (f, ltt_mean, link_responses): the unwhitened
        # responses do not change with the noise model (one diagnosis: one f, one ltt_mean)
        self._links: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._latest: dict[tuple, tuple] = {}  # family -> its latest key (columns built with fitted coefficients)

    def get(self, key: tuple, data) -> ColumnSet | None:
        entry = self._sets.get(key)
        if entry is None:
            return None
        Lh, cs = entry
        if cs.noise_key != data.noise.key:
            cs = rewhitened(cs, Lh, data)
            self._sets[key] = (data.noise.Lh, cs)
        return cs

    def put(self, key: tuple, data, cs: ColumnSet, family: tuple | None = None) -> ColumnSet:
        """Store ``cs`` under ``key``; with ``family`` (the key without the coefficients the
        columns were built with) the family's previous entry is dropped: a model's
        coefficients move with every pass of the noise-model fit, and only the last
        columns are asked for again."""
        if family is not None:
            old = self._latest.get(family)
            if old is not None and old != key:
                self._sets.pop(old, None)
            self._latest[family] = key
        self._sets[key] = (data.noise.Lh, cs)
        return cs

    def mark(self) -> frozenset:
        """The keys of the column sets stored now (for :meth:`release_since`)."""
        return frozenset(self._sets)

    def release_since(self, mark: frozenset, keep: tuple = ()) -> None:
        """Drop the column sets stored after :meth:`mark` gave ``mark`` (but those whose key
        starts with one of ``keep``): a phase's trial columns (the candidates') that nothing
        after it asks for again.  One asked for again is built again, the same numbers (a
        column set is a pure function of its key and the data).  Not while other threads use
        the store."""
        for key in [k for k in self._sets if k not in mark and k[0] not in keep]:
            self._sets.pop(key, None)
        self._latest = {family: key for family, key in self._latest.items() if key in self._sets}

    def _link_responses(self, data, combination, extra: tuple) -> np.ndarray:
        """:func:`ttlcore.tdi.combinations.link_responses` of ``combination`` on ``data.grid.f``
        (every link), computed once per diagnosis and extra delays."""
        entry = self._links.get((combination.name, extra))
        if entry is None or entry[0] is not data.grid.f or entry[1] is not data.tdi.ltt_mean:
            entry = (data.grid.f, data.tdi.ltt_mean, link_responses(combination, data.grid.f, data.tdi.ltt_mean, extra))
            self._links[(combination.name, extra)] = entry
        return entry[2]

    def eiv_response(self, data, link, extra) -> np.ndarray:
        """Whitened A, E, T response (m, 3) to the DWS readout noise of a witness ``-DWS/c``
        placed on ``link`` after ``extra`` delays, times the noise's ASD (velocity)."""
        key = (data.noise.key, link, tuple(extra))
        r = self._eiv.get(key)  # one lookup: candidates scored in threads share the store
        if r is None:
            if len(self._eiv) > 64:
                self._eiv.clear()
            h = np.stack([self._link_responses(data, c, tuple(extra))[LINKS.index(link)] for c in MICHELSON])
            T = (AET_MATRIX @ h).T * (-1.0 / SPEED_OF_LIGHT)  # (m, 3)
            r = self._eiv[key] = (
                np.matmul(data.noise.Lh, T[..., None])[..., 0] * (2 * np.pi * data.grid.f * data.tdi.dws_asd)[:, None]
            )
        return r


# ---------------------------------------------------------------------------
# Building columns
# ---------------------------------------------------------------------------


def ttl_columns(data) -> ColumnSet:
    """The TDI regressor columns of the data (the 24 TTL ones, with their readout noise)."""
    key = ("regressors",)
    cs = data.context.store.get(key, data)
    if cs is None:  # put there by whiten_tdi; recomputed only if a user's store was cleared
        cs = data.context.store.put(key, data, regressor_columns(data, data.grid.spectra(data.tdi.regressor_series)))
    return cs


def regressor_columns(data, R: np.ndarray) -> ColumnSet:
    """The TDI regressor columns from their raw band spectra ``R`` (S, m, 3, k), whitened."""
    eiv: list = []
    for n in data.tdi.regressor_names:
        if n in COEFFICIENT_NAMES:
            link, extra, mosa, angle = placement(n)
            eiv.append((((mosa, angle), link, tuple(extra), 0.0),))
        else:
            eiv.append(())
    k = len(data.tdi.regressor_names)
    return _whitened_set(
        data, data.tdi.regressor_names, R, [TTL_INFO[0]] * k, [TTL_INFO[1]] * k, eiv, None, data.tdi.regressor_series
    )


def derivative_columns(data, series: bool = False) -> ColumnSet:
    """Whitened spectra of the first and second time derivatives of the TDI regressors
    (columns ``d1:<name>``, ``d2:<name>``), computed once; with ``series`` their decimated
    series too (a day's 48 columns: ~400 MB, so kept only when a model asks for them)."""
    key = ("derivatives",)
    cs = data.context.store.get(key, data)
    if cs is not None and (not series or cs.series is not None):
        return cs
    td = data.tdi.td_in
    regs = data.tdi.regressor_names
    k = len(regs)
    names = [f"d{order}:{n}" for order in (1, 2) for n in regs]
    # filled order by order, no concatenation (a day's 48 columns: ~160 MB of spectra)
    x = np.empty((2 * k, len(data.grid.starts), data.grid.f.size, 6))
    kept = np.empty((3, 2 * k, data.grid.mask.size)) if series else None
    for o, order in enumerate((1, 2)):
        s = np.concatenate(
            [
                data.grid.decimate(derivative(data.tdi.input_regressors(regs[j0 : j0 + 8]), td.fs, order), is_aet=True)
                for j0 in range(0, k, 8)
            ],
            axis=1,
        )
        if kept is not None:  # series asked for
            kept[:, o * k : (o + 1) * k] = s
        w = data.noise.whiten(data.grid.spectra(s))
        del s
        xc = x.view(complex)  # (2k, S, m, 3)
        for j in range(k):
            xc[o * k + j] = w[..., j]
        del w
    cs = ColumnSet(
        tuple(names), x, data.noise.key, ("",) * (2 * k), (1.0,) * (2 * k), ((),) * (2 * k), (None,) * (2 * k), kept
    )
    return data.context.store.put(key, data, cs)


def _options_key(effect) -> str:
    return repr(sorted(effect.options.items()))


def effect_columns(
    data, effect, coefficients=None, keep_series: bool = False, exact: bool = True, cache: bool = True
) -> ColumnSet:
    """The whitened columns of ``effect`` (cached; see the module docstring).

    ``exact=False`` (candidate ranking) builds ``drift`` and ``step`` columns by modulating
    the TDI regressors in time (``TDI(m w) = m TDI(w)`` but for the ~70 s the TDI delays
    span, a relative error ~1e-3 on a drift column), saving a TDI per column.  Linearised
    effects (``timing-offset``, ``ltt-error``) always use the time derivatives of the TDI
    regressors (:meth:`ttlcore.effects.shifted._Linearised.tdi_terms`) when the data hold
    the 24 of them.  ``keep_series``: the decimated series are kept (time-domain adequacy,
    filters in time); ``cache=False``: the columns are not kept in the store (trial
    columns of a search or a candidate; the unfiltered base columns are kept)."""
    names_in = set(data.tdi.regressor_names)
    if (
        hasattr(effect, "tdi_terms")
        and len(data.tdi.ttl_names) == 24
        and all(n in names_in for n in data.tdi.ttl_names)
    ):
        if coefficients is None:
            raise ConfigError(f"effect {effect.name!r} needs the linear coefficients")
        key: tuple = ("tdi_terms", effect.name, _options_key(effect), tuple(np.round(coefficients, 15)))
        cs = data.context.store.get(key, data)
        if cs is None or (keep_series and cs.series is None):
            d = derivative_columns(data, series=keep_series)
            names, x, series, units, priors = [], [], [], [], []
            for cname, unit, prior, terms in effect.tdi_terms(coefficients):
                x.append(np.ascontiguousarray(sum(f * d.column(f"d{o}:{n}") for n, o, f in terms)))
                if keep_series and d.series is not None:  # kept: derivative_columns(series=True)
                    series.append(sum(f * d.series[:, d.names.index(f"d{o}:{n}")] for n, o, f in terms))
                names.append(cname)
                units.append(unit)
                priors.append(prior)
            k = len(names)
            cs = data.context.store.put(
                key,
                data,
                ColumnSet(
                    tuple(names),
                    np.stack(x).view(np.float64),
                    data.noise.key,
                    tuple(units),
                    tuple(priors),
                    ((),) * k,
                    (None,) * k,
                    np.stack(series, axis=1) if keep_series else None,
                ),
                family=key[:3],
            )
        return cs
    if (
        not exact
        and effect.modulates_coefficients
        and all(f"{m}.{a}.{sd}" in names_in for m in effect.mosas for a in effect.angles for sd in effect.sides)
    ):
        key = ("approx", effect.name, _options_key(effect))
        cs = data.context.store.get(key, data)
        if cs is None:
            cs = data.context.store.put(key, data, _modulated_regressors(data, effect))
        return cs
    return _exact_columns(data, effect, coefficients, keep_series, cache)


def _exact_columns(data, effect, coefficients, keep_series, cache=True) -> ColumnSet:
    if isinstance(effect, Step) and effect.options.get("t_step") is None:
        raise ConfigError("effect 'step' needs t_step in a model (ttl diagnose reports the searched time)")
    if effect.is_linear_ttl:
        names = [c.name for c in effect.columns(names_only_input())]
        missing = [n for n in names if n not in data.tdi.regressor_names]
        if missing:
            raise ConfigError(f"linear-ttl columns {missing[:3]} missing from the TDI data")
        return ttl_columns(data).select(names, series=keep_series)
    key = (
        "exact",
        effect.name,
        _options_key(effect),
        None if coefficients is None else tuple(np.round(coefficients, 12)),
    )
    cs = data.context.store.get(key, data)
    if cs is not None and (not keep_series or cs.series is not None):
        return cs
    if data.context.tm is None:
        cs = _modulated_regressors(data, effect)
    else:
        cols = effect.columns(effect_input_from_telemetry(data.context.tm, coefficients))
        if not cols:
            raise ConfigError(f"effect {effect.name!r} produced no column (check its options)")
        if any(c.response is not None for c in cols):
            cs = filtered_columns(data, cols)
            return data.context.store.put(key, data, cs, family=key[:3]) if cache else cs
        eiv, mods = zip(*[column_eiv(data, c) for c in cols])
        chunks = []
        for j0 in range(0, len(cols), 8):  # bounded memory (a day: ~70 MB per column in flight)
            _, xyz = tdi_in_blocks(
                data.context.tm.ltt,
                data.context.tm.fs,
                cols[j0 : j0 + 8],
                order=data.context.settings.order,
                delay_order=data.context.settings.delay_order,
            )
            chunks.append(data.grid.decimate(xyz))
        series = np.concatenate(chunks, axis=1)
        cs = _whitened_set(
            data,
            [c.name for c in cols],
            data.grid.spectra(series),
            [c.unit for c in cols],
            [c.prior_scale for c in cols],
            eiv,
            mods,
            series if keep_series else None,
        )
    return data.context.store.put(key, data, cs, family=key[:3]) if cache else cs


def column_eiv(data, column) -> tuple:
    """Errors-in-variables description of an effect's column ``(parts, modulation)``:
    plain (or slowly modulated) DWS witnesses carry their channel's readout noise (the
    modulation resampled to the decimated grid); other columns none."""
    parts = column.parts
    if not parts or any(p.channel is None for p in parts):
        return (), None
    mods = [p.modulation for p in parts]
    mod = None
    if any(m is not None for m in mods):
        if any(m is None or not np.array_equal(m, mods[0]) for m in mods):
            return (), None  # parts modulated differently: not modelled
        t_tm = float(data.context.tm.t0) + np.arange(len(mods[0])) / float(data.context.tm.fs)
        t_dec = data.grid.t0 + np.arange(data.grid.mask.size) / data.grid.fs
        mod = np.interp(t_dec, t_tm, np.asarray(mods[0], dtype=float))
    return tuple((p.channel, p.link, tuple(p.extra), 0.0) for p in parts), mod


def _modulated_regressors(data, effect) -> ColumnSet:
    """The columns of an effect that modulates the linear coefficients (drift, step:
    :meth:`~ttlcore.effects.base.Effect.coefficient_modulation`) as time-modulated TDI
    regressors (no telemetry needed)."""
    t = data.grid.t0 + np.arange(data.tdi.data_series.shape[-1]) / data.grid.fs
    t_mid = 0.5 * (t[data.grid.mask][0] + t[data.grid.mask][-1])
    mod, prefix, unit = effect.coefficient_modulation(t, t_mid)
    base = ttl_columns(data)
    picked = [f"{m}.{a}.{sd}" for m in effect.mosas for a in effect.angles for sd in effect.sides]
    names, eiv, mods = [], [], []
    rs = data.tdi.regressor_series
    # filled in place (a day of 24 columns: 0.1 GB; a list of products and their stack held two)
    series = np.empty((rs.shape[0], len(picked), rs.shape[-1]))
    for j, b in enumerate(picked):
        i = base.names.index(b)
        names.append(f"{prefix}.{b}")
        np.multiply(rs[:, i], mod, out=series[:, j])
        eiv.append(base.eiv[i])
        mods.append(mod if base.eiv[i] else None)
    k = len(names)
    return _whitened_set(data, names, data.grid.spectra(series), [unit] * k, [1e-3] * k, eiv, mods)


def base_column(data, column) -> ColumnSet:
    """The unfiltered column of a filtered one (cached): its parts through the exact TDI,
    whitened, with series.  Keyed by the parts' placement and source, so that witness and
    frequency-dependent candidates on one placement share it."""
    key = "base:" + (column.base or column.name.split(".", 1)[-1])
    key += "|" + ";".join(f"{p.link}/{int(p.delayed)}/{p.channel}" for p in column.parts)
    cs = data.context.store.get(("base", key), data)
    if cs is None:
        plain = Column(key, column.parts, column.unit, column.prior_scale)
        _, xyz = tdi_in_blocks(
            data.context.tm.ltt,
            data.context.tm.fs,
            [plain],
            order=data.context.settings.order,
            delay_order=data.context.settings.delay_order,
        )
        series = data.grid.decimate(xyz)
        eiv, mod = column_eiv(data, plain)
        cs = data.context.store.put(
            ("base", key),
            data,
            _whitened_set(
                data, [key], data.grid.spectra(series), [column.unit], [column.prior_scale], [eiv], [mod], series
            ),
        )
    return cs


def filtered_spectra(data, base: ColumnSet, responses, transform: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Whitened spectra (S, m, 3, k) and decimated series (3, k, n) of the one-column set
    ``base`` through the filters ``responses`` (callables ``f -> complex``), filtered in the
    time domain before the segments are windowed (:func:`ttlcore.effects.filters.filtered`):
    multiplying the windowed segment's spectrum instead misses the filter's ringing across
    the taper, a few tens of per cent of a strong resonance's excess at the segment ends.
    ``transform``: :func:`ttlcore.effects.filters.filter_transform` of the base series,
    when it is filtered many times (a search)."""
    if base.series is None:
        raise ValueError("the base column's series are needed (keep_series)")
    x = base.series[:, 0]
    ok = np.isfinite(x)
    series = np.stack([np.where(ok, y, np.nan) for y in filtered_many(x, data.grid.fs, responses, transform)], axis=1)
    return data.noise.whiten(data.grid.spectra(series)), series


def filtered_columns(data, cols) -> ColumnSet:
    """Columns carrying a frequency response: the base column (its parts through the exact
    TDI, once) filtered in time (:func:`filtered_spectra`); the readout-noise response is the
    base column's times the response (errors-in-variables term)."""
    x, series, eiv, mods = [], [], [], []
    for c in cols:
        base = base_column(data, c)
        resp = (
            np.ones(data.grid.f.size, dtype=complex)
            if c.response is None
            else np.asarray(c.response(data.grid.f), dtype=complex)
        )
        w, s = filtered_spectra(data, base, [c.response or (lambda f: np.ones(np.shape(f)))])
        x.append(np.ascontiguousarray(w[..., 0]))
        series.append(s[:, 0])
        eiv.append(tuple((ch, link, extra, resp) for ch, link, extra, *_ in base.eiv[0]))
        mods.append(base.modulation[0])
    return ColumnSet(
        tuple(c.name for c in cols),
        np.stack(x).view(np.float64),
        data.noise.key,
        tuple(c.unit for c in cols),
        tuple(c.prior_scale for c in cols),
        tuple(eiv),
        tuple(mods),
        np.stack(series, axis=1),
    )


def shifted_columns(data, effect, C, shifts: dict) -> tuple[dict, ColumnSet, dict]:
    """Columns of a linearised effect expanded at ``shifts[group]`` (the exact model of
    :func:`ttlcore.diagnose.fitting.expand_linearised`).

    For each group with an offset ``delta_0``: its TTL columns with the witnesses shifted,
    ``R_k(t + s delta_0)``, named ``"<coefficient>@<effect>.<group>"``, and the column
    ``<effect>.<group>.d1 = s sum_k C_k R_k'(t + s delta_0)`` (parameter: the offset beyond
    ``delta_0`` [s]).  Groups without one: the Taylor columns ``d1``, ``d2`` at zero.  The
    shifted series are built from the 4-Hz TDI regressors (TDI commutes with the shift up to
    the arms' rate of change, ~1e-8).

    Returns
    -------
    replaced : dict
        TTL column name -> the name of its shifted column.
    columns : ColumnSet
        The shifted TTL columns and the effect's own (``d1``, ``d2``), with series.
    expansion : dict
        ``"effect.group" -> delta_0``.
    """
    td = data.tdi.td_in
    base = ttl_columns(data)
    sgn = float(effect.d1_sign)
    replaced, names, blocks, units, priors, eiv, expansion = {}, [], [], [], [], [], {}
    # each group's series decimated as they are made: a day's shifted regressors at 4 Hz
    # (100 MB a group), kept for the stack of all groups, were the peak of a diagnosis
    for g, members in effect.shifted_members().items():
        d0 = float(shifts.get(g, 0.0))
        expansion[f"{effect.name}.{g}"] = d0
        weights = [float(C[COEFFICIENT_NAMES.index(k)]) for k in members]
        if d0:
            R = timeshift(data.tdi.input_regressors(members), sgn * d0 * td.fs)  # (3, k, n)
            for cname in members:
                new = f"{cname}@{effect.name}.{g}"
                replaced[cname] = new
                names.append(new)
                i = base.names.index(cname)
                units.append(base.units[i])
                priors.append(base.priors[i])
                eiv.append(tuple((ch, link, extra, sgn * d0) for ch, link, extra, *_ in base.eiv[i]))
            blocks.append(data.grid.decimate(R, is_aet=True))
            A = np.einsum("k,ckn->cn", weights, R)
            del R
        else:  # only the sum is needed: one column's TDI (TDI is linear), not k
            A = data.tdi.input_combination(members, weights)
        cols = {"d1": sgn * derivative(A, td.fs, 1)}
        if not d0:
            cols["d2"] = 0.5 * derivative(A, td.fs, 2)
        del A
        for kind in cols:
            names.append(f"{effect.name}.{g}.{kind}")
            units.append({"d1": "s", "d2": "s^2"}[kind])
            priors.append({"d1": 0.1, "d2": 0.01}[kind])
            eiv.append(())
        blocks.append(data.grid.decimate(np.stack(list(cols.values()), axis=1), is_aet=True))
        del cols
    series = np.concatenate(blocks, axis=1)
    del blocks
    cs = _whitened_set(data, names, data.grid.spectra(series), units, priors, eiv, None, series)
    return replaced, cs, expansion


# ---------------------------------------------------------------------------
# Errors in variables
# ---------------------------------------------------------------------------


def eiv(data, *sets: ColumnSet) -> np.ndarray:
    """Errors-in-variables term (G, p, p) of the columns of ``sets`` (one after the other),
    summed over segments: ``E_kl = W_kl sum_ch Re sum_f U_k,ch^H U_l,ch``
    (:func:`eiv_products`, one segment) with ``W_kl`` the segments' taper-weighted means of
    the product of the columns' modulations (:func:`eiv_weights`; the number of segments for
    unmodulated columns)."""
    return eiv_products(data, *sets) * eiv_weights(data, *sets)[None]


def eiv_products(data, *sets: ColumnSet) -> np.ndarray:
    """One segment's errors-in-variables products (G, p, p): ``Re sum_f U_k,ch^H U_l,ch``
    summed over the DWS channels ``ch``, ``U_k,ch`` the whitened response of column ``k``
    to the readout noise of channel ``ch``.  Columns whose parts are plain (or slowly
    modulated, shifted or filtered) DWS witnesses carry it; others, built from products of
    the readouts, carry none - their bias is second order in the small readout noise."""
    parts_of = [parts for cs in sets for parts in cs.eiv]
    p = len(parts_of)
    E = np.zeros((data.grid.G, p, p))
    by_channel: dict = {}
    for i, parts in enumerate(parts_of):
        for ch, link, extra, factor in parts:
            by_channel.setdefault(ch, {}).setdefault(i, []).append((link, extra, factor))
    for cols in by_channel.values():
        idx = sorted(cols)
        U = np.stack(
            [
                sum(
                    data.context.store.eiv_response(data, link, extra) * readout_noise_factor(data.grid.f, factor)
                    for link, extra, factor in cols[i]
                )
                for i in idx
            ],
            axis=-1,
        )
        for g, (a, b) in enumerate(data.grid.slices):
            if b > a:
                Ug = U[a:b].reshape(-1, len(idx))
                E[g][np.ix_(idx, idx)] += np.real(Ug.conj().T @ Ug)
    return E


def eiv_weights(data, *sets: ColumnSet) -> np.ndarray:
    """``W_kl = sum_s <m_k m_l>_s`` (p, p): per segment the mean of the product of the
    columns' modulations weighted by the squared taper (the readout noise is white on the
    modulations' time scale), ``m = 1`` for unmodulated columns."""
    mods = [m for cs in sets for m in cs.modulation]
    W = np.full((len(mods), len(mods)), float(len(data.grid.starts)))
    idx = [i for i, m in enumerate(mods) if m is not None]
    if idx:
        A = np.stack(
            [np.stack([m[s0 : s0 + data.grid.L] for s0 in data.grid.starts]) for m in mods if m is not None]
        )  # (q, S, L)
        cross = np.einsum("qsl,sl->q", A, data.grid.w2)  # against m = 1
        W[idx, :] = cross[:, None]
        W[:, idx] = cross[None, :]
        W[np.ix_(idx, idx)] = np.einsum("qsl,rsl,sl->qr", A, A, data.grid.w2)
    return W

"""The base of the shifted-witness effects (``timing-offset``, :mod:`ttlcore.effects.timing_offset`;
``ltt-error``, :mod:`ttlcore.effects.ltt_error`) and their exact injection.

Their exact form ``w(t + epsilon)`` is nonlinear in the offset; the fit uses its Taylor
expansion to second order (columns ``.d1``, ``.d2``), the simulator the exact injection
(:class:`ShiftInjection`, Lagrange reading at the shifted times).
"""

from __future__ import annotations

import numpy as np

from ..conventions import (
    COEFFICIENT_NAMES,
    LINKS,
    MOSAS,
    C,
    parse_time,
    reverse,
)
from ..errors import ConfigError
from ..sim.injection import ChunkContext
from ..tdi.interpolation import apply_taps, shift_taps
from ..tdi.regressors import witness_placement as placement
from .base import Effect
from .columns import Column, Part
from .filters import derivative
from .injection import EffectInjection

OFFSET_OPTION = "offset."


def _offset_parameters(groups) -> dict:
    """The offset options ``offset.<group>`` of a shifted-witness effect (unset: searched)."""
    return {f"{OFFSET_OPTION}{g}": None for g in groups}


class _Linearised(Effect):
    """Effects whose exact form is ``w(t + epsilon)`` (shifted witnesses); the fit uses
    ``epsilon w' + (epsilon^2 / 2) w''`` (columns ``.d1`` with parameter epsilon [s] and
    ``.d2`` with parameter epsilon^2 [s^2]), built with the fitted linear coefficients.

    Each group's offset is a searched parameter (:attr:`searched`): the option
    ``offset.<group>`` [s] (``timing-offset:offset.sc1=0.35``), declared over ``(-inf, inf)``
    and searched over ``+-settings.shift_span`` (:func:`ttlcore.diagnose.search.search_ranges`).
    Unset, the diagnosis searches it where it builds the model's columns
    (:func:`ttlcore.diagnose.fitting.expand_linearised`, through
    :func:`ttlcore.diagnose.search.profile_search`); given, it is the group's expansion point
    (the exact model holds the group's witnesses shifted by it, the fitted ``d1`` the rest).
    A plugin with this interface (:meth:`_groups`, :attr:`d1_sign`) gets the options too;
    listing them in ``parameters`` (:func:`_offset_parameters`) lets ``--effects`` set them.
    """

    needs_coefficients = True

    def __init__(self, **options):
        # offset options a plugin does not list in ``parameters`` (its groups depend on options)
        offsets = {k: options.pop(k) for k in list(options) if k.startswith(OFFSET_OPTION) and k not in self.parameters}
        super().__init__(**options)
        self.options.update(offsets)
        groups = self.shifted_members()
        for key in [k for k, v in self.options.items() if k.startswith(OFFSET_OPTION) and v is not None]:
            if key[len(OFFSET_OPTION) :] not in groups:
                raise ConfigError(
                    f"effect {self.name!r}: option {key} names no group of this effect; its offsets: "
                    f"{', '.join(OFFSET_OPTION + g for g in groups)}"
                )
            try:
                self.options[key] = parse_time(self.options[key])
            except (TypeError, ValueError):
                raise ConfigError(
                    f"effect {self.name!r}: {key}={self.options[key]!r} is not an offset in seconds "
                    f"(e.g. {self.name}:{key}=0.35s)"
                ) from None

    def option_unit(self, key: str) -> str | None:
        """The offsets ``offset.<group>`` are times [s] (printed ``offset.sc1=0.35s``)."""
        return "s" if key.startswith(OFFSET_OPTION) else super().option_unit(key)

    @property
    def searched(self) -> dict:  # type: ignore[override]  # a class attribute in Effect (plugins set it so), computed here
        """``offset.<group> -> (-inf, inf, "linear")``: one offset [s] per group of
        :meth:`shifted_members` (the search's span comes from the settings)."""
        return {f"{OFFSET_OPTION}{g}": (-np.inf, np.inf, "linear") for g in self.shifted_members()}

    def unresolved(self) -> list[str]:
        """The searched options resolved before the fit: none of the offsets, which are
        searched where the model's columns are built (they need the fitted linear
        coefficients and the model's other columns; :meth:`open_offsets`)."""
        return [k for k in super().unresolved() if not k.startswith(OFFSET_OPTION)]

    def reshaped(self) -> None:
        """None: the offsets are searched again at every fit of the model (:meth:`unresolved`)."""
        return None

    def fixed_offsets(self) -> dict[str, float]:
        """Group -> offset [s] given as an option (the group's expansion point)."""
        return {
            g: float(self.options[f"{OFFSET_OPTION}{g}"])
            for g in self.shifted_members()
            if self.options.get(f"{OFFSET_OPTION}{g}") is not None
        }

    def open_offsets(self) -> list[str]:
        """Groups whose offset is not given (searched)."""
        fixed = self.fixed_offsets()
        return [g for g in self.shifted_members() if g not in fixed]

    def without_offsets(self) -> _Linearised:
        """The same effect with every offset unset (its Taylor columns do not depend on them)."""
        return self.with_options(**dict.fromkeys(self.searched))

    def _groups(self) -> dict:
        raise NotImplementedError

    def columns(self, data):
        cols = []
        for gname, members in self._groups().items():
            for order in (1, 2):
                parts = []
                for cname in members:
                    m, a, s = cname.split(".")
                    link, delayed = placement(m, s)
                    if self._shifts_delay() and not delayed:
                        continue
                    coef = data.coefficient(cname)
                    series = derivative(data.witness(m, a), data.fs, order) * coef / (1 if order == 1 else 2)
                    parts.append(Part(link, series, delayed))
                if parts:
                    cols.append(
                        Column(
                            f"{self.name}.{gname}.d{order}",
                            parts,
                            "s" if order == 1 else "s^2",
                            0.1 if order == 1 else 0.01,
                        )
                    )
        return cols

    def _shifts_delay(self) -> bool:
        return False

    #: sign of the first-order term (data hold w(t + sign * epsilon))
    d1_sign = 1.0

    def shifted_members(self) -> dict[str, list[str]]:
        """Group -> names of the linear coefficients whose witnesses the group's offset
        shifts (``ltt-error``: the tx terms only); groups without one are left out."""
        out = {}
        for gname, members in self._groups().items():
            kept = [c for c in members if not (self._shifts_delay() and not c.endswith(".tx"))]
            if kept:
                out[gname] = kept
        return out

    def tdi_terms(self, coefficients) -> list[tuple]:
        """The columns as combinations of time derivatives of the TTL regressors' TDI:
        ``[(column, unit, prior_scale, [(ttl_name, derivative_order, factor), ...]), ...]``.

        ``d/dt TDI(x) = TDI(dx/dt)`` up to the arms' rate of change (``dtau/dt ~ 1e-8``), so
        these equal :meth:`columns` through TDI to that accuracy, at the cost of two
        derivatives of the 24 TDI regressors instead of a TDI per column."""
        out = []
        for gname, members in self.shifted_members().items():
            for order in (1, 2):
                terms = []
                for cname in members:
                    c = float(np.asarray(coefficients)[COEFFICIENT_NAMES.index(cname)])
                    terms.append((cname, order, c * (self.d1_sign if order == 1 else 0.5)))
                if terms:
                    out.append(
                        (
                            f"{self.name}.{gname}.d{order}",
                            "s" if order == 1 else "s^2",
                            0.1 if order == 1 else 0.01,
                            terms,
                        )
                    )
        return out


#: Lagrange order of the off-centre stencils at the end of a chunk (a high order would
#: extrapolate wildly; cubic keeps the local error at a few per cent of the effect)
FALLBACK_ORDER = 3


def _read_at(x: np.ndarray, pos: np.ndarray, order: int) -> np.ndarray:
    """``x`` (m,) at fractional sample positions ``pos``: centred Lagrange taps
    (:func:`ttlcore.tdi.interpolation.shift_taps`), off-centre stencils where those leave the data."""

    out = apply_taps(x, shift_taps(pos - np.arange(pos.size), pos.size, order))
    bad = ~np.isfinite(out)
    if bad.any():
        out[bad] = _lagrange_at(x[None, :], pos[bad], FALLBACK_ORDER)[0]
    return out


def _lagrange_at(x: np.ndarray, pos: np.ndarray, order: int) -> np.ndarray:
    """``x`` (rows, m) read at fractional sample positions ``pos`` (k,) with a Lagrange
    stencil of ``order + 1`` points centred where possible and moved inside ``[0, m)``
    otherwise (off-centre near the end of a chunk)."""
    m = x.shape[-1]
    npts = order + 1
    start = np.clip(np.floor(pos).astype(int) - (order - 1) // 2, 0, m - npts)
    nodes = start[:, None] + np.arange(npts)[None, :]
    w = np.ones(nodes.shape)
    for j in range(npts):
        for l in range(npts):
            if l != j:
                w[:, j] *= (pos - nodes[:, l]) / (nodes[:, j] - nodes[:, l])
    return np.einsum("rkp,kp->rk", x[:, nodes], w)


class ShiftInjection(EffectInjection):
    """Exact injection of the shifted-witness effects (``timing-offset``, ``ltt-error``).

    ``timing-offset`` (DWS of spacecraft s stamped ``delta_s`` late): adds
    ``ttl(angles at t + delta) - ttl(angles at t)`` with the true coefficients, Rx terms
    read at ``t + delta`` and Tx terms at ``t - tau + delta``.  ``ltt-error``: adds
    ``-(1/c) C_tx [D_ij^(tau + eps) - D_ij^(tau)] w``, the tx terms delayed by the wrong
    light travel time.  Values: the ``.d1`` column of a group gives its ``delta`` or ``eps``
    [s]; ``.d2`` values are ignored (they are ``delta^2``, implied).

    Reading at ``t + delta`` needs samples after the chunk: the simulator passes the next
    :data:`ttlcore.sim.injection.LOOKAHEAD` samples (``ChunkContext.*_ahead``), so the Lagrange
    stencils (order 31, the simulator's) stay centred and chunking is invisible for
    ``|delta|`` up to about 12 s at 4 Hz; beyond, the stencil moves back inside (off-centre).
    """

    def link_signal(self, ctx: ChunkContext) -> np.ndarray:
        eff = self.effect
        assert isinstance(eff, _Linearised)  # the injection of the shifted-witness effects only
        n, h, fs = ctx.n, ctx.h, ctx.fs
        # (24 or 6, h + n + look-ahead): the samples after the chunk keep the stencils centred
        ahead = ctx.phi_dot_ahead is not None
        coeffs = np.concatenate([ctx.coefficients, ctx.coefficients_ahead], axis=1) if ahead else ctx.coefficients
        vel = {
            "phi": np.concatenate([ctx.phi_dot, ctx.phi_dot_ahead], axis=1) if ahead else ctx.phi_dot,
            "eta": np.concatenate([ctx.eta_dot, ctx.eta_dot_ahead], axis=1) if ahead else ctx.eta_dot,
        }
        shifts = {g: self.values.get(f"{eff.name}.{g}.d1", 0.0) for g in eff._groups()}
        order = min(31, ctx.interpolation_order)
        out = np.zeros((6, n))
        for g, members in eff._groups().items():
            eps = shifts[g]
            if eps == 0.0:
                continue
            if eff._shifts_delay():  # ltt-error: the delay of the tx terms, not the DWS time
                link = g
                k = LINKS.index(link)
                src = np.zeros(coeffs.shape[1])
                for cname in members:
                    m, a, _ = cname.split(".")
                    src += coeffs[COEFFICIENT_NAMES.index(cname)] * vel[a][MOSAS.index(m)]
                tau = ctx.ltt[k]
                if (tau.max() + abs(eps)) * fs + (order - 1) // 2 > h:
                    raise ConfigError(
                        f"injection {self.name!r}: |eps| = {abs(eps)} s too large for the simulator's history"
                    )
                pos_true = h + np.arange(n) - tau * fs
                pos_wrong = pos_true - eps * fs
                out[k] += -(_read_at(src, pos_wrong, order) - _read_at(src, pos_true, order)) / C
                continue
            for cname in members:
                m, a, s = cname.split(".")
                src = coeffs[COEFFICIENT_NAMES.index(cname)] * vel[a][MOSAS.index(m)]
                if s == "rx":
                    k = LINKS.index(m)
                    pos = h + np.arange(n, dtype=float)
                else:
                    k = LINKS.index(reverse(m))
                    pos = h + np.arange(n) - ctx.ltt[k] * fs
                out[k] += -(_read_at(src, pos + eps * fs, order) - _read_at(src, pos, order)) / C
        return out

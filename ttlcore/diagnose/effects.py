"""Model effects: named groups of extra regressors for the TTL fit, and their injections.

The linear TTL model (docs/physics.md, measurement model; paper eq. (3) differentiated)

    ttl_ij = -(1/c) [ C[ij,phi,rx] phi'_ij + C[ij,eta,rx] eta'_ij
                      + D_ij( C[ji,phi,tx] phi'_ji + C[ji,eta,tx] eta'_ji ) ]

is one hypothesis among many.  An *effect* is a physically motivated set of extra terms in
``eta``, linear in its parameters, written as regressor *columns*: each column is a sum of
*parts*, a witness series built from the telemetry (DWS readouts, time, delays, fitted
coefficients) placed on a link, either undelayed (``extra=()``, the Rx placement) or after
the delay ``D_link`` (``extra=(link,)``, the Tx placement).  A column enters TDI exactly as
the 24 TTL regressors do (:func:`columns_tdi`, the same :class:`ttlcore.tdi.combinations.BuiltCombination`
and delay taps), so ``eta = sum_k C_k w_k + sum_e theta_e col_e + noise`` is fitted by the
same generalised least squares (:mod:`ttlcore.estimate.fit`).

Witness convention: ``w[m, a] = -DWS_a[m] / c`` (rad/s over m/s), so that a coefficient in
m/rad times ``w`` is fractional frequency (docs/physics.md, units).

The same column definitions, evaluated on the *true* angular velocities of a simulated
chunk, give the effect's injection (:class:`EffectInjection`): the simulator adds
``sum_e theta_e col_e`` to ``eta`` (Tx parts through the simulator's own delays,
:attr:`ttlcore.sim.injection.ChunkContext.delayed_onto_links`), and the diagnosis sees the
same columns built from the noisy DWS readouts - exactly as for the linear TTL itself.
Effects whose exact form is nonlinear in their parameter (a timing offset, a light-travel
time error) carry an exact injection and a Taylor expansion to second order in the fit.

Effects are looked up by name (:data:`EFFECTS`), from a user's Python file
(``--effect-module PATH``, :func:`load_effect_module`) or from installed packages through
the entry-point group ``ttl.effects`` (:func:`available_effects`); see
``docs/diagnostics.md`` for the plugin interface.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from importlib import metadata
from math import factorial
from pathlib import Path
from typing import ClassVar, Self

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..conventions import (
    ANGLES,
    COEFFICIENT_NAMES,
    DAY,
    LINKS,
    MOSAS,
    SIDES,
    C,
    local_spacecraft,
    parse_duration,
    reverse,
)
from ..errors import ConfigError
from ..sim.injection import ChunkContext, load_module
from ..tdi.combinations import MICHELSON
from ..tdi.engine import Part as EnginePart
from ..tdi.engine import tdi_columns
from ..tdi.interpolation import apply_taps, shift_taps
from ..tdi.regressors import witness_placement as placement

log = logging.getLogger(__name__)

#: Entry-point group under which installed packages register effect classes.
ENTRY_POINT_GROUP = "ttl.effects"


# ---------------------------------------------------------------------------
# Columns and inputs
# ---------------------------------------------------------------------------


@dataclass
class Part:
    """One witness series placed on a link.

    Attributes
    ----------
    link : str
        Link ``ij`` (received at SC i) whose ``eta`` the series enters.
    series : ndarray, shape (n,)
        The series [fractional frequency per unit of the column's parameter].
    delayed : bool
        False: enters ``eta_ij`` as is (Rx placement).  True: enters as ``D_ij series``
        (Tx placement, the series belongs to the transmitting MOSA ``ji``).
    """

    link: str
    series: np.ndarray | None  # None in the columns of names only (EffectInput.names_only)
    #: False/0: undelayed; True/1: ``D_link series``; an integer n: n delays of the link
    #: (``D_link ... D_link series``, the witness library's "delayed nL")
    delayed: bool | int = False
    #: ``(mosa, angle)`` if the series is the plain witness ``-DWS/c`` of that channel: the
    #: diagnosis then includes its readout noise in the errors-in-variables correction
    channel: tuple | None = None
    #: with ``channel``: the series is ``modulation * witness`` for a slowly varying factor
    #: (a drift's ``(t - t_ref) / day``, a step's ``H(t - t_step)``, same samples), and the
    #: readout noise enters modulated alike
    modulation: np.ndarray | None = None

    @property
    def extra(self) -> tuple:
        return (self.link,) * int(self.delayed)


@dataclass
class Column:
    """One regressor column: ``name`` (unique, ``<effect>.<detail>``), its parts, its unit
    and the prior scale of its parameter (standard deviation of the zero-mean Gaussian prior
    of the exact linear-Gaussian Bayes factor, :func:`ttlcore.diagnose.diagnoser.log_bayes_factor`)."""

    name: str
    parts: list
    unit: str = ""
    prior_scale: float = 1.0
    #: optional frequency response ``f [Hz] -> complex (m,)`` of a filter applied to the
    #: column's witness before it enters the link (a frequency-dependent coupling); the
    #: diagnosis multiplies the column's spectrum, and its readout noise, by it (a linear
    #: time-invariant filter commutes with TDI up to the arms' rate of change, ~1e-8)
    response: object = None
    #: columns of one effect with the same ``base`` share their parts (only the response
    #: differs): their TDI is computed once
    base: str = ""


@dataclass
class EffectInput:
    """What effects build their columns from.

    In the diagnosis: the telemetry's DWS readouts (with readout noise) and the fitted
    linear coefficients.  In the simulator: the true angular velocities of a chunk with
    ``history`` leading samples and the true coefficients.

    Attributes
    ----------
    t : ndarray (n,)
        Sample times [s].
    fs : float
        Sampling rate [Hz].
    phi_dot, eta_dot : ndarray (6, n)
        Angular velocities [rad/s] of the six MOSAs (MOSA order).
    ltt : ndarray (6, n)
        Light travel times [s] (LINKS order).
    coefficients : ndarray (24,) or (24, n), optional
        Linear TTL coefficients [m/rad] (fitted, or true in the simulator).
    angle0 : ndarray (2, 6)
        Angles [rad] just before the first sample (phi, eta): the integration constant of
        :attr:`angles`.
    t_ref : float
        Reference time of time-modulated effects [s] (the middle of the data in the
        diagnosis, the effect's own ``t_ref`` in the simulator).
    """

    t: np.ndarray
    fs: float
    phi_dot: np.ndarray
    eta_dot: np.ndarray
    ltt: np.ndarray
    coefficients: np.ndarray | None = None
    angle0: np.ndarray = field(default_factory=lambda: np.zeros((2, 6)))
    t_ref: float = 0.0
    #: only the column names are wanted (effects may skip options they need for values)
    names_only: bool = False
    _angles: tuple | None = None

    @property
    def n(self) -> int:
        return self.t.size

    def velocity(self, angle: str) -> np.ndarray:
        return {"phi": self.phi_dot, "eta": self.eta_dot}[angle]

    def witness(self, mosa: str, angle: str) -> np.ndarray:
        """``-DWS_angle[mosa] / c`` (the TTL witness)."""
        return -self.velocity(angle)[MOSAS.index(mosa)] / C

    @property
    def angles(self) -> tuple[np.ndarray, np.ndarray]:
        """``(phi, eta)`` angles [rad], (6, n) each: running integral of the velocities
        (rectangle rule, as the simulator's truth angles) from :attr:`angle0`."""
        if self._angles is None:
            self._angles = tuple(
                self.angle0[i][:, None] + np.cumsum(v, axis=1) / self.fs
                for i, v in enumerate((self.phi_dot, self.eta_dot))
            )
        return self._angles

    def coefficient(self, name: str) -> np.ndarray | float:
        """Coefficient ``name`` [m/rad] (scalar or series); ConfigError if none are known."""
        if self.coefficients is None:
            raise ConfigError("this effect needs the linear TTL coefficients (fit linear-ttl first)")
        return np.asarray(self.coefficients)[COEFFICIENT_NAMES.index(name)]


def filtered(x: np.ndarray, fs: float, response) -> np.ndarray:
    """``x`` through the filter of frequency response ``response(f)``, applied on the
    series' own FFT grid (zero-padded to twice its length: no wrap-around for impulse
    responses shorter than the series).  NaN samples count as zero."""
    return filtered_many(x, fs, [response])[0]


def filtered_many(x: np.ndarray, fs: float, responses, transform: tuple | None = None) -> list[np.ndarray]:
    """``x`` through each filter of ``responses`` (:func:`filtered`), the series'
    transform computed once (or given: ``transform``, :func:`filter_transform` of ``x``,
    for many calls on one series)."""
    f, X, n = transform if transform is not None else filter_transform(x, fs)
    return [np.fft.irfft(X * r(f), 2 * n)[..., :n] for r in responses]


def filter_transform(x: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The transform :func:`filtered_many` filters ``x`` with: ``(f, X, n)``, the series
    (NaN as zero) zero-padded to twice its length ``n``."""
    x = np.nan_to_num(np.asarray(x, dtype=float))
    n = x.shape[-1]
    nfft = 2 * n
    return np.fft.rfftfreq(nfft, 1.0 / fs), np.fft.rfft(x, nfft), n


def partner(mosa: str) -> str:
    """The other MOSA on the same spacecraft (``12`` <-> ``13``, ``23`` <-> ``21``, ``31`` <-> ``32``)."""
    i = mosa[0]
    return next(m for m in MOSAS if m[0] == i and m != mosa)


# central finite differences (Fornberg): exact for polynomials of degree 2 HALF, close to the
# spectral derivative up to ~0.9 of Nyquist for band-limited series
_FD_HALF = 12


def _fd_weights(order: int, half: int = _FD_HALF) -> np.ndarray:
    j = np.arange(1, half + 1)

    base = np.array([factorial(half) ** 2 / (factorial(half - k) * factorial(half + k)) for k in j]) * (-1.0) ** (j + 1)
    if order == 1:
        c = base / j
        return np.r_[-c[::-1], 0.0, c]
    c = 2 * base / j**2
    return np.r_[c[::-1], -2 * np.sum(c), c]


def derivative(x: np.ndarray, fs: float, order: int = 1) -> np.ndarray:
    """First or second time derivative by a 25-point central difference along the last
    axis; the first and last 12 samples are NaN (they are outside the valid TDI output
    anyway or inside the segment window's taper)."""
    w = _fd_weights(order) * fs**order
    x = np.asarray(x, dtype=float)
    out = np.full(x.shape, np.nan)

    win = sliding_window_view(x, w.size, axis=-1)
    out[..., _FD_HALF:-_FD_HALF] = win @ w
    return out


# ---------------------------------------------------------------------------
# Effects
# ---------------------------------------------------------------------------


def _split_list(value, allowed, what) -> tuple:
    if value is None or value == "all":
        return tuple(allowed)
    items = value if isinstance(value, (list, tuple)) else [s for s in str(value).replace("+", ",").split(",") if s]
    bad = [s for s in items if s not in allowed]
    if bad:
        raise ConfigError(f"{what}: unknown {bad}; known: {', '.join(allowed)}")
    return tuple(items)


class Effect:
    """Base class of model effects (subclass it for a plugin, see ``docs/diagnostics.md``).

    Class attributes
    ----------------
    name : str
        Registry name (``--effects``, ``--inject``).
    title : str
        One line.
    physics : str
        The physical explanation shown in reports and docs.
    parameters : dict
        Options with their defaults (``mosas``, ``angles``, ``sides`` restrict the effect
        to a subset of MOSAs, angles and sides where meaningful).
    needs_coefficients : bool
        Columns use the linear coefficients (linearised effects).
    searched : dict
        ``option -> (low, high, "log"|"linear")``: nonlinear parameters the diagnosis
        searches when the option is not given (:func:`ttlcore.diagnose.search.profile_search`).

    Instances hold the option values (``Effect(**options)``); :meth:`columns` builds the
    regressor columns, :meth:`injection` the simulator injection.
    """

    name = "effect"
    title = ""
    physics = ""
    parameters: dict = {}
    needs_coefficients = False
    #: where a plugin effect class was loaded from (:func:`load_effect_module`)
    _ttl_module_path: ClassVar[str]

    def __init__(self, **options):
        unknown = set(options) - set(self.parameters)
        if unknown:
            raise ConfigError(
                f"effect {self.name!r}: unknown option(s) {sorted(unknown)}; "
                f"options: {', '.join(self.parameters) or 'none'}"
            )
        self.options = {**self.parameters, **options}
        for key in ("mosas", "angles", "sides"):  # validate the selections now, naming the option
            if key in self.parameters:
                getattr(self, key)

    # selections shared by the coefficient-based effects
    @property
    def mosas(self) -> tuple:
        return _split_list(self.options.get("mosas"), MOSAS, f"effect {self.name!r} mosas")

    @property
    def angles(self) -> tuple:
        return _split_list(self.options.get("angles"), ANGLES, f"effect {self.name!r} angles")

    @property
    def sides(self) -> tuple:
        return _split_list(self.options.get("sides"), SIDES, f"effect {self.name!r} sides")

    def columns(self, data: EffectInput) -> list[Column]:
        """The regressor columns built from ``data``."""
        raise NotImplementedError

    def column_names(self) -> list[str]:
        """Names of the columns (without building them), for parsing injection values."""
        t = np.arange(64.0)
        z = np.zeros((6, 64))
        data = EffectInput(
            t=t,
            fs=1.0,
            phi_dot=z,
            eta_dot=z,
            ltt=z + 8.3,
            coefficients=np.zeros(len(COEFFICIENT_NAMES)),
            names_only=True,
        )
        return [c.name for c in self.columns(data)]

    def describe(self) -> dict:
        d = {"effect": self.name, "options": {k: v for k, v in self.options.items() if v != self.parameters.get(k)}}
        module = getattr(type(self), "_ttl_module_path", None)
        if module:
            d["effect_module"] = module
        return d

    def spec(self, sep: str = ",") -> str:
        """The spelling ``name[:key=value,...]`` of this effect (:func:`parse_effect_spec`);
        ``sep=";"`` gives the command line's (``--effects``, where ``,`` separates effects)."""
        opts = {k: v for k, v in self.options.items() if v != self.parameters.get(k)}
        if not opts:
            return self.name
        return (
            self.name
            + ":"
            + sep.join(f"{k}={'+'.join(v) if isinstance(v, (list, tuple)) else v}" for k, v in opts.items())
        )

    def cli_spec(self) -> str:
        """The ``--effects`` spelling (options separated by ``;``)."""
        return self.spec(";")

    #: nonlinear parameters the diagnosis searches when their option is not given:
    #: ``option -> (low, high, scale)`` with scale ``"log"`` or ``"linear"``
    #: (:func:`ttlcore.diagnose.search.profile_search`)
    searched: dict = {}

    def unresolved(self) -> list[str]:
        """Searched options without a value (the diagnosis finds them)."""
        return [k for k in self.searched if self.options.get(k) is None]

    def with_options(self, **options) -> Self:
        """A copy with some options replaced (searched parameters filled in)."""
        new = type(self)(**{**{k: v for k, v in self.options.items() if v != self.parameters.get(k)}, **options})
        return new

    def injection(self, values: dict, name: str | None = None) -> EffectInjection:
        """Simulator injection adding ``sum_col values[col] * col`` (true angles) to eta."""
        return EffectInjection(self, values, name)

    def signal(self, data: EffectInput, values: dict, delayed_onto_links, history: int) -> np.ndarray:
        """The injected eta signal (6, n) for ``values`` (column name -> parameter value):
        Rx parts are taken after ``history`` samples, Tx parts through
        ``delayed_onto_links`` (the simulator's true delays)."""
        n = data.n - history
        out = np.zeros((6, n))
        tx = np.zeros((6, data.n))
        for col in self.columns(data):
            v = values.get(col.name, 0.0)
            if v == 0.0:
                continue
            for p in col.parts:
                series = p.series if col.response is None else filtered(p.series, data.fs, col.response)
                if int(p.delayed) > 1:
                    raise ConfigError(
                        f"effect {self.name!r}: the simulator injects one delay per part, not {int(p.delayed)}"
                    )
                if p.delayed:  # D_ij x_ji: row of the transmitting MOSA ji
                    tx[LINKS.index(reverse(p.link))] += v * series
                else:
                    out[LINKS.index(p.link)] += v * series[history:]
        if np.any(tx):
            out += delayed_onto_links(tx)
        return out


class LinearTTL(Effect):
    name = "linear-ttl"
    title = "linear tilt-to-length coupling (the 24 coefficients)"
    physics = (
        "Angular jitter of the receiving (rx) and transmitting (tx) MOSA couples linearly into the "
        "measured length, with one coefficient per MOSA, angle and side (paper eq. 3; docs/physics.md)."
    )
    parameters = {"mosas": "all", "angles": "all", "sides": "all"}

    def columns(self, data):
        cols = []
        for m in MOSAS:
            for a in ANGLES:
                for s in SIDES:
                    if m in self.mosas and a in self.angles and s in self.sides:
                        link, delayed = placement(m, s)
                        cols.append(
                            Column(f"{m}.{a}.{s}", [Part(link, data.witness(m, a), delayed, (m, a))], "m/rad", 2.3e-3)
                        )
        return cols


class Drift(Effect):
    name = "drift"
    title = "coefficients drifting linearly in time"
    physics = (
        "Thermal relaxation or slow alignment changes make the coupling coefficients vary with time: "
        "C(t) = C + r (t - t_ref). The extra term r (t - t_ref) w enters each link like the coefficient "
        "it modifies (rx undelayed, tx after the light travel time, with the time of emission)."
    )
    parameters = {"mosas": "all", "angles": "all", "sides": "all", "t_ref": None}

    def columns(self, data):
        t_ref = data.t_ref if self.options.get("t_ref") is None else float(self.options["t_ref"])
        tau = (data.t - t_ref) / DAY
        cols = []
        for m in self.mosas:
            for a in self.angles:
                for s in self.sides:
                    link, delayed = placement(m, s)
                    cols.append(
                        Column(
                            f"drift.{m}.{a}.{s}",
                            [Part(link, tau * data.witness(m, a), delayed, (m, a), tau)],
                            "m/rad/day",
                            1e-3,
                        )
                    )
        return cols


class Step(Effect):
    name = "step"
    title = "coefficient step at a given or searched time"
    physics = (
        "A realignment, a thermal event or a micrometeoroid hit changes the coupling abruptly at t_step: "
        "C(t) = C + J H(t - t_step). The jump J multiplies the witness from t_step on (tx: emission time)."
    )
    parameters = {"mosas": "all", "angles": "all", "sides": "all", "t_step": None}
    #: the step time [s], searched over the data (its own evaluator: :func:`ttlcore.diagnose.search.step_time_search`)
    searched = {"t_step": (-np.inf, np.inf, "linear")}

    def columns(self, data):
        if self.options.get("t_step") is None and data.names_only:
            return [
                Column(f"step.{m}.{a}.{s}", [], "m/rad", 1e-3)
                for m in self.mosas
                for a in self.angles
                for s in self.sides
            ]
        if self.options.get("t_step") is None:
            raise ConfigError(
                "effect 'step' needs t_step (a time, e.g. step:t_step=50000) or a search (ttl diagnose searches it)"
            )

        ts = parse_duration(self.options["t_step"])
        h = (data.t >= ts).astype(float)
        cols = []
        for m in self.mosas:
            for a in self.angles:
                for s in self.sides:
                    link, delayed = placement(m, s)
                    cols.append(
                        Column(
                            f"step.{m}.{a}.{s}", [Part(link, h * data.witness(m, a), delayed, (m, a), h)], "m/rad", 1e-3
                        )
                    )
        return cols


class CrossCoupling(Effect):
    name = "cross-coupling"
    title = "jitter of the neighbouring MOSA on the same spacecraft"
    physics = (
        "Stray light, the shared optical bench or mechanical coupling let the angle of the other MOSA on "
        "the same spacecraft (12 <-> 13, 23 <-> 21, 31 <-> 32) couple into a MOSA's received (rx) or "
        "transmitted (tx) beam path. Distinguishable from the linear TTL only through the MOSA jitter "
        "(the spacecraft jitter is common to both MOSAs). Rx side only: a channel on both sides "
        "of both MOSAs forms, with the linear rx and tx terms, the pattern of a laser's frequency noise "
        "(-1 on the two undelayed links of its spacecraft, +1 delayed on the two links it feeds), "
        "which TDI cancels - the tx cross terms are absorbed by the linear coefficients."
    )
    parameters = {"mosas": "all", "angles": "all", "sides": "rx"}

    def __init__(self, **options):
        super().__init__(**options)
        if set(self.sides) == {"rx", "tx"}:
            raise ConfigError(
                "effect 'cross-coupling': sides rx and tx together are unobservable with the linear TTL "
                "(they form a laser-noise pattern TDI cancels); use sides=rx or sides=tx"
            )

    def columns(self, data):
        cols = []
        for m in self.mosas:
            for a in self.angles:
                for s in self.sides:
                    link, delayed = placement(m, s)
                    cols.append(
                        Column(
                            f"cross.{m}.{a}.{s}",
                            [Part(link, data.witness(partner(m), a), delayed, (partner(m), a))],
                            "m/rad",
                            1e-3,
                        )
                    )
        return cols


class SecondOrder(Effect):
    name = "second-order"
    title = "second-order angle terms (squares and products, static offsets)"
    physics = (
        "The path length depends quadratically on the angles near the optimal alignment: "
        "l = C1 a + K (a + a0)(b + b0) for a, b in {phi, eta}. Differentiated, K (a' b + a b') adds to "
        "eta; the static offsets a0, b0 only add K (a0 b' + b0 a'), absorbed by the linear "
        "coefficients (which then differ from the linear-only truth by K a0, K b0). "
        "Angles are the running integral of the DWS velocities."
    )
    parameters = {"mosas": "all", "sides": "rx", "terms": "phiphi,etaeta,phieta", "offset_phi": 0.0, "offset_eta": 0.0}
    TERMS = ("phiphi", "etaeta", "phieta")

    @property
    def terms(self) -> tuple:
        return _split_list(self.options.get("terms"), self.TERMS, "effect 'second-order' terms")

    def columns(self, data):
        ang = dict(zip(ANGLES, data.angles))
        off = {"phi": float(self.options["offset_phi"]), "eta": float(self.options["offset_eta"])}
        cols = []
        for m in self.mosas:
            k = MOSAS.index(m)
            for term in self.terms:
                a, b = term[:3], term[3:]
                x, y = ang[a][k] + off[a], ang[b][k] + off[b]
                dx, dy = data.velocity(a)[k], data.velocity(b)[k]
                series = -(dx * y + x * dy) / C
                for s in self.sides:
                    link, delayed = placement(m, s)
                    cols.append(Column(f"quad.{m}.{term}.{s}", [Part(link, series, delayed)], "m/rad^2", 1e3))
        return cols


#: prefix of the option that gives a shifted-witness group's offset [s] (``offset.sc1``)
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
                self.options[key] = float(self.options[key])
            except (TypeError, ValueError):
                raise ConfigError(
                    f"effect {self.name!r}: {key}={self.options[key]!r} is not an offset in seconds"
                ) from None

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


class TimingOffset(_Linearised):
    name = "timing-offset"
    title = "timing offset between DWS and phasemeter readouts"
    physics = (
        "The DWS samples of a spacecraft are time-stamped delta late with respect to the phasemeter "
        "(a processing latency, a misaligned data stream): the length readout holds C DWS(t + delta). "
        "To second order C [w + delta w' + delta^2/2 w''], with the fitted C."
    )
    parameters = {"per": "sc", **_offset_parameters(["sc1", "sc2", "sc3", *MOSAS, "all"])}

    def _groups(self):
        per = self.options.get("per", "sc")
        if per not in ("sc", "mosa", "global"):
            raise ConfigError("effect 'timing-offset' per: expected sc, mosa or global")
        groups: dict = {}
        for cname in COEFFICIENT_NAMES:
            m = cname.split(".")[0]
            key = {"sc": f"sc{local_spacecraft(m)}", "mosa": m, "global": "all"}[per]
            groups.setdefault(key, []).append(cname)
        return groups

    def injection(self, values, name=None):
        return ShiftInjection(self, values, name)


class LightTravelTimeError(_Linearised):
    name = "ltt-error"
    title = "error in the light travel time of the delayed (tx) terms"
    physics = (
        "The tx jitter reaches the receiver one light travel time after emission; if the delay used to "
        "place the tx witnesses (the telemetry's ranging) is off by eps on link ij, the fit misses "
        "C D_ij [w(t - eps) - w] = C D_ij [-eps w' + eps^2/2 w'']. One eps per link."
    )
    parameters = {"links": "all", **_offset_parameters(LINKS)}

    d1_sign = -1.0

    def _shifts_delay(self):
        return True

    def _groups(self):
        links = _split_list(self.options.get("links"), LINKS, "effect 'ltt-error' links")
        groups: dict = {}
        for cname in COEFFICIENT_NAMES:
            m, _, s = cname.split(".")
            if s == "tx" and reverse(m) in links:
                groups.setdefault(reverse(m), []).append(cname)
        return groups

    def columns(self, data):
        cols = super().columns(data)
        for c in cols:  # data hold w(t - eps): first order -eps w'
            if c.name.endswith(".d1"):
                for p in c.parts:
                    p.series = -p.series
        return cols

    def injection(self, values, name=None):
        return ShiftInjection(self, values, name)


def witness_series(data: EffectInput, source: str, derivative_order: int = 0) -> tuple[np.ndarray, tuple | None, str]:
    """A witness series of the library (:mod:`ttlcore.witnesses`) from ``data``.

    ``source`` is ``"<mosa>.<phi|eta>"`` (the witness ``-DWS/c``, its time derivative with
    ``derivative_order=1``) or ``"<mosa>.<phiphi|etaeta|phieta>"`` (``-d/dt(a b) / c``, angles
    integrated from the DWS, as :class:`SecondOrder`).

    Returns
    -------
    series : ndarray (n,)
    channel : tuple or None
        ``(mosa, angle)`` of a plain witness (its readout noise enters the
        errors-in-variables term), None for products.
    unit : str
        Unit of the coefficient.
    """
    mosa, _, kind = str(source).partition(".")
    if mosa not in MOSAS or kind not in ANGLES + SecondOrder.TERMS:
        raise ConfigError(
            f"witness source {source!r}: expected <mosa>.<phi|eta> or <mosa>.<phiphi|etaeta|phieta> "
            f"with mosa in {', '.join(MOSAS)}"
        )
    if kind in ANGLES:
        w = data.witness(mosa, kind)
        if derivative_order:
            return derivative(w, data.fs, 1), (mosa, kind), "m s/rad"
        return w, (mosa, kind), "m/rad"
    if derivative_order:
        raise ConfigError(f"witness source {source!r}: products have no derivative option")
    k = MOSAS.index(mosa)
    ang = dict(zip(ANGLES, data.angles))
    a, b = kind[:3], kind[3:]
    return -(data.velocity(a)[k] * ang[b][k] + ang[a][k] * data.velocity(b)[k]) / C, None, "m/rad^2"


def _int_option(effect, key, allowed) -> int:
    try:
        v = int(float(effect.options.get(key) or 0))
    except ValueError:
        raise ConfigError(
            f"effect {effect.name!r} {key}: expected an integer, got {effect.options.get(key)!r}"
        ) from None
    if v not in allowed:
        raise ConfigError(f"effect {effect.name!r} {key}: expected one of {sorted(allowed)}, got {v}")
    return v


#: Time variations of a placed effect's coupling (option ``vary``, :meth:`_Placed.modulations`).
VARY = ("none", "drift", "step", "cycle")
#: Searched range of the period [s] of ``vary=cycle``: 1 h to 4 days (clipped to twice the
#: analysed span; a longer period is a drift), log scale.
CYCLE_PERIOD = (3600.0, 4 * DAY, "log")


class _Placed(Effect):
    """Effects built on witness series placed on links: either one ``source`` (a library
    witness: channel, link, delay) or the standard placements of ``mosas``/``angles``/``sides``
    (rx: the MOSA's own link, undelayed; tx: the link it transmits on, one delay), optionally
    restricted to ``links``."""

    def placements(self) -> list[tuple[str, str, int]]:
        """``[(source, link, n_delays), ...]``."""
        src = self.options.get("source")
        links = _split_list(self.options.get("links"), LINKS, f"effect {self.name!r} links")
        if src:
            mosa = str(src).split(".")[0]
            link = self.options.get("link") or mosa
            if link not in LINKS:
                raise ConfigError(f"effect {self.name!r} link: unknown {link!r}; known: {', '.join(LINKS)}")
            out = [(str(src), link, _int_option(self, "delay", (0, 1, 2)))]
        elif self.options.get("mosas") is not None:
            out = []
            for m in self.mosas:
                for a in self.angles:
                    for sd in self.sides:
                        link, delayed = placement(m, sd)
                        out.append((f"{m}.{a}", link, int(delayed)))
        else:
            raise ConfigError(
                f"effect {self.name!r} needs source=<mosa>.<angle> (with link=, delay=) "
                f"or mosas= (with angles=, sides=)"
            )
        return [p for p in out if p[1] in links]

    @staticmethod
    def placement_label(source, link, n) -> str:
        return f"{source}>{link}" + (f"+{n}L" if n else "")

    @property
    def vary(self) -> str:
        v = self.options.get("vary") or "none"
        if v not in VARY:
            raise ConfigError(f"effect {self.name!r} vary: expected one of {', '.join(VARY)}, got {v!r}")
        return v

    @property
    def searched(self) -> dict:  # type: ignore[override]  # a class attribute in Effect (plugins set it so), computed here
        """The filter's searched poles (:meth:`filter_searched`) and, with ``vary=cycle``,
        the period [s] of the cycle (:data:`CYCLE_PERIOD`)."""
        out = dict(self.filter_searched())
        if self.vary == "cycle":
            out["period"] = CYCLE_PERIOD
        return out

    def filter_searched(self) -> dict:
        return {}

    def modulations(self, data) -> list[tuple[str, np.ndarray | None]]:
        """Time variation of the effect's coupling (option ``vary``): ``(suffix, factor)``
        pairs, one column per pair and placement.  ``none``: one constant coupling;
        ``drift`` multiplies the witness by ``(t - t_ref) / day`` (the coefficients are the
        rate, per day); ``step`` by ``H(t - t_step)`` (the jump); ``cycle`` by
        ``sin(2 pi (t - t_ref) / period)`` and ``cos(...)`` (a slow periodic variation such
        as a thermal cycle: amplitude and phase are the two linear coefficients, the period
        is searched when not given).  A slow modulation commutes with the filters of
        ``fd-coupling`` to ``1 / (f T)``.  Factors are None on a names-only input."""
        vary = self.vary
        if vary == "none":
            return [("", None)]
        if vary == "cycle":
            suffixes = (".sin", ".cos")
            if data.names_only:
                return [(x, None) for x in suffixes]
            if self.options.get("period") is None:
                raise ConfigError(
                    f"effect {self.name!r} vary=cycle: period not given (the diagnosis searches it: "
                    "ttl diagnose, refit)"
                )
            t_ref = data.t_ref if self.options.get("t_ref") is None else float(self.options["t_ref"])
            phase = 2 * np.pi * (data.t - t_ref) / parse_duration(self.options["period"])
            return [(".sin", np.sin(phase)), (".cos", np.cos(phase))]
        if data.names_only:
            return [("", None)]
        if vary == "drift":
            t_ref = data.t_ref if self.options.get("t_ref") is None else float(self.options["t_ref"])
            return [("", (data.t - t_ref) / DAY)]
        if self.options.get("t_step") is None:
            raise ConfigError(f"effect {self.name!r} vary=step needs t_step")
        return [("", (data.t >= parse_duration(self.options["t_step"])).astype(float))]

    @staticmethod
    def _series(data, src, mod):
        series, channel, unit = witness_series(data, src, 0)
        if mod is not None:
            series = series * mod
        return series, channel, unit

    def _label(self, label, suffix="") -> str:
        vary = self.vary
        at = {
            "drift": self.options.get("t_ref"),
            "step": self.options.get("t_step"),
            "cycle": self.options.get("period"),
        }.get(vary)
        return (label if vary == "none" else f"{label}~{vary}" + (f"@{at}" if at is not None else "")) + suffix


class WitnessEffect(_Placed):
    name = "witness"
    title = "a witness series of the library, fitted with one coefficient each"
    physics = (
        "Any series of the witness library (ttlcore.witnesses: a DWS channel on any link, undelayed or "
        "delayed by one or two light travel times, its time derivative, a product of angles) can couple "
        "into the data with a constant coefficient. The column is the series placed on the link through "
        "the exact time-varying TDI delays; a plain DWS channel carries its readout noise into the "
        "errors-in-variables term."
    )
    parameters = {
        "source": None,
        "link": None,
        "delay": 0,
        "derivative": 0,
        "mosas": None,
        "angles": "all",
        "sides": "rx",
        "links": "all",
        "vary": "none",
        "t_ref": None,
        "t_step": None,
        "period": None,
    }

    def columns(self, data):
        der = _int_option(self, "derivative", (0, 1))
        cols = []
        for src, link, n in self.placements():
            if der and src.split(".")[1] not in ANGLES:
                raise ConfigError(f"effect 'witness' source {src!r}: products have no derivative option")
            for suffix, mod in self.modulations(data):
                series, channel, unit = self._series(data, src, mod)
                label = self._label(("d/dt:" if der else "") + self.placement_label(src, link, n), suffix)
                prior = {"m/rad": 1e-3, "m/rad^2": 1e3}[unit]
                # the time derivative as the filter 2 pi i f: its readout noise follows exactly
                cols.append(
                    Column(
                        f"witness.{label}",
                        [Part(link, series, n, channel, mod)],
                        "m s/rad" if der else unit,
                        prior * 10 if der else prior,
                        response=_derivative_response if der else None,
                    )
                )
        return cols


def _derivative_response(f):
    return 2j * np.pi * np.asarray(f, dtype=float)


def rational_basis(kind: str, f: np.ndarray, f0: float, q: float | None = None) -> list[np.ndarray]:
    """The frequency-dependent coupling basis: one real pole or one complex pole pair
    with a numerator of full degree, ``x = i f / f0``,

    - ``pole1``: ``1/(1 + x)``, ``x/(1 + x)`` (a first-order path of corner ``f0``: low-pass,
      high-pass and constant couplings are combinations);
    - ``pole2``: ``1/D``, ``x/D``, ``x^2/D`` with ``D = 1 + x/q + x^2`` (a resonance at ``f0``
      of quality factor ``q``: its low-pass, band-pass, high-pass and notch forms and the
      constant coupling ``D/D`` are combinations).

    Any coupling ``H(f)`` that is a ratio of polynomials of that order in ``i f`` is fitted
    linearly once the poles are known; the poles are searched (:data:`Effect.searched`).
    """
    x = 1j * np.asarray(f, dtype=float) / float(f0)
    if kind == "pole1":
        D = 1.0 + x
        return [1.0 / D, x / D]
    if q is None:
        raise ValueError(f"a {kind!r} basis needs q")
    D = 1.0 + x / float(q) + x * x
    return [1.0 / D, x / D, x * x / D]


class FrequencyCoupling(_Placed):
    name = "fd-coupling"
    title = "frequency-dependent coupling of a witness (resonance, first-order path)"
    physics = (
        "A witness couples through a path whose gain varies with frequency: a mechanical resonance of "
        "unknown frequency and quality factor (filter=pole2, the default: 1/D, x/D, x^2/D with "
        "D = 1 + x/q + x^2, x = i f/f0) or a first-order low- or high-pass path of unknown corner "
        "(filter=pole1: 1/(1+x), x/(1+x), x = i f/fc). Linear in the numerator coefficients; the poles "
        "(f0, q or fc) are searched by the diagnosis when not given. Place it with source=, link=, "
        "delay= (a library witness) or mosas=, angles=, sides=, links=. On the placement of a linear TTL "
        "coefficient (its own link undelayed, or the link it transmits on after one delay) the constant "
        "coupling is that coefficient: the basis drops one column there (flat=auto, the default; "
        "flat=keep for a model without linear-ttl)."
    )
    parameters = {
        "source": None,
        "link": None,
        "delay": 0,
        "mosas": None,
        "angles": "all",
        "sides": "rx",
        "links": "all",
        "filter": "pole2",
        "f0": None,
        "q": None,
        "fc": None,
        "vary": "none",
        "t_ref": None,
        "t_step": None,
        "period": None,
        "flat": "auto",
    }

    @property
    def kind(self) -> str:
        k = self.options.get("filter") or "pole2"
        if k not in ("pole1", "pole2"):
            raise ConfigError(f"effect 'fd-coupling' filter: expected pole1 or pole2, got {k!r}")
        return k

    def filter_searched(self) -> dict:
        if self.kind == "pole1":
            return {"fc": (1e-3, 2.0, "log")}
        return {"f0": (1e-3, 2.0, "log"), "q": (0.5, 300.0, "log")}

    def response_functions(self) -> list:
        """The basis responses ``f -> complex`` for the current poles.  They share the
        basis: computed once for the frequency array they are called with in turn (the same
        array object, which must not change in place between the calls)."""
        poles: tuple[float, ...]
        if self.kind == "pole1":
            poles, n = (float(self.options["fc"]),), 2
        else:
            poles, n = (float(self.options["f0"]), float(self.options["q"])), 3
        last: list = []  # [(f, basis)]: the last frequency array and its basis

        def basis(f):
            if not (last and last[0][0] is f):
                last[:] = [(f, rational_basis(self.kind, f, *poles))]
            return last[0][1]

        return [functools.partial(lambda f, j: basis(f)[j], j=j) for j in range(n)]

    def holds_flat(self, source: str, link: str, n_delays: int) -> bool:
        """Whether the basis keeps all its columns on this placement.

        The basis spans the constant coupling (``1/(1+x) + x/(1+x) = 1``;
        ``1/D + (x/D)/q + x^2/D = 1``).  On the placement of a linear TTL coefficient
        (:func:`ttlcore.tdi.regressors.witness_placement`: rx on the MOSA's own link,
        undelayed; tx on the link it transmits on, one delay) that constant coupling *is*
        the coefficient's column, so with ``linear-ttl`` in the model the full basis would
        be collinear with it: with ``flat=auto`` (default) and no time variation the last
        basis column is dropped there (the remaining ones and the coefficient span the
        same couplings); ``flat=keep`` keeps it (a model without ``linear-ttl``)."""
        flat = self.options.get("flat") or "auto"
        if flat not in ("auto", "keep"):
            raise ConfigError(f"effect 'fd-coupling' flat: expected auto or keep, got {flat!r}")
        if flat == "keep" or self.vary != "none":
            return True
        mosa, _, angle = source.partition(".")
        return (
            angle not in ANGLES
            or (link, bool(n_delays)) not in (placement(mosa, "rx"), placement(mosa, "tx"))
            or n_delays > 1
        )

    def columns(self, data):
        n_basis = 2 if self.kind == "pole1" else 3
        poles = [k for k in self.unresolved() if k != "period"]
        if poles:
            if not data.names_only:
                raise ConfigError(
                    f"effect 'fd-coupling': {', '.join(poles)} not given "
                    "(the diagnosis searches them: ttl diagnose, refit)"
                )
            resp = [None] * n_basis
        else:
            resp = self.response_functions()
        cols = []
        for src, link, n in self.placements():
            for suffix, mod in self.modulations(data):
                if data.names_only:  # names and responses only (the searches evaluate many poles)
                    series, channel = None, None
                    unit = "m/rad" if src.partition(".")[2] in ANGLES else "m/rad^2"
                else:
                    series, channel, unit = self._series(data, src, mod)
                label = self._label(self.placement_label(src, link, n), suffix)
                parts = [Part(link, series, n, channel, mod)]
                for j in range(n_basis if self.holds_flat(src, link, n) else n_basis - 1):
                    cols.append(
                        Column(
                            f"fd.{label}.b{j}",
                            parts,
                            unit,
                            1e-3 if unit == "m/rad" else 1e3,
                            response=resp[j],
                            base=label,
                        )
                    )
        return cols


#: The named effects.
EFFECTS: dict[str, type] = {
    cls.name: cls
    for cls in (
        LinearTTL,
        Drift,
        Step,
        CrossCoupling,
        TimingOffset,
        SecondOrder,
        LightTravelTimeError,
        WitnessEffect,
        FrequencyCoupling,
    )
}


# ---------------------------------------------------------------------------
# Lookup, parsing, plugins
# ---------------------------------------------------------------------------


def load_effect_module(spec: str) -> list[type[Effect]]:
    """Effect classes of a user module (a ``.py`` path or a dotted name).

    The module lists its classes in ``EFFECTS`` (a list, or a dict name -> class); without
    it, every :class:`Effect` subclass defined in the module is taken.  ConfigError names the
    module if it defines none.
    """
    module = load_module(spec)
    found = getattr(module, "EFFECTS", None)
    if isinstance(found, dict):
        found = list(found.values())
    if found is None:
        found = [
            v
            for v in vars(module).values()
            if isinstance(v, type) and issubclass(v, Effect) and v is not Effect and v.__module__ == module.__name__
        ]
    if not found:
        raise ConfigError(f"{spec}: defines no effect (an Effect subclass, or a list EFFECTS)")
    out = []
    for cls in found:
        if (
            not (isinstance(cls, type) and issubclass(cls, Effect))
            or not getattr(cls, "name", None)
            or cls.name == "effect"
        ):
            raise ConfigError(f"{spec}: {cls!r} is not an Effect subclass with a name")
        if spec.endswith(".py"):
            cls._ttl_module_path = str(Path(spec).resolve())
        else:
            cls._ttl_module_path = spec
        out.append(cls)
    return out


@functools.lru_cache(maxsize=1)
def _entry_point_effects() -> dict[str, type[Effect]]:
    """Effect classes registered by installed packages (scanned once per process)."""
    out: dict[str, type[Effect]] = {}
    eps = metadata.entry_points(group=ENTRY_POINT_GROUP)
    for ep in eps:
        try:
            obj = ep.load()
        except Exception as exc:  # a broken third-party package must not stop the analysis
            log.warning("entry point %s in %s: cannot load (%s)", ep.name, ENTRY_POINT_GROUP, exc)
            continue
        for cls in obj if isinstance(obj, (list, tuple)) else [obj]:
            if isinstance(cls, type) and issubclass(cls, Effect):
                out[cls.name] = cls
    return out


def available_effects(modules=()) -> dict[str, type[Effect]]:
    """Named effects, those of installed packages (entry points ``ttl.effects``) and those of
    the given plugin modules (later ones override earlier ones with the same name)."""
    out = dict(EFFECTS)
    out.update(_entry_point_effects())
    for spec in modules:
        for cls in load_effect_module(spec):
            out[cls.name] = cls
    return out


def parse_effect_spec(spec: str, modules=()) -> tuple[Effect, dict]:
    """``"NAME[:key=value,...]"`` -> (effect instance, column values).

    Keys that are options of the effect set options; keys that are column names (with or
    without the effect prefix, e.g. ``12.phi.rx`` for ``drift.12.phi.rx``) or ``all`` set
    the parameter values of an injection (in the column's unit).  Lists inside an option
    use ``+`` (``mosas=12+13``).
    """
    name, _, rest = str(spec).partition(":")
    name = name.strip()
    effects = available_effects(modules)
    if name not in effects:
        raise ConfigError(f"unknown effect {name!r}; known: {', '.join(sorted(effects))}")
    cls = effects[name]
    options, raw_values = {}, {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"effect {name!r}: expected key=value, got {item!r}")
        if key in cls.parameters:
            options[key] = value
        else:
            try:
                raw_values[key] = float(value)
            except ValueError:
                raise ConfigError(
                    f"effect {name!r}: {key!r} is neither an option ({', '.join(cls.parameters) or 'none'}) "
                    f"nor a column with a number (got {value!r})"
                ) from None
    effect = cls(**options)
    values = {}
    if raw_values:
        names = effect.column_names()
        for key, v in raw_values.items():
            if key == "all":
                values.update(dict.fromkeys(names, v))
                continue
            matches = [n for n in names if n == key or n == f"{_prefix(n)}.{key}" or n.endswith("." + key)]
            if not matches:
                raise ConfigError(
                    f"effect {name!r}: unknown column {key!r}; columns: {', '.join(names[:8])}"
                    + (", ..." if len(names) > 8 else "")
                )
            values.update(dict.fromkeys(matches, v))
    return effect, values


def _prefix(column_name: str) -> str:
    return column_name.split(".", 1)[0]


def make_effects(specs, modules=()) -> list[Effect]:
    """Effect instances from a comma-free list of specs or one comma-separated string of
    names (``"linear-ttl,drift"``)."""
    if isinstance(specs, str):
        specs = [s for s in specs.split(",") if s.strip()]
    return [s if isinstance(s, Effect) else parse_effect_spec(s, modules)[0] for s in specs]


# ---------------------------------------------------------------------------
# Injections
# ---------------------------------------------------------------------------


class EffectInjection:
    """Injection of an effect into the simulator (:mod:`ttlcore.sim.injection` protocol).

    ``values`` maps column names to the true parameter values (column units).
    """

    def __init__(self, effect: Effect, values: dict, name: str | None = None):
        self.effect = effect
        self.values = {k: float(v) for k, v in values.items()}
        unknown = set(self.values) - set(effect.column_names())
        if unknown:
            raise ConfigError(f"injection of {effect.name!r}: unknown columns {sorted(unknown)[:5]}")
        self.name = name or effect.name
        self._angle: np.ndarray | None = (
            None  # running angle integral (phi, eta) at the last sample of the previous chunk
        )
        self._next_n0 = 0

    def describe(self) -> dict:
        return {"kind": "effect", "name": self.name, **self.effect.describe(), "values": dict(self.values)}

    def _input(self, ctx: ChunkContext) -> EffectInput:
        angle0 = np.zeros((2, 6))
        if isinstance(self.effect, SecondOrder):
            # angles need the running integral: chunks must come in order (Simulator.chunks)
            if ctx.n0 == 0:
                self._angle = np.zeros((2, 6))
            elif self._angle is None or ctx.n0 != self._next_n0:
                raise ConfigError(
                    f"injection {self.name!r}: second-order terms need the chunks in order from "
                    f"the start (got sample {ctx.n0}, expected {self._next_n0})"
                )
            # angle just before the first history sample: subtract the history's integral
            hist = np.stack([ctx.phi_dot[:, : ctx.h].sum(axis=1), ctx.eta_dot[:, : ctx.h].sum(axis=1)]) / ctx.fs
            angle0 = self._angle - hist
        t_ref = self.effect.options.get("t_ref")
        data = EffectInput(
            t=ctx.t_ext,
            fs=ctx.fs,
            phi_dot=ctx.phi_dot,
            eta_dot=ctx.eta_dot,
            ltt=np.pad(ctx.ltt, ((0, 0), (ctx.h, 0)), mode="edge"),
            coefficients=ctx.coefficients,
            angle0=angle0,
            t_ref=0.0 if t_ref is None else float(t_ref),
        )
        return data

    def link_signal(self, ctx: ChunkContext) -> np.ndarray:
        data = self._input(ctx)
        out = self.effect.signal(data, self.values, ctx.delayed_onto_links, ctx.h)
        if isinstance(self.effect, SecondOrder):
            phi, eta = data.angles
            self._angle = np.stack([phi[:, -1], eta[:, -1]])
            self._next_n0 = ctx.n0 + ctx.n
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
            if isinstance(eff, LightTravelTimeError):
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


def injection_from_description(description: dict):
    """Rebuild an effect injection from :meth:`EffectInjection.describe` (the hook
    :func:`ttlcore.sim.injection.injection_from_description` calls for kind ``"effect"``)."""
    name = description.get("effect")
    if not name:
        raise ConfigError(f"effect injection description needs 'effect': {description!r}")
    modules = [description["effect_module"]] if description.get("effect_module") else []
    effects = available_effects(modules)
    if name not in effects:
        raise ConfigError(f"unknown effect {name!r} in injection description; known: {', '.join(sorted(effects))}")
    effect = effects[name](**description.get("options", {}))
    return effect.injection(description.get("values", {}), description.get("name"))


def injection_from_spec(spec: str, modules=()) -> EffectInjection:
    """``--inject EFFECT[:key=value,...]`` -> injection (values in the columns' units)."""
    effect, values = parse_effect_spec(spec, modules)
    if not values:
        raise ConfigError(
            f"--inject {spec}: no parameter value given; e.g. --inject "
            f"{effect.name}:{effect.column_names()[0].split('.', 1)[-1]}=VALUE (or all=VALUE)"
        )
    return effect.injection(values)


# ---------------------------------------------------------------------------
# TDI of columns
# ---------------------------------------------------------------------------


def effect_input_from_telemetry(tm, coefficients=None) -> EffectInput:
    """:class:`EffectInput` from a :class:`~ttlcore.io.telemetry.Telemetry` (DWS readouts)."""
    t = tm.t0 + np.arange(tm.size) / tm.fs
    return EffectInput(
        t=t,
        fs=tm.fs,
        phi_dot=np.asarray(tm.dws_phi),
        eta_dot=np.asarray(tm.dws_eta),
        ltt=np.asarray(tm.ltt),
        coefficients=coefficients,
        t_ref=float(t[0] + t[-1]) / 2,
    )


def tdi_in_blocks(
    ltt: np.ndarray,
    fs: float,
    columns=(),
    eta: np.ndarray | None = None,
    *,
    order: int,
    delay_order: int,
    block: int = 43200,
) -> tuple:
    """TDI (X2, Y2, Z2) of regressor columns (:func:`columns_tdi`) and optionally of ``eta``,
    by the block engine :func:`ttlcore.tdi.engine.tdi_columns` (each block with the history
    its delays reach back to; memory does not grow with the data).  The first ~70 s are NaN.

    Parameters
    ----------
    ltt : ndarray, shape (6, n)
        Light travel times [s].
    fs : float
        Sampling rate [Hz].
    columns : list of Column
        Parts sampled like ``ltt``.
    eta : ndarray, shape (6, n), optional
        Link readouts.
    order, delay_order : int
        Lagrange orders of the data and of the delay interpolation.
    block : int
        Kept for callers; the engine chooses its own blocks (~2.2 h at 4 Hz), which bound
        the memory, so the result equals the one-call :func:`columns_tdi` exactly.

    Returns
    -------
    data : ndarray (3, n) or None
        TDI of ``eta``.
    regressors : ndarray (3, len(columns), n)
    """
    parts = _engine_parts(columns, first=1)
    if eta is not None:
        parts += [EnginePart(0, link, (), np.asarray(eta)[k]) for k, link in enumerate(LINKS)]
    out = tdi_columns(parts, 1 + len(columns), ltt, fs, combinations=MICHELSON, order=order, delay_order=delay_order)
    return (None if eta is None else out[:, 0]), out[:, 1:]


def _engine_parts(columns, first: int = 0) -> list:
    """The parts of ``columns`` as :class:`ttlcore.tdi.engine.Part` (column ``first + j``)."""
    return [EnginePart(first + j, p.link, p.extra, p.series) for j, col in enumerate(columns) for p in col.parts]


def columns_tdi(columns: list[Column], built) -> np.ndarray:
    """TDI (the combinations of ``built``, :func:`ttlcore.tdi.combinations.build`) of
    regressor columns: each column is the sum of its parts placed on their links, through
    the block engine :func:`ttlcore.tdi.engine.tdi_columns` - the code path of the 24 TTL
    regressors.

    Returns
    -------
    ndarray, shape (len(built), len(columns), n)
    """
    b = built[0]
    return tdi_columns(
        _engine_parts(columns),
        len(columns),
        b.ltt,
        b.fs,
        history=b.history,
        combinations=[x.combination for x in built],
        order=b.order,
        delay_order=b.delay_order,
    )


def readout_noise_factor(f, shift):
    """Factor of a part's readout-noise response: a time shift [s] (the phase
    ``exp(2 pi i f shift)``) or a frequency response (m,) of a filtered column."""
    if isinstance(shift, np.ndarray):
        return shift[:, None]
    return np.exp(2j * np.pi * f * shift)[:, None] if shift else 1.0


def names_only_input() -> EffectInput:
    """A tiny input with ``names_only=True``: enough for an effect to name its columns."""
    t = np.arange(64.0)
    z = np.zeros((6, 64))
    return EffectInput(t=t, fs=1.0, phi_dot=z, eta_dot=z, ltt=z + 8.3, coefficients=np.zeros(24), names_only=True)

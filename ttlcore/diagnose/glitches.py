"""Glitches and gates: transients a user (or the diagnosis' advice) adds to a model.

docs/diagnostics.md, "Glitches and gates".  Two effects that act on a short span of the
data instead of the whole of it, for the excess the transient finder
(:mod:`ttlcore.diagnose.transients`) localises:

**glitch** - the LISA Pathfinder glitch shape, the one ``lisaglitch``'s
``IntegratedShapeletGlitch`` injects (the integrated single-component exponential
shapelet that fitted the Pathfinder catalogue): a test-mass velocity

    v(t) = dv [1 - (1 + x) exp(-x)],   x = (t - t_g) / beta  (t >= t_g; 0 before),

a velocity step ``dv`` [m/s] reached over the damping time ``beta`` [s].  A glitch of
test mass ``ij`` (MOSA ``ij``, received at ``i``) moves the far end of link ``ji`` and the
near end of link ``ij``: it enters ``eta_ij`` as ``2 v(t) / c`` undelayed and ``eta_ji``
as ``D_ji 2 v / c`` (the light leaving test mass ``ij`` reaches ``j`` one light travel
time later) - as lisainstrument and the blind generator inject it.  A glitch of one link's
optical path (``link=ij``) enters ``eta_ij`` alone, as ``v(t) / c``.  The column is that
series through the exact TDI (a velocity step that stays is cancelled by TDI once every
delay has seen it: the column is localised, ~70 s plus a few ``beta``); its one linear
parameter is ``dv``.  Time, damping and the test mass (or link) are searched
(:func:`glitch_search`) when not given.

**gate** - a span of the data down-weighted to zero, as lisa-gap smooths a gap: the A, E,
T series of the data and of every column are multiplied by

    g(t) = 0 inside [start, stop],  1/2 - 1/2 cos(pi d / taper) for the distance d < taper
           outside it,  1 beyond,

before the segments are windowed (:class:`GatedData`), so that the fit ignores the span
and no hard edge leaks.  A segment partly gated holds less noise: its spectra are divided
by ``sqrt(r_s)``, ``r_s = sum (w g)^2 / sum w^2`` over its taper ``w``, so that its chi^2
keeps the expectation of an ungated segment; a segment with ``r_s < MIN_KEPT`` is left out
(its remnant leaks the red noise below the band).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import optimize

from ..conventions import LINKS, MOSAS, C, parse_duration, reverse
from ..errors import ConfigError
from ..tdi.data import history_samples
from .columns import ColumnSet, ColumnStore, regressor_columns
from .effects import Column, Effect, Part, effect_input_from_telemetry, tdi_in_blocks
from .evidence import added_evidence
from .search import SearchResult
from .transients import GATE_TAPER, gate
from .whitened import WhitenedData, noise_digest

log = logging.getLogger(__name__)

#: Range [s] of the damping time searched (the Pathfinder catalogue: 5-300 s).
BETA_RANGE = (1.0, 3000.0)
#: Damping times of the search's first grid [s].
BETA_GRID = tuple(float(x) for x in np.geomspace(2.0, 2000.0, 10))
#: Prior scale [m/s] of a glitch's velocity step (the Bayes factor's Gaussian prior).
GLITCH_PRIOR = 1e-10
#: Segments keeping less than this share of their taper's power under a gate are left out:
#: a short remnant of a segment leaks the red noise below the band into it through the
#: gate's ramps (4-h simulated day, 58-min segments, a 55-min gate: keeping a remnant of
#: 0.3 read chi2/dof 1.43 and pull RMS 2.49; leaving it out, 0.993 and 0.88).
MIN_KEPT = 0.6


def glitch_velocity(t, t_glitch: float, beta: float) -> np.ndarray:
    """``v(t) / dv = 1 - (1 + x) exp(-x)``, ``x = (t - t_glitch) / beta`` (0 before): the
    Pathfinder shape of unit velocity step (module docstring)."""
    x = (np.asarray(t, dtype=float) - float(t_glitch)) / float(beta)
    out = np.zeros_like(x)
    on = x >= 0
    out[on] = 1.0 - (1.0 + x[on]) * np.exp(-x[on])
    return out


def parse_time(value, option: str) -> float:
    """A time [s]: a number (any sign, zero included) or a duration with its unit
    (``"2.7h"``, ``"30min"``; :func:`ttlcore.conventions.parse_duration`)."""
    if isinstance(value, (int, float)):
        return float(value)
    try:
        return float(str(value).strip())
    except ValueError:
        return parse_duration(value, option)


def _parse_span(text) -> tuple[float, float] | None:
    """``"a-b"`` (durations, :func:`ttlcore.conventions.parse_duration`) -> (a, b) [s]."""
    if text is None:
        return None
    a, sep, b = str(text).partition("-")
    if not sep:
        raise ConfigError(f"span {text!r}: expected START-STOP (e.g. 9000-11000 or 2.5h-3h)")
    lo, hi = parse_time(a.strip(), "span"), parse_time(b.strip(), "span")
    if hi <= lo:
        raise ConfigError(f"span {text!r}: stop before start")
    return lo, hi


def placement_parts(where: str) -> list[tuple[str, int, float]]:
    """``"tm12"`` -> ``[("12", 0, 2), ("21", 1, 2)]`` (link, delays, factor of ``v / c``);
    ``"link12"`` -> ``[("12", 0, 1)]`` (module docstring)."""
    if where.startswith("tm"):
        m = where[2:]
        return [(m, 0, 2.0), (reverse(m), 1, 2.0)]
    return [(where[4:], 0, 1.0)]


#: The placements a glitch search tries when neither ``tm`` nor ``link`` is given.
PLACEMENTS = tuple(f"tm{m}" for m in MOSAS) + tuple(f"link{k}" for k in LINKS)


class Glitch(Effect):
    name = "glitch"
    title = "a test-mass (or link) glitch of the LISA Pathfinder shape"
    physics = (
        "A test mass kicked by outgassing, a discharge or a micrometeoroid changes velocity by dv over a "
        "damping time beta: v(t) = dv [1 - (1 + x) exp(-x)], x = (t - t_g)/beta (the integrated shapelet "
        "that fits the LISA Pathfinder glitches, lisaglitch's IntegratedShapeletGlitch). Test mass ij enters "
        "eta_ij as 2v/c and eta_ji as D_ji 2v/c; a link glitch (link=ij) eta_ij alone as v/c. One linear "
        "parameter, dv [m/s]; the time t, the damping beta and the test mass are searched when not given "
        "(span=START-STOP restricts the time searched)."
    )
    parameters = {"t": None, "tm": None, "link": None, "beta": None, "span": None}
    searched = {"t": (-np.inf, np.inf, "linear"), "beta": (BETA_RANGE[0], BETA_RANGE[1], "log")}

    def __init__(self, **options):
        super().__init__(**options)
        tm, link = self.options.get("tm"), self.options.get("link")
        if tm is not None and link is not None:
            raise ConfigError("effect 'glitch': give tm= (a test mass) or link= (one link), not both")
        for key, value in (("tm", tm), ("link", link)):
            if value is not None and str(value) not in LINKS:
                raise ConfigError(f"effect 'glitch' {key}: unknown {value!r}; known: {', '.join(LINKS)}")
            if value is not None:
                self.options[key] = str(value)
        if self.options.get("t") is not None:
            self.options["t"] = parse_time(self.options["t"], "glitch t")
        if self.options.get("beta") is not None:
            beta = float(self.options["beta"])
            if not beta > 0:
                raise ConfigError(f"effect 'glitch' beta: a damping time > 0 s, got {beta}")
            self.options["beta"] = beta
        _parse_span(self.options.get("span"))

    @property
    def where(self) -> str | None:
        """``"tm12"``, ``"link12"`` or None (searched)."""
        if self.options.get("tm") is not None:
            return f"tm{self.options['tm']}"
        if self.options.get("link") is not None:
            return f"link{self.options['link']}"
        return None

    def unresolved(self) -> list[str]:
        out = super().unresolved()
        return out + (["tm"] if self.where is None else [])

    def column_name(self) -> str:
        t = self.options.get("t")
        return f"glitch.{self.where or '?'}@{'?' if t is None else f'{float(t):.1f}'}"

    def columns(self, data):
        if self.unresolved():
            if data.names_only:
                return [Column(self.column_name(), [], "m/s", GLITCH_PRIOR)]
            raise ConfigError(
                f"effect 'glitch': {', '.join(self.unresolved())} not given (the diagnosis searches "
                "them: ttl diagnose, refit)"
            )
        v = glitch_velocity(data.t, self.options["t"], self.options["beta"])
        assert self.where is not None  # resolved above (unresolved() names it otherwise)
        parts = [Part(link, factor * v / C, n) for link, n, factor in placement_parts(self.where)]
        return [Column(self.column_name(), parts, "m/s", GLITCH_PRIOR)]

    def profile_search(self, model, coefficients=None) -> SearchResult:
        """The search of the unset time, damping and placement (:func:`glitch_search`)."""
        return glitch_search(model, self)

    def describe_text(self) -> str:
        """``"glitch at 2.70 h on tm 12"`` (or ``on link 12``)."""
        w = self.where or "?"
        on = f"tm {w[2:]}" if w.startswith("tm") else f"link {w[4:]}"
        return f"glitch at {float(self.options['t']) / 3600:.2f} h on {on}"


class Gate(Effect):
    name = "gate"
    title = "a span of the data gated out (tapered window, as lisa-gap smooths a gap)"
    physics = (
        "The data between start and stop (a loud transient, a gap with hard edges, hours of changed noise) "
        "are down-weighted to zero with cosine tapers of 'taper' seconds outside the span, in the data and in "
        "every column alike, so that the fit ignores them (lisa-gap's smoothed gap). Not a physical effect: no "
        "parameter is fitted; the gated hours are left out of the fit and of the adequacy tests."
    )
    parameters = {"start": None, "stop": None, "taper": GATE_TAPER}

    def __init__(self, **options):
        super().__init__(**options)
        for key in ("start", "stop"):
            if self.options.get(key) is None:
                raise ConfigError("effect 'gate' needs start= and stop= (e.g. gate:start=15.2h,stop=15.8h)")
            self.options[key] = parse_time(self.options[key], f"gate {key}")
        self.options["taper"] = (
            float(self.options["taper"])
            if isinstance(self.options["taper"], (int, float))
            else parse_duration(self.options["taper"], "gate taper")
        )
        if self.options["stop"] <= self.options["start"]:
            raise ConfigError(
                f"effect 'gate': stop ({self.options['stop']:g} s) before start ({self.options['start']:g} s)"
            )

    @property
    def span(self) -> tuple[float, float]:
        return float(self.options["start"]), float(self.options["stop"])

    def columns(self, data):
        return []

    def describe_text(self) -> str:
        a, b = self.span
        return f"gate {a / 3600:.2f}-{b / 3600:.2f} h"


def split_gates(effects) -> tuple[list, list]:
    """``(gates, others)`` of a model's effects."""
    gates = [e for e in effects if isinstance(e, Gate)]
    return gates, [e for e in effects if not isinstance(e, Gate)]


# ---------------------------------------------------------------------------
# Gated data
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class GatedData(WhitenedData):
    """:class:`~ttlcore.diagnose.whitened.WhitenedData` with spans gated out (module
    docstring).  Every decimated series is multiplied by ``gate``: the data's and the TTL
    regressors' (``data_series``, ``regressor_series``) once here, every column's where it
    is decimated (:meth:`decimate`, the one path from an effect's TDI to its spectra), so
    that data and columns carry the same window and the time-domain residual (per-hour
    adequacy, transients) is tapered too, without a hard edge; each segment's spectra are
    multiplied by ``seg_scale`` (``1 / sqrt(r_s)``).  Inside a span (``gate == 0``) the
    samples are out of ``mask``."""

    gate: np.ndarray | None = None
    seg_scale: np.ndarray | None = None
    gates: tuple = ()
    #: ``((start, stop), ...)`` [s] of the gates
    gate_spans: tuple = ()

    def spectra(self, x: np.ndarray) -> np.ndarray:
        assert self.seg_scale is not None  # set with the gate (gate_data)
        return super().spectra(x) * self.seg_scale[:, None, None, None]

    def decimate(self, xyz: np.ndarray, is_aet: bool = False) -> np.ndarray:
        """The decimated A, E, T of columns (:meth:`WhitenedData.decimate`) times the gate;
        full-length series only (a stretch: decimate it ungated and gate it once placed)."""
        out = super().decimate(xyz, is_aet)
        assert self.gate is not None  # set with the gate (gate_data)
        if out.shape[-1] != self.gate.size:
            raise ConfigError(
                f"gated data: a series of {out.shape[-1]} decimated samples cannot be gated ({self.gate.size} expected)"
            )
        return out * self.gate


def gated_data(data: WhitenedData, gates) -> WhitenedData:
    """``data`` with the spans of ``gates`` (:class:`Gate`) gated out (:class:`GatedData`);
    ``data`` itself when there is none.  The noise model is kept; the column store is new
    (columns built on ungated data do not apply)."""
    gates = list(gates)
    if not gates:
        return data
    if isinstance(data, GatedData):
        raise ConfigError("these data are already gated")
    n = data.mask.size
    g = np.ones(n)
    for e in gates:
        g = np.minimum(g, gate(n, data.fs, data.t0, [e.span], taper=float(e.options["taper"])))
    inside = g <= 0.0
    mask = data.mask & ~inside
    if not mask.any():
        raise ConfigError("the gates leave no data")
    keep, scale = [], []
    for s0 in data.starts:
        w = data.win * data.mask[s0 : s0 + data.L]
        r = float(np.sum((w * g[s0 : s0 + data.L]) ** 2) / max(np.sum(w**2), 1e-300))
        keep.append(r >= MIN_KEPT)
        scale.append(1.0 / math.sqrt(max(r, 1e-300)))
    if not any(keep):
        raise ConfigError("the gates leave no FFT segment with data")
    idx = [i for i, k in enumerate(keep) if k]
    starts = tuple(data.starts[i] for i in idx)
    w2 = np.stack([(data.win * mask[s0 : s0 + data.L] * g[s0 : s0 + data.L]) ** 2 for s0 in starts])
    # gated once; inside a span exactly zero (a gap's NaN there too)
    series = np.where(inside, 0.0, data.data_series * g)
    regs = np.where(inside, 0.0, data.regressor_series * g)
    out = GatedData(
        **{
            **{k: getattr(data, k) for k in data.__dataclass_fields__},
            "mask": mask,
            "starts": starts,
            "seg_t0": np.asarray(data.seg_t0)[idx],
            "w2": w2 / w2.sum(axis=1, keepdims=True),
            "data_series": series,
            "regressor_series": regs,
            "store": ColumnStore(),
            "d": np.empty(0),
            "wd": np.empty(0),
            "dd": np.empty(0),
            "gate": g,
            "seg_scale": np.asarray(scale)[idx],
            "gates": tuple(e.spec() for e in gates),
            "gate_spans": tuple(e.span for e in gates),
        }
    )
    d = out.spectra(series[:, None, :])[..., 0]
    R = out.spectra(regs)
    wd = np.matmul(out.Lh, d[..., None])[..., 0]
    dd = np.zeros((len(starts), out.G))
    for gi, (a, b) in enumerate(out.slices):
        dd[:, gi] = np.sum(np.abs(wd[:, a:b]) ** 2, axis=(1, 2))
    out = replace(out, d=d, wd=wd, dd=dd, noise_key=noise_digest(out.noise_csd) + ":gated:" + ",".join(out.gates))
    out.store.put(("regressors",), out, regressor_columns(out, R))
    log.info("gated %s: %d of %d segments kept", ", ".join(out.gates), len(starts), len(data.starts))
    return out


def in_gates(data, a: float, b: float) -> bool:
    """Whether ``[a, b]`` [s] lies inside one of ``data``'s gates (:class:`GatedData`)."""
    return any(lo <= a + 1e-6 and b <= hi + 1e-6 for lo, hi in getattr(data, "gate_spans", ()))


# ---------------------------------------------------------------------------
# Glitch search
# ---------------------------------------------------------------------------


def glitch_series(data, where, t_glitch: float, beta: float) -> np.ndarray:
    """Decimated A, E, T (3, n) of a unit glitch (``dv = 1 m/s``) placed ``where`` at
    ``t_glitch`` with damping ``beta`` - (3, k, n) for a list of ``k`` placements: the
    exact TDI of its parts computed on a stretch of telemetry from the delays' history
    before ``t_glitch`` to ``12 beta + 300 s`` after it (beyond, TDI cancels the velocity
    step that stays, to ``13 exp(-12)``), zero elsewhere.  The stretch starts on a multiple
    of the decimation factor, so that its decimated samples are the data's; on gated data
    the series is gated once placed."""
    tm = data.tm
    if tm is None:
        raise ConfigError("effect 'glitch' needs the telemetry")
    many = not isinstance(where, str)
    wheres = list(where) if many else [where]
    fs = float(tm.fs)
    dec = int(data.decimation)
    hist = history_samples(fs, float(np.nanmax(tm.ltt)))
    i0 = int(math.floor((t_glitch - float(tm.t0)) * fs))
    a = max(i0 - hist - 16, 0)
    a -= a % dec
    b = min(max(i0, 0) + hist + int((12.0 * beta + 300.0) * fs), tm.size)
    n_dec = data.mask.size
    out = np.zeros((3, len(wheres), n_dec))
    if b > a + hist:
        sub = tm.slice(a, b)
        inp = effect_input_from_telemetry(sub)
        v = glitch_velocity(inp.t, t_glitch, beta) / C
        cols = [Column(w, [Part(link, factor * v, n) for link, n, factor in placement_parts(w)]) for w in wheres]
        _, xyz = tdi_in_blocks(sub.ltt, fs, cols, order=data.settings.order, delay_order=data.settings.delay_order)
        # (3, k, m): global decimated samples a / dec + j, ungated (a stretch), gated once placed
        x = WhitenedData.decimate(data, np.nan_to_num(xyz))
        k0 = a // dec
        m = min(x.shape[-1], n_dec - k0)
        out[:, :, k0 : k0 + m] = x[:, :, :m]
        g = getattr(data, "gate", None)
        if g is not None:
            out *= g
    return out if many else out[:, 0]


def glitch_spectra(data, where, t_glitch: float, beta: float) -> np.ndarray:
    """Whitened segment spectra (S, m, 3) of a unit glitch (:func:`glitch_series`); (S, m,
    3, k) for a list of placements."""
    x = glitch_series(data, where, t_glitch, beta)
    w = data.whiten(data.spectra(x if x.ndim == 3 else x[:, None, :]))
    return w if x.ndim == 3 else w[..., 0]


class _Scanner:
    """Profile of a glitch's time against a fitted model, for templates.

    Adding one column ``g`` to the model ``M`` (fitted: residual ``r``, normal matrix with
    errors in variables ``N_MM - E``) gains

        delta chi2 = 2 c^2 / (D kappa),  c = Re sum conj(g) r,
        D = Re sum |g|^2 - n^T (N_MM - E)^-1 n,  n = Re sum conj(g) M,

    (the glitch column carries no readout noise).  A template moved by ``tau`` is the
    phase ``exp(-2 pi i f tau)`` of its spectra (inside one segment, away from the taper),
    so ``c`` and ``n`` at every shift by a sample of the decimated grid are one inverse FFT
    of their per-bin products over the segment's frequency grid (``n`` matters: a glitch
    already in the model, near in time, is correlated with the template).  The model's columns and
    residual are arranged once per search (:meth:`products` then costs a batched product
    per template)."""

    def __init__(self, model):
        self.data = model.data
        S, m = model.residual_w.shape[:2]
        self.r = np.ascontiguousarray(model.residual_w.transpose(1, 0, 2)).reshape(m, S * 3)
        x = model.columns.x.view(complex)  # (P, S, m, 3)
        self.M = np.ascontiguousarray(x.transpose(2, 1, 3, 0)).reshape(m, S * 3, -1)  # (m, S 3, P)
        NM = model.normal[0].sum(axis=(0, 1)) - model.eiv_term.sum(axis=0)
        self.NMinv = np.linalg.inv(NM)

    def products(self, G: np.ndarray) -> list[tuple]:
        """``(p (m,), q (m, P), |g|^2)`` per template of ``G`` (S, m, 3, k): the per-bin
        products ``sum conj(g) r``, ``sum conj(g) M``."""
        S, m, _, k = G.shape
        Gc = np.ascontiguousarray(G.conj().transpose(1, 3, 0, 2)).reshape(m, k, S * 3)
        p = np.einsum("mkj,mj->mk", Gc, self.r)
        q = np.matmul(Gc, self.M)  # (m, k, P)
        ngg = np.sum(np.abs(G) ** 2, axis=(0, 1, 2))
        return [(p[:, j], q[:, j], float(ngg[j])) for j in range(k)]

    def shifts(self, prods, max_shift: float) -> tuple[np.ndarray, np.ndarray]:
        """``(tau [s], delta chi2)`` of one template's products on the decimated grid,
        ``|tau| <= max_shift``."""
        data = self.data
        p, q, ngg = prods
        L = data.L
        kmax = int(max_shift * data.fs) + 1
        full = np.zeros((1 + q.shape[1], L), dtype=complex)
        full[0, data.bins] = p
        full[1:, data.bins] = q.T
        z = np.fft.ifft(full, axis=1).real * L  # sum_f x(f) exp(2 pi i f k / fs)
        k = np.r_[np.arange(-min(kmax, L // 2 - 1), 0), np.arange(0, min(kmax, L // 2) + 1)]
        c = z[0, k]
        n = z[1:, k]  # (P, K)
        D = ngg - np.einsum("pk,pk->k", n, self.NMinv @ n)
        return k / data.fs, 2.0 * c**2 / (np.maximum(D, 1e-300) * data.kappa)

    def at(self, prods, tau: float) -> float:
        """delta chi2 of one template's products at a shift ``tau`` [s] (any real value)."""
        p, q, ngg = prods
        ph = np.exp(2j * np.pi * self.data.f * tau)
        c = float(np.real(np.sum(p * ph)))
        n = np.real(ph @ q)
        D = ngg - n @ self.NMinv @ n
        return 2.0 * c**2 / (max(D, 1e-300) * self.data.kappa)


def _pieces(data, lo: float, hi: float) -> list[tuple[float, float, float]]:
    """``[lo, hi]`` cut at the segment boundaries: ``(t_ref, a, b)`` per piece, the
    template's reference time the piece's centre."""
    bounds = sorted({float(t) for t in data.seg_t0} | {float(data.seg_t0[-1] + data.seg_duration)})
    cuts = [lo] + [t for t in bounds if lo < t < hi] + [hi]
    return [(0.5 * (a + b), a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]


def glitch_search(model, effect: Glitch) -> SearchResult:
    """Profile-likelihood search of a glitch's unset time, damping and placement.

    For each placement (``tm`` or ``link`` given: that one; otherwise the six test masses
    and the six links, :data:`PLACEMENTS`) and each damping of :data:`BETA_GRID` (or the
    given one), a template at the centre of each piece of the searched span (``span``, the
    analysed data without it; cut at the segments' boundaries) is scanned over every shift
    by a decimated sample (:class:`_Scanner`); the best (placement, damping, time) is refined
    by Brent's method in ``log beta`` (templates rebuilt exactly at the time found, the
    time rescanned +-60 s) and in time (the phase formula).  The estimate is scored with
    its exact template (:func:`ttlcore.diagnose.evidence.added_evidence`).

    The marginal evidence: Laplace's rule over time and ``log beta`` (the curvatures of the
    profile), a uniform prior over the span and the damping range, and ``1 / n`` for the
    ``n`` placements tried; never above the evidence at the estimate.
    """
    data = model.data
    if data.tm is None:
        raise ConfigError("effect 'glitch': the search needs the telemetry")
    idx = np.flatnonzero(data.mask)
    t_lo, t_hi = data.t0 + idx[0] / data.fs, data.t0 + idx[-1] / data.fs
    span = _parse_span(effect.options.get("span"))
    if effect.options.get("t") is not None:
        t_fixed = float(effect.options["t"])
        lo = hi = t_fixed
    else:
        lo, hi = span if span is not None else (t_lo, t_hi)
        lo, hi = max(lo, t_lo), min(hi, t_hi)
        if hi <= lo:
            raise ConfigError(f"effect 'glitch': the searched span {span} is outside the analysed data")
    places = [effect.where] if effect.where else list(PLACEMENTS)
    betas = [float(effect.options["beta"])] if effect.options.get("beta") is not None else list(BETA_GRID)
    n_eval = 0
    scanner = _Scanner(model)
    best: tuple = (-np.inf, None, None, None)  # (dchi2, where, beta, t)
    grid = []
    for t_ref, a, b in _pieces(data, lo, hi) if hi > lo else [(lo, lo, lo)]:
        half = max(t_ref - a, b - t_ref)
        for beta in betas:
            # every placement in one TDI
            prods = scanner.products(glitch_spectra(data, places, t_ref, beta))
            for j_place, where in enumerate(places):
                tau, dchi2 = scanner.shifts(prods[j_place], half)
                inside = (t_ref + tau >= a) & (t_ref + tau <= b)
                n_eval += int(inside.sum())
                j = int(np.argmax(np.where(inside, dchi2, -np.inf)))
                grid.append(([where, beta, float(t_ref + tau[j])], float(dchi2[j])))
                if dchi2[j] > best[0]:
                    best = (float(dchi2[j]), where, beta, float(t_ref + tau[j]))
    _, where, beta, t_best = best
    fixed_t = effect.options.get("t") is not None

    def refine_time(beta_):
        """Best time [s] and delta chi2 near ``t_best`` for a damping (exact template there)."""
        nonlocal n_eval
        pr = scanner.products(glitch_spectra(data, [where], t_best, beta_))[0]
        if fixed_t:
            n_eval += 1
            return t_best, scanner.at(pr, 0.0), pr
        tau, dchi2 = scanner.shifts(pr, 60.0)
        j = int(np.argmax(dchi2))
        res = optimize.minimize_scalar(
            lambda x: -scanner.at(pr, x),
            bounds=(tau[j] - 1.0 / data.fs, tau[j] + 1.0 / data.fs),
            method="bounded",
            options={"xatol": 1e-3},
        )
        n_eval += tau.size + res.nfev
        x, val = (float(res.x), -float(res.fun)) if -res.fun >= dchi2[j] else (float(tau[j]), float(dchi2[j]))
        return t_best + x, val, pr

    if effect.options.get("beta") is None:
        lb = math.log(beta)
        step = math.log(BETA_GRID[1] / BETA_GRID[0])
        res = optimize.minimize_scalar(
            lambda x: -refine_time(math.exp(x))[1],
            bounds=(max(lb - step, math.log(BETA_RANGE[0])), min(lb + step, math.log(BETA_RANGE[1]))),
            method="bounded",
            options={"xatol": 2e-3},
        )
        beta = float(math.exp(res.x))
    t_best, _, _ = refine_time(beta)
    found = effect.with_options(
        t=round(t_best, 2),
        beta=float(f"{beta:.4g}"),
        span=None,
        **({} if effect.where else {("tm" if where.startswith("tm") else "link"): where[-2:]}),
    )
    g = glitch_spectra(data, where, t_best, beta)
    ev = _evidence(model, found, g)
    # curvatures of l = delta chi2 / 2 in time and log beta (the others at the estimate)
    sig_t = sig_lb = float("nan")
    if not fixed_t:
        pr = scanner.products(g[..., None])[0]
        h = 0.25 / data.fs
        curv = -(scanner.at(pr, h) - 2 * scanner.at(pr, 0.0) + scanner.at(pr, -h)) / (2 * h * h)
        sig_t = 1.0 / math.sqrt(curv) if curv > 0 else float("nan")
    if effect.options.get("beta") is None:
        h = 0.05
        prods = [scanner.products(glitch_spectra(data, [where], t_best, beta * math.exp(x)))[0] for x in (-h, 0.0, h)]
        vals = [scanner.at(pr, 0.0) for pr in prods]
        curv = -(vals[0] - 2 * vals[1] + vals[2]) / (2 * h * h)
        sig_lb = 1.0 / math.sqrt(curv) if curv > 0 else float("nan")
    marg = ev.log_bayes_factor - math.log(len(places))
    if not fixed_t:
        marg += (
            (0.5 * math.log(2 * math.pi) + math.log(sig_t) - math.log(max(hi - lo, 1e-9)))
            if np.isfinite(sig_t)
            else -math.log(max((hi - lo) * data.fs, 1.0))
        )
    if effect.options.get("beta") is None:
        width = math.log(BETA_RANGE[1] / BETA_RANGE[0])
        marg += (
            (0.5 * math.log(2 * math.pi) + math.log(sig_lb) - math.log(width))
            if np.isfinite(sig_lb)
            else -math.log(len(BETA_GRID))
        )
    marg = float(min(marg, ev.log_bayes_factor))
    est = {"t": float(t_best), "beta": float(beta)}
    intervals = {}
    if np.isfinite(sig_t):
        intervals["t"] = (t_best - sig_t, t_best + sig_t)
    if np.isfinite(sig_lb):
        intervals["beta"] = (beta * math.exp(-sig_lb), beta * math.exp(sig_lb))
    log.info("glitch search: %s at %.1f s, beta %.3g s, delta chi2 %.1f", where, t_best, beta, ev.delta_chi2)
    return SearchResult(
        found,
        est,
        intervals,
        float(ev.delta_chi2),
        float(ev.log_bayes_factor),
        marg,
        n_eval,
        grid=grid,
        evidence=ev,
        theta={found.column_name(): float(ev.beta[0])},
    )


def glitch_columns(data, effect: Glitch, g: np.ndarray | None = None) -> ColumnSet:
    """The whitened column of a resolved glitch (its exact template on a stretch,
    :func:`glitch_spectra`)."""
    if g is None:
        g = glitch_spectra(data, effect.where, float(effect.options["t"]), float(effect.options["beta"]))
    x = np.ascontiguousarray(g)[None].view(np.float64)
    return ColumnSet((effect.column_name(),), x, data.noise_key, ("m/s",), (GLITCH_PRIOR,), ((),), (None,))


def _evidence(model, effect: Glitch, g: np.ndarray):
    return added_evidence(model, glitch_columns(model.data, effect, g))


def with_gates(model_json: dict, gates) -> dict:
    """A report's ``model`` part (:func:`ttlcore.diagnose.report.model_json`) with the
    model's gates listed among its effects (they change the data, not the columns) and
    under ``gates`` (``[start, stop]`` [s] each)."""
    gates = list(gates)
    if not gates:
        return model_json
    out = dict(model_json)
    out["effects"] = list(out["effects"]) + [g.spec() for g in gates]
    out["cli_effects"] = ",".join([out["cli_effects"]] + [g.cli_spec() for g in gates])
    out["gates"] = [list(g.span) for g in gates]
    return out

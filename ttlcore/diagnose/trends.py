"""Trends of the TTL coefficients over a sequence of rolling-window fits: steps and drifts.

The fitter refits a window of fixed length (one day) every time a segment (one hour)
arrives, so consecutive estimates share almost all their data: a 24-segment window
moved by one segment keeps 23/24 of it.  Their errors are therefore strongly
correlated, and neither "two estimates differ by more than their sigmas" nor an
ordinary least-squares line through the estimates is a valid test.  This module works
with the correlation that the overlap implies.

Correlation model
-----------------
For estimates that are (to a good approximation) averages of independent per-segment
information of equal weight, two windows ``a`` and ``b`` of lengths ``L_a``, ``L_b``
that share a duration ``o`` have

    rho_ab = o / sqrt(L_a L_b),        Cov(C_a, C_b) = rho_ab sigma_a sigma_b

(:func:`window_correlation`).  The window boundaries are the fits' ``t_start`` and
``t_stop``, so growing windows at the start of a run, gaps and irregular refits are
handled alike.

Steps (:func:`detect_steps`)
----------------------------
A coefficient that jumps by ``Delta`` at time ``T`` moves the rolling estimate along a
ramp: every new window takes in one more segment after ``T`` and drops one before it,
so each *consecutive difference* ``d_k = C_k - C_{k-1}`` is raised by about
``Delta x (new fraction of the window)`` (``Delta / 24`` for hourly refits of a day)
until the window lies wholly after ``T``.  The noise of ``d_k`` is small, because the
shared data cancel: ``sd(d_k) = sqrt(s_k^2 + s_{k-1}^2 - 2 rho s_k s_{k-1})``, about
``0.29 sigma`` for 23/24 overlap.  A 0.3 mm/rad step with sigma = 0.01 mm/rad per
window raises each difference by about 4.3 of its own standard deviations.

Each difference is standardised, ``z_k = (d_k - mu_k) / (f_k sd(d_k))``, where

* ``mu_k`` is the inverse-variance weighted mean of the previous
  :attr:`TrendSettings.baseline_windows` differences (those of a step's ramp left out):
  a steady drift raises every difference by the same amount and must not look like a
  step.  A mean of consecutive differences telescopes, ``(C_k - C_{k-B}) / B`` for equal
  weights, so its noise is about ``sqrt(2) sigma / B`` - a tenth of ``sd(d)`` for
  ``B = 48``; a median would be twice as noisy, and a baseline error enters the CUSUM as
  a persistent shift that shortens the time between false alarms;
* ``f_k >= 1`` is the robust scatter (1.4826 x MAD) of the previous standardised
  differences, once at least :attr:`TrendSettings.min_history` are available: if the
  fitter's sigmas are too small, the differences' own scatter takes over (the brief's
  "difference of consecutive estimates against its own scatter"); it never makes the
  test more sensitive than the quoted sigmas allow.  The test is armed only once these
  are available (12 differences: half a day of hourly fits into a run).

A two-sided CUSUM runs on ``z``: ``S+ = max(0, S+ + z - k)``, ``S- = max(0, S- - z - k)``
with allowance ``k`` (:attr:`TrendSettings.step_allowance`, default 1) and decision
interval ``h`` (:attr:`TrendSettings.step_threshold`, default 6).  The alarm names the
coefficient; the change point (the first difference of the run that crossed ``h``)
dates the step to the start of that window's new data; the size is the weighted
least-squares fit of the exact ramp (window averages of a unit step) to the run's
differences, with its standard error giving the significance.  After an alarm the
coefficient is held off until the ramp has passed (one window length), and those
differences are kept out of later baselines.

False alarms: for independent standard-normal ``z``, Siegmund's approximation gives an
in-control average run length of ``(exp(2k(h+1.166)) - 2k(h+1.166) - 1) / (2k^2)``, about
8e5 differences per side for ``k = 1, h = 6``; the noise of the baseline shortens that to
about 3.5e5 coefficient-windows between false alarms (measured on simulated rolling
fits: 6 alarms in 2.3 million), that is, with 24 coefficients refitted 24 times a day,
about one false step alarm in 600 days of Gaussian noise.  The smallest
step found quickly is where the per-difference shift exceeds ``k``: with hourly refits of a
day, ``Delta > ~7 (k + 0.5) sigma``, about 0.1 mm/rad for sigma = 0.01 mm/rad - the
coefficient accuracy the mission asks for.  A 0.3 mm/rad step (shift 4.3) at a segment
boundary crosses ``h`` after two differences in about 55 % of simulations, three in 40 %,
four in 6 %, and is dated to the right segment in 96 % of them (within two segments in
all of 200).

Drifts (:func:`detect_drifts`, :func:`trend_estimates`, :func:`drift_alerts`)
-----------------------------------------------------------------------------
Over the fits whose window ends within the last :attr:`TrendSettings.drift_lookback`
(default three days; all fits while fewer exist), a generalised least-squares line ``C(t) = a + b t`` (``t`` the window
centre) is fitted with the full overlap covariance above, plus, for every step already
detected in that coefficient inside the span, the window average of a unit step at the
step time (so a step is not read as a drift).  The rate ``b`` [mm/rad/day] is significant
when ``|b| / se(b) >= drift_threshold`` (default 5).  ``se(b)`` is inflated by
``sqrt(chi2/dof)`` of the GLS fit when that exceeds one, so a sequence that scatters more
than its sigmas say (or that a line does not describe) raises fewer alarms, never more.

False alarms: the test is two-sided at 5 sigma, p = 5.7e-7 per evaluation; a monitor
evaluating 24 coefficients 24 times a day makes 576 evaluations a day, so fewer than
3.3e-4 false drift alarms a day (successive evaluations share most of their data, so the
true rate is lower still).  Sensitivity: with hourly fits of a day and sigma = 0.01 mm/rad
per window, two days of fits constrain the rate to about 0.0075 mm/rad/day and three days
to about 0.0045, so a 0.05 mm/rad/day drift stands at about 7 sigma after two days of
fits and 11 after three - drifts are flagged about when they have moved a coefficient by
the 0.1 mm/rad accuracy requirement.  A longer lookback is more sensitive to steady
drifts but slower to forget one that stopped.

Model epochs (:class:`TrendMonitor`, :func:`model_key`)
------------------------------------------------------
The fitter's model can change during a run (``ttl control``, ``--adopt auto``, a transient
leaving the window), and every fit message says under which model its coefficients were
estimated (meta ``model``, the list of effect specs).  A change of the model moves the
estimates at once - the fitter rebuilds its window under the new model - by what the old
model got wrong, not by anything the coefficients did: on a live day that adopted a
round-trip-ghost witness the change raised two step alerts at 7.4 sigma.  The trends
therefore compare fits under the same model only:

* **a new coupling** (any change of the effects other than the transients ``glitch`` and
  ``gate``: a witness, a drift, an fd-coupling added, removed or re-parametrised) starts a
  new *model epoch*: the step scan, its baselines and its scatter, the drift line and the
  reported drifts start again from the first fit of the new model, and the alerts of the
  epoch are de-duplicated among themselves.  What the 24 numbers mean can change with the
  couplings (with ``drift`` in the model they are the values at the reference time), so no
  statistic of the old epoch is carried over.  The cost: the step test is armed again only
  after ``min_history`` differences (13 fits, half a day of hourly fits) and the drift line
  after ``drift_min_windows`` fits; a drift that goes on is reported again in the new epoch
  once its own fits show it.
* **a change of the transients only** (a glitch or a gate added, merged, or removed when it
  leaves the window) does not: the 24 coefficients are the same quantity under both models,
  but the estimate jumps by what the transient pulled it by.  The series goes on; the one
  difference across the change is left out of the step test (not accumulated, not in a
  baseline, not in a step's size) and the drift line gets a free offset from the first fit
  of the new model.  A live day with a merger changes its gates at every diagnosis (a gate
  merged with the next to the window's end) and drops each transient a day later: starting
  the series again each time would leave the step test unarmed most of such a day, for a
  jump that one left-out difference already takes.

A fit without ``model`` in its meta is under the model of the fit before it.

Units: coefficients and sigmas are given in m/rad (the bus's unit) unless ``units`` says
otherwise; alert values are in mm/rad (steps) or mm/rad/day (drifts); times in seconds.
"""

# size: the step and drift detectors share the window-correlation statistics of overlapping
# rolling fits (window_correlation, step_response) and the alerts they raise; TrendMonitor is
# their streaming face.

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy.linalg import solve_triangular

from ..conventions import COEFFICIENT_NAMES, DAY
from ..effects.registry import EFFECTS

#: Alert kinds.
STEP = "step"
DRIFT = "drift"
#: Factor from a unit to mm/rad.
_TO_MM = {"m/rad": 1e3, "mm/rad": 1.0, "um/rad": 1e-3}
#: Robust sigma from the median absolute deviation.
_MAD = 1.4826


@dataclass(frozen=True)
class Alert:
    """A step or drift alert.

    Attributes
    ----------
    kind : {"step", "drift"}
    coefficient : str
        Coefficient name (``"12.phi.rx"``).
    t : float
        Mission time [s]: for a step, the estimated time of the step (start of the new
        data of the first window that saw it); for a drift, the end of the latest window
        used.
    value : float
        Step size [mm/rad] or drift rate [mm/rad/day].
    significance : float
        ``value`` over its standard error (signed like ``value``).
    message : str
        One line for people.
    t_detected : float
        End of the window of the fit that raised the alert [s].
    index : int or None
        Index of that fit (the fit's segment index when known, else its position).
    details : dict
        Test statistics (CUSUM value, baseline, scatter factor, standard error...).
    """

    kind: str
    coefficient: str
    t: float
    value: float
    significance: float
    message: str
    t_detected: float = float("nan")
    index: int | None = None
    details: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """JSON-ready dict (non-finite numbers as None)."""
        out = asdict(self)
        for key in ("t", "value", "significance", "t_detected"):
            v = out[key]
            out[key] = None if v is None or not math.isfinite(v) else float(v)
        out["units"] = "mm/rad" if self.kind == STEP else "mm/rad/day"
        out["details"] = {
            k: (
                float(v)
                if isinstance(v, (np.floating, float)) and math.isfinite(v)
                else None
                if isinstance(v, (np.floating, float))
                else int(v)
                if isinstance(v, np.integer)
                else v
            )
            for k, v in self.details.items()
        }
        return out

    @classmethod
    def from_json(cls, d: Mapping) -> Alert:
        nan = float("nan")
        return cls(
            kind=str(d["kind"]),
            coefficient=str(d["coefficient"]),
            t=nan if d.get("t") is None else float(d["t"]),
            value=nan if d.get("value") is None else float(d["value"]),
            significance=nan if d.get("significance") is None else float(d["significance"]),
            message=str(d.get("message", "")),
            t_detected=nan if d.get("t_detected") is None else float(d["t_detected"]),
            index=d.get("index"),
            details=dict(d.get("details") or {}),
        )


@dataclass(frozen=True)
class TrendSettings:
    """Thresholds of the trend tests (see the module docstring for the reasoning).

    Attributes
    ----------
    step_threshold : float
        CUSUM decision interval ``h`` [standard deviations of a consecutive difference].
    step_allowance : float
        CUSUM allowance ``k`` (shifts below ``k`` per difference are not accumulated).
    baseline_windows : int
        Past differences used for the baseline level (drift) and the empirical scatter.
    min_history : int
        Differences needed before the baseline and the empirical scatter are used.
    drift_lookback : float
        Span of window ends used for the drift line [s].
    drift_threshold : float
        ``|rate| / se`` above which a drift is reported.
    drift_release : float
        A reported drift is considered over (and may be reported again) when its
        significance falls below this (hysteresis of :class:`TrendMonitor`).
    drift_min_windows : int
        Fewest windows for a drift line.
    """

    step_threshold: float = 6.0
    step_allowance: float = 1.0
    baseline_windows: int = 48
    min_history: int = 12
    drift_lookback: float = 3 * DAY
    drift_threshold: float = 5.0
    drift_release: float = 3.0
    drift_min_windows: int = 12

    @classmethod
    def from_dict(cls, d: Mapping | None) -> TrendSettings:
        d = dict(d or {})
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(
                f"trend settings: unknown field {sorted(unknown)[0]!r} (known: {', '.join(cls.__dataclass_fields__)})"
            )
        return cls(**d)


# ---------------------------------------------------------------------------- inputs


def _scale(units: str) -> float:
    try:
        return _TO_MM[units]
    except KeyError:
        raise ValueError(f"units: {units!r} not one of {', '.join(_TO_MM)}") from None


def _prepare(times, coefficients, sigma, t_start, window, names, units):
    """Validated arrays: (t_start, t_stop, C [mm/rad], S [mm/rad], names)."""
    t_stop = np.asarray(times, dtype=float).reshape(-1)
    k = t_stop.size
    C = np.asarray(coefficients, dtype=float)
    if C.ndim == 1:
        C = C[:, None]
    if C.ndim != 2 or C.shape[0] != k:
        raise ValueError(f"coefficients: expected shape ({k}, P), got {np.shape(coefficients)}")
    S = _sigmas(sigma, C)
    ts = _window_starts(t_start, window, t_stop)
    if not (np.all(np.isfinite(t_stop)) and np.all(np.isfinite(ts))):
        raise ValueError("times: non-finite window boundaries")
    if np.any(t_stop <= ts):
        raise ValueError("times: every window must end after it starts")
    if k > 1 and np.any(np.diff(t_stop) <= 0):
        raise ValueError("times: window ends must increase strictly (sort and de-duplicate the fits)")
    if names is None:
        names = COEFFICIENT_NAMES if C.shape[1] == len(COEFFICIENT_NAMES) else tuple(f"c{i}" for i in range(C.shape[1]))
    names = tuple(str(n) for n in names)
    if len(names) != C.shape[1]:
        raise ValueError(f"names: {len(names)} names for {C.shape[1]} coefficients")
    f = _scale(units)
    return ts, t_stop, C * f, S * f, names


def _sigmas(sigma, C: np.ndarray) -> np.ndarray:
    """The 1-sigma errors, shaped as the coefficients ``C`` (k, P), from ``sigma``: the
    same shape, (k,) for one coefficient, or covariances (k, P, P)."""
    k = C.shape[0]
    S = np.asarray(sigma, dtype=float)
    if S.ndim == 3:  # covariances
        if S.shape != (k, C.shape[1], C.shape[1]):
            raise ValueError(f"sigma: covariances of shape {S.shape}, expected ({k}, {C.shape[1]}, {C.shape[1]})")
        S = np.sqrt(np.maximum(np.einsum("kii->ki", S), 0.0))
    elif S.ndim == 1 and C.shape[1] == 1:
        S = S[:, None]
    if S.shape != C.shape:
        raise ValueError(f"sigma: expected shape {C.shape} (or covariances), got {np.shape(sigma)}")
    return S


def _window_starts(t_start, window, t_stop: np.ndarray) -> np.ndarray:
    """The windows' starts [s]: ``t_start``, else ``t_stop - window``; ValueError without either."""
    if t_start is not None:
        ts = np.asarray(t_start, dtype=float).reshape(-1)
        if ts.size != t_stop.size:
            raise ValueError(f"t_start: expected {t_stop.size} values, got {ts.size}")
    elif window is not None:
        if not float(window) > 0:
            raise ValueError(f"window: expected a positive length [s], got {window!r}")
        ts = t_stop - float(window)
    else:
        raise ValueError("the windows are needed (t_start or window): overlapping windows are correlated")
    return ts


def window_correlation(t_start, t_stop) -> np.ndarray:
    """Correlation of window estimates implied by their overlap: ``o_ab / sqrt(L_a L_b)``."""
    ts = np.asarray(t_start, dtype=float)
    te = np.asarray(t_stop, dtype=float)
    length = te - ts
    overlap = np.clip(np.minimum(te[:, None], te[None, :]) - np.maximum(ts[:, None], ts[None, :]), 0.0, None)
    return overlap / np.sqrt(np.outer(length, length))


def step_response(t_start, t_stop, t_step: float) -> np.ndarray:
    """Window averages of a unit step at ``t_step``: the fraction of each window after it."""
    ts = np.asarray(t_start, dtype=float)
    te = np.asarray(t_stop, dtype=float)
    return np.clip((te - t_step) / (te - ts), 0.0, 1.0)


def format_time(t: float) -> str:
    """Mission time for messages: ``"2.042 d"``."""
    return f"{t / DAY:.3f} d" if math.isfinite(t) else "?"


# ---------------------------------------------------------------------------- steps


def consecutive_differences(t_start, t_stop, C, S):
    """Differences of consecutive estimates and their model standard deviations.

    Returns ``(d, sd)``, both ``(k - 1, P)``: ``d[j] = C[j + 1] - C[j]``.
    """
    ts, te = np.asarray(t_start, float), np.asarray(t_stop, float)
    overlap = np.clip(np.minimum(te[1:], te[:-1]) - np.maximum(ts[1:], ts[:-1]), 0.0, None)
    rho = overlap / np.sqrt((te[1:] - ts[1:]) * (te[:-1] - ts[:-1]))
    s1, s0 = S[1:], S[:-1]
    var = s1**2 + s0**2 - 2 * rho[:, None] * s1 * s0
    # two windows can never be more alike than their different lengths allow; keep a floor
    floor = (1e-3 * np.minimum(s1, s0)) ** 2
    return C[1:] - C[:-1], np.sqrt(np.maximum(var, floor))


def detect_steps(
    times,
    coefficients,
    sigma,
    *,
    t_start=None,
    window: float | None = None,
    names: Sequence[str] | None = None,
    units: str = "m/rad",
    indices: Sequence[int] | None = None,
    settings: TrendSettings | None = None,
) -> list[Alert]:
    """Step alerts in a sequence of rolling-window fits (CUSUM on consecutive differences).

    Parameters
    ----------
    times : array_like, shape (k,)
        End of each fit window [s] (strictly increasing).
    coefficients : array_like, shape (k, P)
        Estimates [``units``].
    sigma : array_like, shape (k, P) or (k, P, P)
        Their standard errors, or their covariance matrices [``units``].
    t_start : array_like, shape (k,), optional
        Start of each window [s]; or give ``window`` (fixed length [s]).
    names : sequence of str, optional
        Coefficient names (default: the 24 canonical names).
    units : {"m/rad", "mm/rad", "um/rad"}
    indices : sequence of int, optional
        Fit (segment) indices, reported in the alerts (default: positions).
    settings : TrendSettings, optional

    Returns
    -------
    list of Alert
        In order of detection.  The test is causal: an alert depends only on the fits up
        to the one that raised it, so a longer sequence never changes earlier alerts.
    """
    s = settings or TrendSettings()
    ts, te, C, S, names = _prepare(times, coefficients, sigma, t_start, window, names, units)
    if C.shape[0] < 2:
        return []
    idx = list(range(C.shape[0])) if indices is None else [int(i) for i in indices]
    return _StepScan(C.shape[1]).run(ts, te, C, S, names, idx, s)


class _StepScan:
    """The state of the CUSUM scan of :func:`detect_steps` over the rows (consecutive
    differences) seen so far, so that a longer sequence of the same fits is scanned from
    where it stopped: the scan is causal (row ``j`` depends on rows up to ``j``), so the
    alerts are the same as a scan from the start, at O(baseline) work per new fit instead of
    O(history)."""

    def __init__(self, P: int):
        self.rows = 0
        self.excluded = np.zeros((0, P), dtype=bool)
        self.hold = np.full(P, -1)  # rows up to here are held off (scanned already)
        self.hold_time = np.full(P, -np.inf)  # and later rows while their older window starts before this
        self.s_plus = np.zeros(P)
        self.s_minus = np.zeros(P)
        self.start_plus = np.zeros(P, dtype=int)
        self.start_minus = np.zeros(P, dtype=int)

    def run(self, ts, te, C, S, names, idx, s: TrendSettings, skip=None) -> list[Alert]:
        """Scan the rows not scanned yet; returns their alerts.  ``skip`` (bool per row): the
        differences left out (across a change of the model's transients: not accumulated, not
        in a baseline, not in a step's size)."""
        P = C.shape[1]
        d, sd = consecutive_differences(ts, te, C, S)  # row j is the difference into window j + 1
        n = d.shape[0]
        skip = np.zeros(n, dtype=bool) if skip is None else np.asarray(skip, dtype=bool)[:n]
        if self.excluded.shape[0] < n:
            self.excluded = np.vstack([self.excluded, np.zeros((n - self.excluded.shape[0], P), dtype=bool)])
        excluded, hold = self.excluded, self.hold
        alerts: list[Alert] = []
        h, k_allow, B = s.step_threshold, s.step_allowance, max(2, int(s.baseline_windows))
        for j in range(self.rows, n):
            if skip[j]:
                excluded[j] = True
                continue
            mu, factor, enough = _baseline(d, sd, excluded, j, B, s.min_history)
            z = (d[j] - mu) / (factor * sd[j])
            for p in range(P):
                if j > hold[p] and j > 0 and ts[j - 1] < self.hold_time[p]:
                    # the ramp of the last step has not passed (batch: j <= ramp_end): held off
                    excluded[j, p] = True
                    continue
                if j <= hold[p] or not enough[p] or not self._cusum(p, j, z[p], h, k_allow):
                    continue
                alerts.append(self._alarm(p, j, (ts, te, d, sd, mu, factor, skip), names[p], idx, (k_allow, h)))
        self.rows = n
        return alerts

    def _cusum(self, p: int, j: int, z: float, h: float, k_allow: float) -> bool:
        """Row ``j`` of coefficient ``p`` (its normalised difference ``z``) into the two
        one-sided sums (a run starts where a sum leaves zero); True when one reaches ``h``."""
        s_plus, s_minus = self.s_plus, self.s_minus
        if s_plus[p] == 0.0:
            self.start_plus[p] = j
        if s_minus[p] == 0.0:
            self.start_minus[p] = j
        s_plus[p] = max(0.0, s_plus[p] + z - k_allow)
        s_minus[p] = max(0.0, s_minus[p] - z - k_allow)
        return not (s_plus[p] < h and s_minus[p] < h)

    def _alarm(self, p: int, j: int, rows: tuple, name: str, idx, bounds: tuple) -> Alert:
        """The alert of coefficient ``p`` raised at row ``j`` (``rows``: ``(ts, te, d, sd, mu,
        factor, skip)``; ``bounds``: ``(allowance, threshold)``), and the scan held off until
        the step's ramp has passed, the sums reset."""
        ts, te, d, sd, mu, factor, skip = rows
        k_allow, h = bounds
        n = d.shape[0]
        up = self.s_plus[p] >= h
        run_start = int(self.start_plus[p] if up else self.start_minus[p])
        stat = float(self.s_plus[p] if up else self.s_minus[p])
        j0 = _change_point(ts, te, d, sd, mu, factor, p, run_start, j, skip)
        alert = _step_alert(ts, te, d, sd, mu, factor, p, j0, j, name, idx, stat, k_allow, h, skip)
        # hold off until the ramp has passed: until a window lies wholly after the
        # latest possible step time (the end of the alarm's older window, te[j]):
        # the rows up to the first window starting after it, those to come included
        ramp_end = int(np.searchsorted(ts, te[j], side="left"))  # first window starting after it
        self.hold[p] = max(j, min(n - 1, ramp_end))  # difference rows up to that window
        self.hold_time[p] = te[j]
        self.excluded[min(j0, run_start) : self.hold[p] + 1, p] = True
        self.s_plus[p] = self.s_minus[p] = 0.0
        return alert


def _baseline(d, sd, excluded, j: int, B: int, min_history: int) -> tuple:
    """The baseline of difference row ``j``: over the ``B`` rows before it not excluded, the
    weighted mean ``mu`` of each coefficient's differences and the robust scale ``factor``
    of their normalised spread (at least 1), where there are ``min_history`` of them
    (``enough``; elsewhere 0 and 1)."""
    P = d.shape[1]
    lo = max(0, j - B)
    past_d = np.where(excluded[lo:j], np.nan, d[lo:j])
    count = np.sum(~np.isnan(past_d), axis=0)
    enough = count >= min_history
    mu = np.zeros(P)
    factor = np.ones(P)
    if np.any(enough):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns
            med_d = np.nanmedian(past_d, axis=0)
            wts = np.where(np.isnan(past_d), 0.0, 1.0 / sd[lo:j] ** 2)
            mean_d = np.sum(wts * np.nan_to_num(past_d), axis=0) / np.where(wts.sum(0) > 0, wts.sum(0), 1.0)
            zc = (past_d - med_d) / sd[lo:j]
            mad = _MAD * np.nanmedian(np.abs(zc - np.nanmedian(zc, axis=0)), axis=0)
        mu = np.where(enough, mean_d, 0.0)
        factor = np.where(enough & np.isfinite(mad), np.maximum(1.0, mad), 1.0)
    return mu, factor, enough


def _ramp(ts, te, j0: int, rows: slice) -> np.ndarray:
    """Window-average ramp of a unit step at ``te[j0]`` seen by the difference rows ``rows``."""
    resp = step_response(ts, te, te[j0])
    return (resp[1:] - resp[:-1])[rows]


def _change_point(ts, te, d, sd, mu, factor, p, run_start: int, j: int, skip=None) -> int:
    """Most likely difference row where the step entered, among the CUSUM run's rows.

    For each candidate the exact ramp is fitted to the run's differences (weighted least
    squares); the candidate with the largest explained chi^2, ``(sum w r y)^2 / sum w r^2``,
    wins.  The CUSUM's own run start tends to be early (noise before the step lifts it).
    """
    rows = slice(run_start, j + 1)
    w = 1.0 / (factor[p] * sd[rows, p]) ** 2
    if skip is not None:
        w = np.where(skip[rows], 0.0, w)
    y = d[rows, p] - mu[p]
    best, best_score = run_start, -1.0
    for c in range(run_start, j + 1):
        r = _ramp(ts, te, c, rows)
        info = float(np.sum(w * r * r))
        if info <= 0:
            continue
        score = float(np.sum(w * r * y)) ** 2 / info
        if score > best_score:
            best, best_score = c, score
    return best


def _step_alert(ts, te, d, sd, mu, factor, p, j0, j, name, idx, stat, k_allow, h, skip=None) -> Alert:
    t_step = te[j0]  # difference row j0 brings in the data after the end of window j0
    r = _ramp(ts, te, j0, slice(j0, j + 1))  # ramp seen by difference rows j0..j
    w = 1.0 / (factor[p] * sd[j0 : j + 1, p]) ** 2
    if skip is not None:
        w = np.where(skip[j0 : j + 1], 0.0, w)
    y = d[j0 : j + 1, p] - mu[p]
    info = float(np.sum(w * r * r))
    size = float(np.sum(w * r * y) / info) if info > 0 else float("nan")
    se = 1.0 / math.sqrt(info) if info > 0 else float("nan")
    sig = size / se if info > 0 else float("nan")
    msg = (
        f"step of {size:+.3f} mm/rad in {name} at {format_time(t_step)} "
        f"({abs(sig):.1f} sigma), detected at {format_time(te[j + 1])}"
    )
    return Alert(
        kind=STEP,
        coefficient=name,
        t=float(t_step),
        value=size,
        significance=sig,
        message=msg,
        t_detected=float(te[j + 1]),
        index=idx[j + 1],
        details={
            "se": se,
            "cusum": stat,
            "allowance": k_allow,
            "threshold": h,
            "change_index": idx[j0 + 1],
            "baseline_mm_per_window": float(mu[p]),
            "scatter_factor": float(factor[p]),
            "differences": int(j - j0 + 1),
        },
    )


# ---------------------------------------------------------------------------- drifts


@dataclass
class TrendEstimates:
    """Linear trends of every coefficient over the last ``lookback`` (see :func:`trend_estimates`).

    Attributes
    ----------
    names : tuple of str
    rate, se, significance : ndarray (P,)
        [mm/rad/day], its standard error (inflated by ``sqrt(chi2/dof)`` when above 1),
        ``rate / se``.  NaN where there are too few windows.
    chi2_dof : ndarray (P,)
        Whitened residual chi^2 per degree of freedom of the line.
    windows : int
        Number of fits used.
    t_first, t_last : float
        First and last window end used [s].
    steps : dict
        Coefficient name -> step times modelled [s].
    """

    names: tuple
    rate: np.ndarray
    se: np.ndarray
    significance: np.ndarray
    chi2_dof: np.ndarray
    windows: int
    t_first: float
    t_last: float
    steps: dict = field(default_factory=dict)


def trend_estimates(
    times,
    coefficients,
    sigma,
    *,
    t_start=None,
    window: float | None = None,
    names: Sequence[str] | None = None,
    units: str = "m/rad",
    steps: Sequence[Alert] = (),
    at: float | None = None,
    settings: TrendSettings | None = None,
    breaks: Sequence[float] = (),
) -> TrendEstimates:
    """GLS line through the fits of the last ``lookback`` with the overlap covariance.

    Parameters are those of :func:`detect_steps`; ``steps`` are step alerts whose steps
    are modelled as nuisance terms, ``at`` the time of evaluation (default: the last
    window end; fits ending after it are ignored); ``breaks`` are window ends from which the
    fits are under another model's transients: each adds a free level from that fit on (the
    estimate jumps there at once, not along a step's ramp).
    """
    s = settings or TrendSettings()
    ts, te, C, S, names = _prepare(times, coefficients, sigma, t_start, window, names, units)
    P = C.shape[1]
    nan = np.full(P, np.nan)
    t_end = te[-1] if at is None else float(at)
    sel = (te <= t_end) & (te > t_end - s.drift_lookback)
    n = int(sel.sum())
    if n < max(3, s.drift_min_windows):
        return TrendEstimates(
            tuple(names),
            nan,
            nan.copy(),
            nan.copy(),
            nan.copy(),
            n,
            float(te[sel][0]) if n else float("nan"),
            float(t_end),
        )
    ts, te, C, S = ts[sel], te[sel], C[sel], S[sel]
    rho = window_correlation(ts, te)
    centre = 0.5 * (ts + te)
    x = (centre - centre.mean()) / DAY
    rate, se, sig, chi2dof = nan.copy(), nan.copy(), nan.copy(), nan.copy()
    modelled: dict[str, list[float]] = {}
    by_name: dict[str, list[float]] = {}
    for a in steps:
        if a.kind == STEP and math.isfinite(a.t):
            by_name.setdefault(a.coefficient, []).append(float(a.t))
    # cov_p = D_p rho D_p with D_p = diag(S[:, p]): one Cholesky factor of rho serves every
    # coefficient (L_p = D_p L_rho, whitening = triangular solves, O(n^2) each)
    rho_j = rho.copy()
    rho_j[np.diag_indices(n)] *= 1.0 + 1e-9
    try:
        L_rho = np.linalg.cholesky(rho_j)
    except np.linalg.LinAlgError:
        L_rho = None
    levels = [col for col in ((te >= float(b)).astype(float) for b in sorted(breaks)) if np.ptp(col) > 0]
    for p in range(P):
        cols = [np.ones(n), x, *levels]
        for t_step in sorted(by_name.get(names[p], ())):
            col = step_response(ts, te, t_step)
            if np.ptp(col) > 1e-6:
                cols.append(col)
                modelled.setdefault(names[p], []).append(t_step)
        rate[p], se[p], chi2dof[p], dropped = _coefficient_trend(
            np.stack(cols, axis=1), C[:, p], S[:, p], rho, L_rho, len(levels)
        )
        if dropped:
            modelled.pop(names[p], None)
        sig[p] = rate[p] / se[p]
    return TrendEstimates(tuple(names), rate, se, sig, chi2dof, n, float(te[0]), float(te[-1]), modelled)


def _coefficient_trend(X: np.ndarray, y: np.ndarray, sp: np.ndarray, rho, L_rho, n_levels: int) -> tuple:
    """GLS fit of one coefficient's estimates ``y`` (errors ``sp``, correlation ``rho``, its
    Cholesky factor ``L_rho`` or None) on the columns ``X``: constant, line, ``n_levels``
    levels, then steps.  Steps that cannot be told from the trend are dropped (then the
    levels too if still ill-conditioned).

    Returns
    -------
    (float, float, float, bool)
        The rate (the line's coefficient, per day), its standard error (inflated by
        ``sqrt(chi2/dof)`` when that exceeds 1 with 5 or more degrees of freedom),
        ``chi2/dof`` and whether the steps were dropped.
    """
    n = y.size
    if L_rho is not None and np.all(sp > 0):
        Xw = solve_triangular(L_rho, X / sp[:, None], lower=True)
        yw = solve_triangular(L_rho, y / sp, lower=True)
    else:
        cov = rho * np.outer(sp, sp)
        cov[np.diag_indices(n)] *= 1.0 + 1e-9
        w, V = np.linalg.eigh(cov)
        L = V * np.sqrt(np.clip(w, w.max() * 1e-12, None))
        Xw = np.linalg.solve(L, X)
        yw = np.linalg.solve(L, y)
    beta, *_ = np.linalg.lstsq(Xw, yw, rcond=None)
    A = Xw.T @ Xw
    dropped = False
    if np.linalg.cond(A) > 1e12:  # a step that cannot be told from the trend: drop steps
        keep = 2 + n_levels
        Xw, A = Xw[:, :keep], (Xw[:, :keep]).T @ Xw[:, :keep]
        if np.linalg.cond(A) > 1e12:  # nor a level (a break among the last fits): drop those too
            Xw, A = Xw[:, :2], (Xw[:, :2]).T @ Xw[:, :2]
        beta, *_ = np.linalg.lstsq(Xw, yw, rcond=None)
        dropped = True
    resid = yw - Xw @ beta
    dof = n - Xw.shape[1]
    chi2 = float(resid @ resid)
    cd = chi2 / dof if dof > 0 else float("nan")
    inflate = math.sqrt(cd) if dof >= 5 and cd > 1 else 1.0
    var = np.linalg.inv(A)[1, 1]
    return beta[1], math.sqrt(var) * inflate, cd, dropped


def detect_drifts(
    times,
    coefficients,
    sigma,
    *,
    t_start=None,
    window: float | None = None,
    names: Sequence[str] | None = None,
    units: str = "m/rad",
    steps: Sequence[Alert] = (),
    at: float | None = None,
    indices: Sequence[int] | None = None,
    settings: TrendSettings | None = None,
    breaks: Sequence[float] = (),
) -> list[Alert]:
    """Drift alerts: coefficients whose linear trend over the last ``drift_lookback`` is
    significant (``|rate| / se >= drift_threshold``), evaluated at the last fit (or ``at``).

    Parameters are those of :func:`trend_estimates` (typed here too, so that callers are
    checked); ``indices`` the segment index of each fit (the alerts').  Returns the alerts,
    most significant first (:func:`drift_alerts`).
    """
    est = trend_estimates(
        times,
        coefficients,
        sigma,
        t_start=t_start,
        window=window,
        names=names,
        units=units,
        steps=steps,
        at=at,
        settings=settings,
        breaks=breaks,
    )
    return drift_alerts(est, times, indices, settings)


def drift_alerts(
    est: TrendEstimates, times, indices: Sequence[int] | None = None, settings: TrendSettings | None = None
) -> list[Alert]:
    """The drift alerts of trend estimates ``est`` (:func:`trend_estimates` of fits ending at
    ``times`` [s], with segment ``indices``): the coefficients whose trend is significant
    (``|rate| / se >= drift_threshold``), most significant first."""
    s = settings or TrendSettings()
    t_stop = np.asarray(times, dtype=float).reshape(-1)
    last = int(np.searchsorted(t_stop, est.t_last, side="right") - 1) if t_stop.size else 0
    index = None if indices is None or not len(indices) else int(list(indices)[max(0, last)])
    alerts = []
    for p in np.argsort(-np.nan_to_num(np.abs(est.significance), nan=-1.0)):
        z = est.significance[p]
        if not (np.isfinite(z) and abs(z) >= s.drift_threshold):
            continue
        name = est.names[p]
        msg = (
            f"drift of {est.rate[p]:+.3f} mm/rad/day in {name} over the last "
            f"{(est.t_last - est.t_first) / DAY + 0.0:.2f} d of fits ({abs(z):.1f} sigma)"
        )
        alerts.append(
            Alert(
                kind=DRIFT,
                coefficient=name,
                t=est.t_last,
                value=float(est.rate[p]),
                significance=float(z),
                message=msg,
                t_detected=est.t_last,
                index=index,
                details={
                    "se": float(est.se[p]),
                    "chi2_dof": float(est.chi2_dof[p]),
                    "windows": est.windows,
                    "t_first": est.t_first,
                    "lookback": s.drift_lookback,
                    "steps_modelled": est.steps.get(name, []),
                },
            )
        )
    return alerts


# ---------------------------------------------------------------------------- streaming use


def is_transient(spec: str) -> bool:
    """Whether an effect spec names a transient of a model (``Effect.transient``: a glitch, a
    gate), whose change alone starts no new epoch; an effect this process does not know (a
    plugin not loaded here) counts as a coupling."""
    cls = EFFECTS.get(spec.partition(":")[0].strip())
    return bool(cls is not None and cls.transient)


def model_key(model) -> tuple[tuple[str, ...], tuple[str, ...]] | None:
    """``(couplings, transients)`` of a model (a list of effect specs, as a fit's meta
    ``model``), each sorted; None when ``model`` is not a list (unknown).  Two fits are in one
    model epoch when their couplings are equal; a change of the transients alone is a break
    of the series (module docstring, "Model epochs")."""
    if not isinstance(model, (list, tuple)):
        return None
    specs = [str(spec).strip() for spec in model]
    transient = [is_transient(spec) for spec in specs]
    return (
        tuple(sorted(spec for spec, t in zip(specs, transient) if not t)),
        tuple(sorted(spec for spec, t in zip(specs, transient) if t)),
    )


@dataclass
class ModelEpoch:
    """A stretch of fits under one model's couplings (:class:`TrendMonitor`).

    Attributes
    ----------
    number : int
        0 for the first epoch of the run, then 1, 2, ...
    index : int
        The epoch's first fit (the first fit under its model).
    t_start, t_stop : float
        That fit's window [s].
    model : list of str or None
        Its effect specs (None: not known).
    breaks : list of int
        Fits from which the transients changed within the epoch (the difference into each is
        not tested).
    """

    number: int
    index: int
    t_start: float
    t_stop: float
    model: list | None = None
    breaks: list = field(default_factory=list)

    def to_json(self) -> dict:
        return asdict(self)


class TrendMonitor:
    """Feeds fits one at a time and reports each new alert once (used by the monitor stage).

    Steps come from :func:`detect_steps` on the stored history (causal, so alerts do not
    change as fits arrive; an alert of a coefficient within one window length of one
    already reported is a duplicate).  Drifts are re-evaluated at every fit: a drift is
    reported when its significance first reaches ``drift_threshold``, and again only after
    it has fallen below ``drift_release``.  Both look at the fits of the current model epoch
    only (:meth:`add`'s ``model``; module docstring, "Model epochs").

    Parameters
    ----------
    names : sequence of str, optional
    settings : TrendSettings, optional
    units : str
        Units of the coefficients given to :meth:`add` (default m/rad).
    max_history : float
        History kept [s] (default 30 days).

    Attributes
    ----------
    alerts : list of Alert
        Every alert reported, all epochs.
    epoch : ModelEpoch or None
        The current model epoch; ``epochs`` every epoch so far, oldest first.
    """

    def __init__(
        self,
        names: Sequence[str] | None = None,
        settings: TrendSettings | None = None,
        units: str = "m/rad",
        max_history: float = 30 * DAY,
    ):
        self.names = tuple(names) if names is not None else COEFFICIENT_NAMES
        self.settings = settings or TrendSettings()
        self.units = units
        self.max_history = float(max_history)
        # index -> (t_start, t_stop, coefficients, sigmas, model, model_key)
        self._fits: dict[int, tuple[float, float, np.ndarray, np.ndarray, list | None, tuple | None]] = {}
        self.alerts: list[Alert] = []
        self._epoch_alerts: list[Alert] = []  # the current epoch's (duplicates, steps in the drift line)
        self._drifting: set[str] = set()
        self.estimates: TrendEstimates | None = None
        self.cusum = np.zeros(len(self.names))
        self._scan: _StepScan | None = None
        self._scanned: list = []
        self.epoch: ModelEpoch | None = None
        self.epochs: list[ModelEpoch] = []

    def add(self, index: int, t_start: float, t_stop: float, coefficients, sigma, model=None) -> list[Alert]:
        """Store one fit and return the alerts it raises (possibly none).  ``model``: the
        effect specs the fit was estimated under (a fit message's meta ``model``; None: the
        model of the fit before it)."""
        self._store(index, t_start, t_stop, coefficients, sigma, model)
        order, breaks = self._series()
        ts = np.array([self._fits[i][0] for i in order])
        te = np.array([self._fits[i][1] for i in order])
        Cs = np.array([self._fits[i][2] for i in order])
        Ss = np.array([self._fits[i][3] for i in order])
        new: list[Alert] = []
        for a in self._steps(order, breaks, (ts, te, Cs, Ss)):
            a = self._in_epoch(a)
            if not self._known_step(a):
                self.alerts.append(a)
                self._epoch_alerts.append(a)
                new.append(a)
        steps = [a for a in self._epoch_alerts if a.kind == STEP]
        at_breaks = [float(te[k]) for k in sorted(breaks)]
        self.estimates = trend_estimates(
            te,
            Cs,
            Ss,
            t_start=ts,
            names=self.names,
            units=self.units,
            steps=steps,
            settings=self.settings,
            breaks=at_breaks,
        )
        z = np.nan_to_num(np.abs(self.estimates.significance), nan=0.0)
        for a in drift_alerts(self.estimates, te, order, self.settings):
            if a.coefficient not in self._drifting:
                a = self._in_epoch(a)
                self._drifting.add(a.coefficient)
                self.alerts.append(a)
                self._epoch_alerts.append(a)
                new.append(a)
        for p, name in enumerate(self.names):
            if name in self._drifting and z[p] < self.settings.drift_release:
                self._drifting.discard(name)
        return new

    def _store(self, index: int, t_start: float, t_stop: float, coefficients, sigma, model) -> None:
        """One fit validated and stored (replacing one with the same window end), the
        history trimmed to ``max_history``; ValueError naming the fit when it is not valid."""
        C = np.asarray(coefficients, dtype=float).reshape(-1)
        S = np.asarray(sigma, dtype=float)
        if S.ndim == 2:
            S = np.sqrt(np.maximum(np.diag(S), 0.0))
        S = S.reshape(-1)
        if C.size != len(self.names) or S.size != len(self.names):
            raise ValueError(f"fit {index}: {C.size} coefficients and {S.size} sigmas for {len(self.names)} names")
        if not (math.isfinite(t_start) and math.isfinite(t_stop) and t_stop > t_start):
            raise ValueError(f"fit {index}: window [{t_start}, {t_stop}] is not valid")
        # one fit per window end (a refit of the same index replaces it)
        for other, (_, stop, *_rest) in list(self._fits.items()):
            if stop == t_stop and other != index:
                del self._fits[other]
        key = model_key(model)
        self._fits[int(index)] = (float(t_start), float(t_stop), C, S, list(model) if key else None, key)
        horizon = max(f[1] for f in self._fits.values()) - self.max_history
        for other, (_, stop, *_rest) in list(self._fits.items()):
            if stop < horizon:
                del self._fits[other]

    def _steps(self, order: list[int], breaks: set[int], series: tuple) -> list[Alert]:
        """The step alerts of the epoch's fits ``order`` (``series``: their window starts and
        ends [s], coefficients and sigmas): the causal scan goes on from the fits scanned
        before (O(baseline) per fit); from the start again when the history changed otherwise
        (a refit, trimmed history, a new epoch)."""
        ts, te, Cs, Ss = series
        keys = [(i, self._fits[i][1], k in breaks) for k, i in enumerate(order)]
        if self._scan is None or keys[: len(self._scanned)] != self._scanned or len(keys) < 2:
            self._scan, self._scanned = _StepScan(len(self.names)), []
        found = []
        if len(keys) >= 2:
            ts_, te_, C_, S_, names_ = _prepare(te, Cs, Ss, ts, None, self.names, self.units)
            skip = np.array([k + 1 in breaks for k in range(len(order) - 1)])
            found = self._scan.run(ts_, te_, C_, S_, names_, order, self.settings, skip)
            self._scanned = keys
        return found

    def _series(self) -> tuple[list[int], set[int]]:
        """The fits of the current model epoch in order of window end, and the positions in
        it where the transients changed; a new epoch (its first fit later than the current
        one's) resets what the trends carried (the scan restarts with the fits it is given)."""
        order = sorted(self._fits, key=lambda i: self._fits[i][1])
        keys: list = []
        for i in order:  # a fit without a model is under the model of the fit before it
            key = self._fits[i][5]
            keys.append(key if key is not None or not keys else keys[-1])
        start = 0
        for k in range(1, len(order)):
            if keys[k] is not None and keys[k - 1] is not None and keys[k][0] != keys[k - 1][0]:
                start = k
        breaks = {
            k
            for k in range(start + 1, len(order))
            if keys[k] is not None and keys[k - 1] is not None and keys[k][1] != keys[k - 1][1]
        }
        first = order[start]
        t_first = self._fits[first][1]
        if self.epoch is None or (start > 0 and t_first > self.epoch.t_stop):
            if self.epoch is not None:  # a new model: what the trends carried was another model's
                self._epoch_alerts, self._drifting = [], set()
            self.epoch = ModelEpoch(len(self.epochs), first, self._fits[first][0], t_first, self._fits[first][4])
            self.epochs.append(self.epoch)
        elif start > 0 and t_first < self.epoch.t_stop:  # its first fit came late
            self.epoch.index, self.epoch.t_start, self.epoch.t_stop = first, self._fits[first][0], t_first
        self.epoch.breaks = [order[k] for k in sorted(breaks)]
        return order[start:], {k - start for k in breaks}

    def _in_epoch(self, a: Alert) -> Alert:
        """The alert with its model epoch in ``details`` (``model_epoch``)."""
        return replace(a, details={**a.details, "model_epoch": self.epoch.number if self.epoch else 0})

    def _known_step(self, a: Alert) -> bool:
        """Already reported in this epoch: same coefficient, step time within one window length."""
        lengths = [f[1] - f[0] for f in self._fits.values()]
        length = float(np.median(lengths)) if lengths else 0.0
        return any(
            b.kind == STEP and b.coefficient == a.coefficient and abs(b.t - a.t) <= length for b in self._epoch_alerts
        )

    @property
    def drifting(self) -> frozenset:
        """Coefficients currently in a reported drift."""
        return frozenset(self._drifting)

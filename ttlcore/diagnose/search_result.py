"""What a search of an effect's nonlinear parameters returns (:class:`SearchResult`) and the
ranges it searches (:func:`search_ranges`): shared by the profile search
(:mod:`ttlcore.diagnose.search`), the step-time search (:mod:`ttlcore.diagnose.step_search`),
the offset search (:mod:`ttlcore.diagnose.offset_search`) and the glitch search."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..effects.base import Effect
from ..effects.shifted import OFFSET_OPTION
from ..errors import ConfigError
from .evidence import (
    Evidence,
)

log = logging.getLogger(__name__)

#: The log Bayes factor a search gives a point where the columns are collinear with the model's.
COLLINEAR = -1e300


@dataclass(frozen=True)
class SearchResult:
    """Outcome of a profile search.

    Attributes
    ----------
    effect : Effect
        The effect with the searched options set to their estimates.
    estimates : dict
        Parameter -> estimate.
    intervals : dict
        Parameter -> (low, high), one sigma from the profile's curvature (empty when not
        measured).
    delta_chi2 : float
        Profiled chi^2 gain at the estimate (over ``kappa``).
    log_bayes_factor_best, log_bayes_factor : float
        At the estimate, and marginalised over the searched parameters.
    n_evaluations : int
    grid : list
        ``(parameters, value)`` of the grid points.
    evidence : Evidence or None
        The evidence at the estimate when the search computed it with columns more exact
        than those :func:`ttlcore.diagnose.columns.effect_columns` gives (the step time).
    gains : dict
        Per searched parameter, the chi^2 gain of its estimate against zero, the others at
        their estimates (offsets).
    theta : dict
        Column -> linear parameter at the optimum (offsets).
    """

    effect: Effect
    estimates: dict
    intervals: dict
    delta_chi2: float
    log_bayes_factor_best: float
    log_bayes_factor: float
    n_evaluations: int
    grid: list = field(default_factory=list, repr=False)
    evidence: Evidence | None = field(default=None, repr=False)
    gains: dict = field(default_factory=dict)
    theta: dict = field(default_factory=dict, repr=False)

    def to_json(self) -> dict:
        return {
            "estimates": {k: float(v) for k, v in self.estimates.items()},
            "intervals": {k: [float(a), float(b)] for k, (a, b) in self.intervals.items()},
            "delta_chi2": float(self.delta_chi2),
            "log_bayes_factor_best": float(self.log_bayes_factor_best),
            "log_bayes_factor_marginal": float(self.log_bayes_factor),
            "evaluations": int(self.n_evaluations),
        }


def search_ranges(data, effect) -> dict:
    """The declared ranges, frequencies (``f0``, ``fc``, names starting with ``f``) clipped
    to the diagnosis band widened by a third of an octave, periods (names starting with
    ``period``) to twice the analysed span, the offsets of shifted-witness effects (names
    starting with ``offset.``) to ``+-settings.shift_span``."""
    out = {}
    idx = np.flatnonzero(data.grid.mask)
    span = (idx[-1] - idx[0]) / data.grid.fs
    for k, (lo, hi, scale) in effect.searched.items():
        if k.startswith("f"):
            lo, hi = max(lo, data.grid.f[0] / 1.26), min(hi, data.grid.f[-1] * 1.26)
        if k.startswith("period"):
            hi = min(hi, 2 * span)
        if k.startswith(OFFSET_OPTION):
            lo, hi = max(lo, -float(data.context.settings.shift_span)), min(hi, float(data.context.settings.shift_span))
        if lo >= hi:
            raise ConfigError(f"effect {effect.name!r}: the range of {k} does not fit these data")
        out[k] = (float(lo), float(hi), scale)
    return out

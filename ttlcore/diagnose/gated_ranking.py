"""The candidates ranked again on the data with the signals gated: the simplest effect that
explains the excess there.

docs/diagnostics.md, "Candidates beside a signal".  The candidates are first scored on the
data as they are (:class:`ttlcore.diagnose.candidates.CandidatePool`).  Beside a loud
signal (a merger's hours, a glitch, a noise change: the transient finder's
:data:`~ttlcore.diagnose.transients.NOT_AN_EFFECT` classes) a candidate with a shape of its
own - a resonance, a pole, a modulation - can take the signal's power as well as the
coupling's, and win on evidence the quiet data do not give it (a merger day with a
round-trip ghost advised a 7.2 mHz, Q 47 resonance on the right witness: the shape existed
only to take the chirp).  The significant candidates are therefore scored again, at the
parameters their search found, on the model refitted with the signals' spans gated (the
fit the transient finder reads its quiet tiles on), and the recommendation is

- the candidate with the largest ``delta chi^2`` there, unless
- a candidate with fewer parameters (its own plus the ones its search estimated) explains
  the gated data alike: its ``delta chi^2`` short of the best's by less than the
  ``1 - alpha`` quantile of chi^2 with the difference in parameters, or than the noise
  model's tolerance times the best's ``delta chi^2`` (a shape that improves the fit by
  less than the tolerance of the test is not needed); then the simplest of those, and
  between equals the higher evidence.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from scipy import stats

from ..errors import ConfigError
from .candidates import rescore
from .model_fit import ModelFit

__all__ = ["GatedRanking", "rank_on_gated", "simplest_alike", "reordered", "complexity"]

log = logging.getLogger(__name__)

#: Significant candidates scored again on the gated data (best first by their evidence on
#: the data as they are): seconds each, at the parameters their search found.
MAX_RESCORED = 8


def complexity(candidate: dict) -> int:
    """A candidate's parameters: its linear ones plus the nonlinear ones its search
    estimated (a resonance's ``f0`` and ``q``, a pole's ``fc``, a step's time)."""
    searched = candidate.get("searched") or {}
    n = len((searched.get("search") or {}).get("estimates") or {}) + ("t_step" in searched)
    return int(candidate.get("n_parameters") or 0) + n


@dataclass(frozen=True)
class GatedRanking:
    """The candidates scored on the gated data (:func:`rank_on_gated`).

    Attributes
    ----------
    spans : tuple of (float, float)
        The spans gated [s] (the signals' and the gaps').
    scores : tuple of dict
        ``{"cli_spec", "complexity", "delta_chi2", "delta_chi2_gated"}`` per candidate
        scored, in the order of the first ranking.
    chosen : str
        ``cli_spec`` of the candidate advised.
    reason : str
        Why it, in one sentence.
    """

    spans: tuple[tuple[float, float], ...]
    scores: tuple[dict, ...]
    chosen: str
    reason: str

    def to_json(self) -> dict:
        return {
            "spans": [list(s) for s in self.spans],
            "scores": list(self.scores),
            "chosen": self.chosen,
            "reason": self.reason,
        }


def rank_on_gated(candidates: list[dict], gated: ModelFit, alpha: float, tolerance: float) -> GatedRanking | None:
    """Score the significant ``candidates`` (a diagnosis' ranked list) again on ``gated``
    (the model refitted with the signals' spans gated) and choose the simplest that
    explains the gated data as well as the best (module docstring).  None when fewer than
    two could be scored there (nothing to choose between)."""
    significant = [c for c in candidates if c.get("significant")][:MAX_RESCORED]
    if len(significant) < 2:
        return None
    C = gated.ttl_coefficients()
    scored = []
    for c in significant:
        try:
            ev = rescore(gated, c, C)
        except ConfigError as exc:
            log.info("candidate %s not scored on the gated data: %s", c["cli_spec"], exc)
            continue
        scored.append((c, float(ev.delta_chi2), float(ev.log_bayes_factor)))
    if len(scored) < 2:
        return None
    best, best_chi2, _ = max(scored, key=lambda x: x[1])
    chosen, chosen_chi2 = simplest_alike(scored, alpha, tolerance)
    k_best = complexity(best)
    if chosen is best:
        reason = f"the largest delta chi2 on the gated data ({best_chi2:.1f})"
    else:
        reason = (
            f"explains the gated data as {best['cli_spec']} does (delta chi2 {chosen_chi2:.1f} against "
            f"{best_chi2:.1f}) with {k_best - complexity(chosen)} parameter(s) fewer"
        )
    spans = tuple((float(a), float(b)) for a, b in getattr(gated.data.grid, "gate_spans", ()))
    spans += tuple((float(a), float(b)) for a, b in getattr(gated.data.grid, "gap_spans", ()))
    return GatedRanking(
        spans=spans,
        scores=tuple(
            {
                "cli_spec": c["cli_spec"],
                "complexity": complexity(c),
                "delta_chi2": c["delta_chi2"],
                "delta_chi2_gated": d,
            }
            for c, d, _ in scored
        ),
        chosen=chosen["cli_spec"],
        reason=reason,
    )


def simplest_alike(scored: list[tuple[dict, float, float]], alpha: float, tolerance: float) -> tuple[dict, float]:
    """The candidate to advise among ``scored`` (``(candidate, delta_chi2, log_bayes_factor)``
    on the gated data) and its ``delta chi^2``: the one with the fewest parameters
    (:func:`complexity`) among those that explain the data as the best does (module
    docstring), between equals the higher evidence."""
    best, best_chi2, _ = max(scored, key=lambda x: x[1])
    k_best = complexity(best)
    alike = []
    for c, d, logb in scored:
        k = complexity(c)
        if k >= k_best and c is not best:
            continue
        dk = max(k_best - k, 1)
        margin = max(float(stats.chi2.isf(alpha, dk)), tolerance * max(best_chi2, 0.0))
        if best_chi2 - d <= margin:
            alike.append((k, -logb, c, d))
    alike.sort(key=lambda x: (x[0], x[1]))
    return alike[0][2], alike[0][3]


def reordered(candidates: list[dict], ranking: GatedRanking) -> list[dict]:
    """``candidates`` with the chosen one first and every rescored one carrying its
    ``delta_chi2_gated``."""
    gated = {s["cli_spec"]: s["delta_chi2_gated"] for s in ranking.scores}
    out = [{**c, "delta_chi2_gated": gated[c["cli_spec"]]} if c["cli_spec"] in gated else c for c in candidates]
    first = next(c for c in out if c["cli_spec"] == ranking.chosen)
    return [first] + [c for c in out if c is not first]

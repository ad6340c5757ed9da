"""Candidates: every effect that could be added to a fitted model, scored by evidence.

Each candidate goes through the same steps (docs/diagnostics.md, "Candidates"): its
searched parameters, if any, are profiled (:func:`ttlcore.diagnose.glitches.effect_search`:
the step time, the poles of a frequency-dependent coupling, a plugin's parameters); its
columns are built at the estimates (:func:`ttlcore.diagnose.columns.effect_columns`) and
its evidence computed against the model (:func:`ttlcore.diagnose.evidence.added_evidence`,
the errors-in-variables term of model and candidate together); a shifted-witness effect
whose Taylor columns are significant is scored with its offsets searched, as the model
would hold it (:func:`ttlcore.diagnose.fitting.fit_model`, Laplace evidence).  Nothing a
candidate builds changes the model or the data (both are values).
"""

from __future__ import annotations

import logging
import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace

import numpy as np
from scipy import stats
from threadpoolctl import threadpool_limits

from ..effects.base import Effect
from ..effects.registry import make_effects
from ..errors import ConfigError
from .columns import effect_columns
from .evidence import Evidence, added_evidence, laplace_evidence
from .fitting import fit_model, fit_resolved
from .glitches import effect_search
from .model_fit import ModelFit, parameter_name, total_offset

log = logging.getLogger(__name__)

#: Column sets of the store (:class:`ttlcore.diagnose.columns.ColumnStore`, by the first item
#: of their key) that several candidates ask for: the TDI regressors, their derivatives (the
#: timing offsets'), the base columns of the pole searches.  The others a candidate builds
#: are its own, dropped once it is scored when candidates are scored one at a time.
SHARED_SETS = ("regressors", "derivatives", "base")


def rank_key(c: dict) -> tuple:
    """The order of a ranking: significant candidates first, then by log Bayes factor."""
    return (not c["significant"], -np.nan_to_num(c["log_bayes_factor"], nan=-np.inf))


def candidates(model: ModelFit, names=None, extra=(), workers: int = 1) -> list[dict]:
    """Try every available effect not in ``model`` and the effect instances ``extra``
    (witness effects and frequency-dependent couplings of the top witnesses,
    :func:`ttlcore.diagnose.witnesses.witness_candidates`); ranked list (best first).
    Effects that need options to mean anything (``witness``, ``fd-coupling``) are tried
    through ``extra`` only.  ``workers`` threads score candidates side by side
    (:class:`CandidatePool`; the result does not depend on it)."""
    with CandidatePool(model, workers) as pool:
        pool.submit(named_candidates(model, names))
        pool.submit(extra)
        return pool.ranked()


def named_candidates(model: ModelFit, names=None) -> list:
    """The named effects (registry names, or ``names``) that could be added to ``model``,
    as effect instances with their default options; the costly searches first (the step
    time, the offsets, any searched parameter), so that parallel scoring ends together."""
    data = model.data
    registry = data.context.registry
    in_model = {e.name for e in model.effects}
    # witness effects need options; glitches and gates are tried where the transient
    # finder localises an excess (:func:`transient_actions`): Effect.named_candidate
    todo = [n for n in (names or registry) if n not in in_model and registry[n].named_candidate]
    effects = [registry[n]() for n in todo]
    return sorted(effects, key=lambda e: not (e.unresolved() or hasattr(e, "shifted_members")))


class CandidatePool:
    """Candidates scored against one model, ``workers`` at a time (threads).

    Scoring only reads the model and the data (values: their arrays are read-only), and
    the expensive parts are numpy, FFT and BLAS calls that release the GIL, so threads
    share the data instead of copying it.  With more than one worker, BLAS runs one
    thread per call while the pool is open (threadpoolctl): two threads each asking
    OpenBLAS for every core spin against each other (docs/diagnostics.md, "Measured").

    Use as a context manager: :meth:`submit` effects (names or instances) as they become
    known - the witness candidates after the witness search, while the named ones are
    being scored - then :meth:`ranked`.
    """

    def __init__(self, model: ModelFit, workers: int = 1, checkpoint=None):
        self.model = model
        # called before each candidate is scored; may raise to abandon the ranking (a stage
        # told to stop): ttlcore.diagnose.diagnoser.diagnose's ``checkpoint``
        self.checkpoint = checkpoint or (lambda step: None)
        data = model.data
        s = data.context.settings
        self.C = model.ttl_coefficients()
        # the excess the noise model (with its tolerance) cannot explain
        self.excess = (
            float(np.sum(np.maximum(model.bands.chi2 - (1 + s.tolerance) * model.bands.dof, 0.0))) / data.grid.kappa
        )
        self.n_data = float(model.dof_band.sum())
        self.workers = max(1, int(workers))
        self._seen = {e.spec() for e in model.effects}
        self._futures: list = []
        self._executor: ThreadPoolExecutor | None = None
        self._limits: threadpool_limits | None = None

    def __enter__(self):
        if self.workers > 1:
            self._limits = threadpool_limits(limits=1, user_api="blas")
            self._executor = ThreadPoolExecutor(self.workers, thread_name_prefix="candidate")
        return self

    def __exit__(self, *exc):
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=exc[0] is not None)
        if self._limits is not None:
            self._limits.restore_original_limits()
        return False

    def submit(self, effects) -> None:
        """Queue effects (registry names or :class:`~ttlcore.effects.base.Effect`
        instances) for scoring; one already in the model or queued is skipped."""
        registry = self.model.data.context.registry
        for effect in effects:
            if not isinstance(effect, Effect):
                effect = registry[effect]()
            if effect.spec() in self._seen:
                continue
            self._seen.add(effect.spec())
            self._queue(effect)

    def submit_reshapes(self) -> None:
        """Queue every effect of the model whose shape can be searched again
        (:meth:`~ttlcore.effects.base.Effect.reshaped`) as a candidate that replaces it
        (:func:`replacement_evidence`; the entry's ``replaces`` names it)."""
        for old in self.model.effects:
            new = old.reshaped()
            if new is None or "replaces " + old.spec() in self._seen:
                continue
            self._seen.add("replaces " + old.spec())
            self._queue(new, old)

    def _queue(self, effect, replaces=None) -> None:
        if self._executor is None:  # serial: scored now, held as a finished future
            done: Future = Future()
            store = self.model.data.context.store
            mark = store.mark()
            done.set_result(self.score(effect, replaces))
            # its trial columns are no other candidate's: not kept through the phase (a day's
            # drift candidate holds 80 MB); the sets candidates share are
            store.release_since(mark, keep=SHARED_SETS)
            self._futures.append(done)
        else:
            self._futures.append(self._executor.submit(self.score, effect, replaces))

    def ranked(self) -> list[dict]:
        """Every submitted candidate that could be scored, best first (significant ones
        first, then by log Bayes factor)."""
        out = [r for r in (f.result() for f in self._futures) if r is not None]
        out.sort(key=rank_key)
        return out

    def score(self, effect, replaces=None) -> dict | None:
        """One candidate's entry of the ranking (None when it cannot be scored here):
        ``effect`` added to the model, or put in the place of its effect ``replaces``."""
        self.checkpoint(f"candidate {effect.spec()}")
        model, data = self.model, self.model.data
        s = data.context.settings
        cls, name = type(effect), effect.name
        t_start = time.monotonic()
        try:
            if replaces is None:
                ev, extra_json = score(model, effect, self.C)
            else:
                ev, extra_json = replacement_evidence(model, replaces, effect, self.C)
        except ConfigError as exc:
            log.info("candidate %s skipped: %s", name, exc)
            return None
        n_searched = len(extra_json.get("search", {}).get("estimates", {})) + ("t_step" in extra_json)
        ev = replace(ev, delta_bic=ev.delta_chi2 - (ev.n_parameters + n_searched) * math.log(self.n_data))
        k = ev.n_parameters
        # a searched nonlinear parameter counts as one more degree of freedom (a rough
        # allowance for the look-elsewhere effect of the search; the evidence is marginal)
        k_eff = k + len(extra_json.get("search", {}).get("estimates", {}))
        p = float(stats.chi2.sf(max(ev.delta_chi2, 0.0), k_eff))
        significant = bool(p < s.alpha and ev.log_bayes_factor > s.log_bf_threshold)
        found = extra_json.pop("_effect", effect)
        return {
            "effect": name,
            "spec": found.spec(),
            "cli_spec": found.cli_spec(),
            "title": cls.title,
            "physics": cls.physics,
            "n_parameters": k,
            "delta_chi2": float(ev.delta_chi2),
            "p_value": p,
            "log_bayes_factor": float(ev.log_bayes_factor),
            "delta_bic": float(ev.delta_bic) if ev.delta_bic is not None else None,
            "explained_fraction": float(min(1.0, max(ev.delta_chi2, 0.0) / self.excess)) if self.excess > 0 else 0.0,
            "significant": significant,
            "where": where(data, ev, extra_json),
            "parameters": top_parameters(ev),
            "seconds": round(time.monotonic() - t_start, 2),
            **({"replaces": replaces.spec()} if replaces is not None else {}),
            **({"searched": extra_json} if extra_json else {}),
        }


def score(model: ModelFit, effect, C) -> tuple[Evidence, dict]:
    """The evidence for adding ``effect`` to ``model`` and what its search found
    (``{"search": ...}``, ``{"t_step": ...}`` or ``{"offsets": ...}``; the key ``_effect``
    holds the effect at the estimates).  ConfigError when it cannot be scored here."""
    data = model.data
    extra: dict = {}
    if effect.unresolved():
        found = effect_search(model, effect, C, screen=True)  # refined only where it could matter
        effect = found.effect
        if found.evidence is not None and "t_step" in found.estimates:
            # the step time: the evidence with the exact step near t_s
            ev = found.evidence
            extra = {"t_step": found.estimates["t_step"], "log_bayes_factor_at_best": ev.log_bayes_factor}
        elif found.evidence is not None:  # a search that scored its estimate (a glitch's template)
            ev = found.evidence
            extra = {"search": found.to_json(), "log_bayes_factor_at_best": ev.log_bayes_factor}
        else:
            cs = effect_columns(data, effect, C if effect.needs_coefficients else None, cache=False)
            ev = added_evidence(model, cs)
            extra = {"search": found.to_json(), "log_bayes_factor_at_best": ev.log_bayes_factor}
        ev = replace(ev, log_bayes_factor=found.log_bayes_factor)
        extra["_effect"] = effect
        return ev, extra
    if effect.needs_coefficients and np.isnan(C).any():
        raise ConfigError(f"effect {effect.name!r} needs the 24 linear coefficients in the model")
    trial = effect.trial_columns
    # trial columns of witness effects are not kept; drift and step ranked from modulated
    # TDI regressors (exact=False)
    cs = effect_columns(data, effect, C if effect.needs_coefficients else None, exact=trial, cache=not trial)
    ev = added_evidence(model, cs)
    if (
        hasattr(effect, "shifted_members")
        and stats.chi2.sf(max(ev.delta_chi2, 0.0), len(cs)) < data.context.settings.alpha
    ):
        ev, extra = shifted_evidence(model, effect, ev)
    return ev, extra


def replacement_evidence(model: ModelFit, old, new, C) -> tuple[Evidence, dict]:
    """The evidence for putting ``new`` in the place of the model's effect ``old`` (the
    same effect with its shape searched again on these data, :meth:`Effect.reshaped`), and
    what the search found (as :func:`score`).

    Both are scored against the model without ``old``, fitted on the same data: the
    evidence of the change is the difference, ``delta chi^2`` and log Bayes factor of
    ``new`` (marginal over its searched parameters) less those of ``old`` (at its
    parameters), with no parameter added.  ConfigError when ``old`` is not in the model."""
    rest = [e for e in model.effects if e.spec() != old.spec()]
    if len(rest) == len(model.effects):
        raise ConfigError(f"{old.spec()} is not in the model {[e.spec() for e in model.effects]}")
    base = fit_model(model.data, rest, keep_series=False, time_table=False)
    was, _ = score(base, old, C)
    now, extra = score(base, new, C)

    def less(a, b):
        return None if a is None or b is None else a - b

    ev = replace(
        now,
        delta_chi2=now.delta_chi2 - was.delta_chi2,
        log_bayes_factor=now.log_bayes_factor - was.log_bayes_factor,
        n_parameters=0,
        band_delta=less(now.band_delta, was.band_delta),
        segment_delta=less(now.segment_delta, was.segment_delta),
        delta_bic=None,
    )
    return ev, extra


def rescore(model: ModelFit, candidate: dict, C=None) -> Evidence:
    """The evidence of a ranking's entry ``candidate`` on another fit of the model (the same
    effects on other data: the signals' hours gated), at the parameters its search found:
    its effect added, or put in the place of the one it ``replaces``.  ConfigError when it
    cannot be scored there."""
    modules = model.data.context.effect_modules
    effect = make_effects([candidate["spec"]], modules)[0]
    C = model.ttl_coefficients() if C is None else C
    if candidate.get("replaces"):
        old = make_effects([candidate["replaces"]], modules)[0]
        return replacement_evidence(model, old, effect, C)[0]
    return score(model, effect, C)[0]


def shifted_evidence(model: ModelFit, effect, taylor: Evidence) -> tuple[Evidence, dict]:
    """Evidence of a shifted-witness candidate with its offsets searched (the exact model
    of :func:`ttlcore.diagnose.fitting.expand_linearised`) instead of the Taylor columns at
    zero, which lose most of a large offset's delta chi^2 where ``2 pi f delta`` nears one.
    Falls back to the Taylor evidence when no group's offset needs the exact model.

    The extra holds ``offsets`` (``"effect.group"`` -> fitted offset [s]), ``offset_search``
    (the search of the offsets, :meth:`ttlcore.diagnose.search.SearchResult.to_json`: profile
    estimates with their 1-sigma intervals, marginal evidence) and ``_effect``: the effect
    with the offsets of its expanded groups given (``offset.<group>``, 6 significant
    digits), whose ``--effects`` spelling fits the same model."""
    data = model.data
    if data.context.settings.expansion_passes == 0 or len(data.tdi.ttl_names) != 24:
        return taylor, {}
    exact = fit_resolved(data, list(model.effects) + [effect], None, False)
    if all("@" not in n for n in exact.names):
        return taylor, {}
    dchi2, lbf = laplace_evidence(model, exact)
    new = [i for i, n in enumerate(exact.names) if parameter_name(n) not in set(model.parameter_names)]
    names = [exact.names[i] for i in new]
    beta = np.array([total_offset(exact.names[i], exact.theta[i], exact.expansion) for i in new])
    ev = Evidence(
        dchi2,
        lbf,
        len(new),
        tuple(names),
        beta,
        exact.sigma[new],
        (model.chi2_seg_band - exact.chi2_seg_band).sum(axis=0) / data.grid.kappa,
        (model.chi2_seg_band - exact.chi2_seg_band).sum(axis=1) / data.grid.kappa,
    )
    offsets = {n[:-3]: float(b) for n, b in zip(names, beta) if n.endswith(".d1")}
    prefix = effect.name + "."
    expanded = {
        f"offset.{k[len(prefix) :]}": float(f"{v:.6g}")
        for k, v in offsets.items()
        if k.startswith(prefix) and exact.expansion.get(k, 0.0) != 0.0
    }
    extra = {"offsets": offsets, "_effect": effect.with_options(**expanded)}
    if effect.cli_spec() in exact.searches:
        extra["offset_search"] = exact.searches[effect.cli_spec()]
    return ev, extra


def where(data, ev: Evidence, extra: dict) -> dict:
    """Where a candidate acts: delta chi^2 per band and per segment, per group of its
    parameters (link, MOSA, spacecraft), the step time or offsets it was scored at."""
    bd = ev.band_delta
    sd = ev.segment_delta
    if bd is None or sd is None:
        raise ValueError("where(): the evidence has no band and segment deltas")
    tot = max(float(np.sum(np.maximum(bd, 0))), 1e-300)
    bands = [
        {
            "f_lo": float(data.grid.edges[g]),
            "f_hi": float(data.grid.edges[g + 1]),
            "delta_chi2": float(bd[g]),
            "share": float(max(bd[g], 0) / tot),
        }
        for g in range(data.grid.G)
    ]
    strong = [b for b in bands if b["share"] >= 0.1]
    z2 = (ev.beta / np.where(ev.sigma > 0, ev.sigma, np.inf)) ** 2
    groups: dict = {}
    for n, z in zip(ev.names, z2):
        parts = n.split(".")
        groups[parts[1] if len(parts) > 1 else n] = groups.get(parts[1] if len(parts) > 1 else n, 0.0) + float(z)
    links = sorted(groups.items(), key=lambda kv: -kv[1])
    ztot = max(sum(groups.values()), 1e-300)
    out = {
        "bands": bands,
        "main_bands": [[b["f_lo"], b["f_hi"]] for b in strong],
        "segments": [
            {"t_start": float(t), "t_stop": float(t + data.grid.seg_duration), "delta_chi2": float(x)}
            for t, x in zip(data.grid.seg_t0, sd)
        ],
        "links": [{"group": g, "z2": z, "share": z / ztot} for g, z in links[:6]],
    }
    if "t_step" in extra:
        out["t_step"] = extra["t_step"]
    if "offsets" in extra:  # searched offsets [s] of a shifted-witness effect, per group
        out["offsets"] = extra["offsets"]
    return out


def top_parameters(ev: Evidence, n: int = 6) -> list[dict]:
    beta, sig = ev.beta, ev.sigma
    z = np.abs(beta) / np.where(sig > 0, sig, np.inf)
    order = np.argsort(-z)[:n]
    return [{"name": ev.names[i], "value": float(beta[i]), "sigma": float(sig[i]), "z": float(z[i])} for i in order]

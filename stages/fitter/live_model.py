"""The fitter's model in force: its effects, its changes, and what a restarted fitter restores.

The model is a list of effect specs (``ttl diagnose``'s effects, plugins from the stage's
configuration only) that always holds ``linear-ttl``.  It changes from a given segment on, by
a control message (``ttl/<run>/control/fitter/model``, :meth:`LiveModel.parse_control`) or
by the adoption of a live diagnosis' recommendation; the change is then due in the next fit
message (``model_change``) and the new model is diagnosed on its first segment.

A change is checked completely when it is asked for (:meth:`LiveModel.check`: every option,
the size limits, its columns built on the newest telemetry, the size of the fit header it
makes) and queued (:meth:`LiveModel.request`); it takes effect at a segment boundary only,
when the segment it applies from is about to be processed (:meth:`LiveModel.apply`): a
segment is always fitted with one model from its start to its end.

A restarted fitter queues again the changes of its earlier processes (``model`` events,
:meth:`LiveModel.restore`): each takes effect at its own segment while the window is rebuilt
and afterwards, so that a segment is recomputed with the model that was in force for it and the
state is the uninterrupted run's.  The stage records the events; this class only holds the
state.
"""

from __future__ import annotations

import json
from typing import TypedDict

from streamer.bus.codec import MAX_HEADER_BYTES
from ttlcore.conventions import DAY
from ttlcore.effects import effect_input_from_telemetry, make_effects, split_effects
from ttlcore.effects.gate import split_gates
from ttlcore.errors import ConfigError


class PendingChange(TypedDict):
    """A model change asked for and not yet in force (:attr:`LiveModel.pending`)."""

    effects: list[str]  # the validated specs of the new model
    from_index: int  # the segment it applies from
    due: bool  # its ``model_change`` is still to be reported
    report: bool  # reported at all (a window refit of both models); not a transient's expiry
    diagnose: bool  # the new model's first segment is diagnosed
    restored: bool  # queued again after a restart (an earlier process reported it, or not)


#: Most effects a live model may hold (a day of glitches and gates, with room): a control
#: message with more is refused before any effect is built (docs/operations.md, "Model limits")
MAX_EFFECTS = 64
#: Most columns of a live model (the 24 linear ones included; a drift adds 24, a glitch 1)
MAX_COLUMNS = 256
#: Most gates of a live model (a gate adds no column, but a span of the window left out)
MAX_GATES = 32
#: Most of the window the gates of a live model may span together (the union of their spans):
#: a gate over the whole day left the window without data, and every later fit was a copy of
#: the last one published under a new index
MAX_GATED_FRACTION = 0.5
#: Most bytes of the fit header the model's own fields may take (``model``, ``model_change``,
#: ``extra_parameters``, ``model_parts``, the gates of ``adequacy``): the whole header is
#: refused beyond :data:`streamer.bus.codec.MAX_HEADER_BYTES` (10,000 gates made a fit header
#: larger than that: the fit was lost)
MAX_MODEL_HEADER_BYTES = MAX_HEADER_BYTES // 4


def header_bytes(effects: list[str], columns: list[str], gates: int) -> int:
    """An upper estimate of the bytes the model's fields take in a fit header: the specs
    three times (``model``, ``model_change``'s ``before`` and ``after``) and once more as
    ``model_parts``, each column with two full-precision numbers, each gate's span."""
    number = -1.2345678901234567e-100
    fields = {
        "model": effects,
        "model_change": {"before": effects, "after": effects},
        "model_parts": effects,
        "extra_parameters": {c: [number, number] for c in columns},
        "gates": [[number, number]] * gates,
    }
    return len(json.dumps(fields))


class LiveModel:
    """The model in force and its recorded changes.

    Parameters
    ----------
    effects : list of str or str
        The configured model (a list of effect specs, or one comma-separated string).
    effect_modules : sequence of str
        Plugin modules or ``.py`` files defining effects (the stage's configuration).
    window_duration : float
        The fitter's window [s]: the gates of a model span at most
        :data:`MAX_GATED_FRACTION` of it.

    Attributes
    ----------
    effects : list of str
        The validated specs of the model in force.
    initial : list of str
        The configured model (what a restarted fitter replays before the first change).
    pending : list of PendingChange
        The changes asked for and not yet in force, in the order asked.
    change_due : dict or None
        A change not yet reported in a fit message: ``before``, ``after``, ``from_index``.
    diagnose_due : bool
        The first segment of a new model is diagnosed (cleared once it was).
    """

    def __init__(self, effects, effect_modules=(), window_duration: float = DAY):
        self.effect_modules = tuple(effect_modules)
        self.window_duration = float(window_duration)
        self.effects = self.check(effects)
        self.initial = list(self.effects)
        self.pending: list[PendingChange] = []
        self.change_due: dict | None = None
        self.diagnose_due = False

    @property
    def extended(self) -> bool:
        """True when the model holds more than ``linear-ttl``."""
        return self.effects != ["linear-ttl"]

    def check(self, specs, window=None) -> list[str]:
        """Validated effect specs of a model (a list, or one comma-separated string).

        Parameters
        ----------
        specs : list of str or str
            The model asked for.
        window : ttlcore.io.telemetry.Telemetry, optional
            The newest telemetry of the window: the model's columns are built on it too (an
            option that only fails on real data is refused now, not at the next segment).

        Raises
        ------
        ValueError
            Naming what is wrong: an effect or option at fault, or a limit exceeded
            (docs/operations.md, "Control messages and model limits").
        """
        if isinstance(specs, str):  # the command line's form (docs/cli.md, "Effect specs")
            specs = split_effects(specs)
        if not isinstance(specs, (list, tuple)) or not specs or not all(isinstance(s, str) for s in specs):
            raise ValueError(f"effects: expected a list of effect specs, got {specs!r}")
        flat = [e for s in specs for e in split_effects(s)]  # one item may hold several effects
        if len(flat) > MAX_EFFECTS:  # before anything is built: 100,000 effects grew a fitter to 6 GB
            raise ValueError(f"effects: {len(flat)} effects, at most {MAX_EFFECTS} (docs/operations.md, model limits)")
        effects = make_effects(flat, self.effect_modules)
        if "linear-ttl" not in [e.name for e in effects]:
            raise ValueError("effects: the model must include linear-ttl")
        # every option read now, not at the next segment: the effect's columns are built on a
        # stand-in input (``step:t_step=abc`` was accepted, then failed every later segment)
        columns: list[str] = []
        for e in effects:
            try:
                columns += e.column_names()
            except (ValueError, TypeError, KeyError) as exc:  # ConfigError is a ValueError
                raise ValueError(f"effects: {e.spec()}: {exc}") from None
        if len(columns) > MAX_COLUMNS:
            raise ValueError(
                f"effects: {len(columns)} columns, at most {MAX_COLUMNS} (docs/operations.md, model limits)"
            )
        self.check_gates(split_gates(effects)[0])
        out = [e.spec() for e in effects]
        size = header_bytes(out, columns, len(split_gates(effects)[0]))
        if size > MAX_MODEL_HEADER_BYTES:
            raise ValueError(
                f"effects: the model takes about {size} bytes of the fit header, at most {MAX_MODEL_HEADER_BYTES} "
                f"(the header's limit is {MAX_HEADER_BYTES}; docs/operations.md, model limits)"
            )
        if window is not None:
            self.check_columns(effects, window)
        return out

    def check_gates(self, gates) -> None:
        """At most :data:`MAX_GATES` gates, spanning together (their union) at most
        :data:`MAX_GATED_FRACTION` of the window; ValueError otherwise."""
        if len(gates) > MAX_GATES:
            raise ValueError(f"effects: {len(gates)} gates, at most {MAX_GATES} (docs/operations.md, model limits)")
        total, end = 0.0, -float("inf")
        for a, b in sorted(g.span for g in gates):  # the union of the spans
            a = max(a, end)
            if b > a:
                total += b - a
            end = max(end, b)
        limit = MAX_GATED_FRACTION * self.window_duration
        if total > limit:
            raise ValueError(
                f"effects: the gates span {total / 3600:.3g} h in total, at most {limit / 3600:.3g} h "
                f"({MAX_GATED_FRACTION:.0%} of the {self.window_duration / 3600:.3g}-h window: the window "
                "would hold no data to fit; docs/operations.md, model limits)"
            )

    def check_columns(self, effects, window) -> None:
        """Build the columns of ``effects`` on the telemetry ``window`` (the newest segment):
        ValueError naming the effect whose columns cannot be built on it."""
        data = effect_input_from_telemetry(window)
        for e in effects:
            if e.is_linear_ttl or e.active_span() is not None or e.needs_coefficients or e.unresolved():
                # the 24 regressors; a transient's columns vanish outside its span; an effect
                # whose columns need the fitted coefficients or searched parameters is built by
                # the window refit (its search on the window)
                continue
            try:
                e.columns(data)
            except (ValueError, TypeError, KeyError, IndexError, ArithmeticError) as exc:
                raise ValueError(f"effects: {e.spec()}: its columns cannot be built on the window ({exc})") from None

    def request(
        self, new: list[str], start: int, *, diagnose: bool = True, due: bool = True, report: bool = True
    ) -> bool:
        """Queue the model ``new`` (validated) from segment ``start`` on (:meth:`apply` puts
        it in force); False when it is the model already in force or queued for ``start``
        (nothing to record).  ``report`` False: the change is never reported by a window refit
        (transients that left the window: both models are the same on it)."""
        after = self.pending[-1]["effects"] if self.pending else self.effects
        if list(new) == list(after):
            return False
        self.pending.append(
            {
                "effects": list(new),
                "from_index": int(start),
                "due": due and report,
                "report": report,
                "diagnose": diagnose,
                "restored": False,
            }
        )
        return True

    @property
    def planned(self) -> list[str]:
        """The model of the next segment (the last change queued, else the model in force)."""
        return list(self.pending[-1]["effects"]) if self.pending else list(self.effects)

    def apply(self, index: int, recomputed: bool = False) -> list[PendingChange]:
        """Segment ``index`` is about to be processed: the changes queued for it (from
        ``index`` or earlier) take effect, in the order they were asked for; their change is
        due in the next fit message (one ``model_change``, from the model before the first
        to the model after the last) and the new model is diagnosed on its first segment.
        A restored change an earlier process reported is due again when its segment is
        ``recomputed`` whole (published again: the board did not know it was out, or
        recorded again): the fit then is the earlier one, its window refit and
        ``model_change`` included (the chaos test, seed 825968289: a restarted fitter
        published fit 140 again, the first of a restored change, without its window refit).
        Returns the changes applied."""
        applied = [c for c in self.pending if c["from_index"] <= index]
        if not applied:
            return []
        self.pending = [c for c in self.pending if c["from_index"] > index]
        before = self.change_due["before"] if self.change_due else list(self.effects)
        for c in applied:
            self.effects = list(c["effects"])
            self.diagnose_due = self.diagnose_due or c["diagnose"]
        reported = any(c["report"] and (c["due"] or (recomputed and c["restored"])) for c in applied)
        if (reported or self.change_due is not None) and self.effects != before:
            self.change_due = {"before": before, "after": list(self.effects), "from_index": index}
        else:  # back to the model last reported, or changes an earlier process reported
            self.change_due = None
        return applied

    def change(self, new: list[str], start: int, *, diagnose: bool = True) -> None:
        """The model ``new`` (validated) in force from segment ``start`` on at once
        (:meth:`request` then :meth:`apply`)."""
        self.request(new, start, diagnose=diagnose)
        self.apply(start)

    def only_transients_added(self, new: list[str]) -> bool:
        """Whether the model ``new`` differs from the one in force by transients alone (gates,
        glitches: effects with an :meth:`~ttlcore.effects.base.Effect.active_span`)."""
        return self.transients_added_until(new) is not None

    def transients_added_until(self, new: list[str]) -> float | None:
        """The end [s] of the latest span among the transients the model ``new`` adds, when
        it differs from the one in force by transients alone (else None)."""
        new = [e.spec() for e in make_effects(list(new), self.effect_modules)]  # as the model prints them
        added = [e for e in new if e not in self.effects]
        removed = [e for e in self.effects if e not in new]
        spans = [e.active_span() for e in make_effects([*added, *removed], self.effect_modules)]
        ends = [span[1] for span in spans if span is not None]
        if not added or len(ends) < len(spans):
            return None
        return max(ends[: len(added)])

    def expired(self, t_start: float) -> list[str]:
        """The transients of the model (effects with an
        :meth:`~ttlcore.effects.base.Effect.active_span`: glitches, gates) whose span ends
        before ``t_start`` [s], the start of the window: nothing in the window informs them
        any more, and they leave the model (the recordings keep them for offline refits)."""
        out = []
        for spec, effect in zip(self.effects, make_effects(self.effects, self.effect_modules), strict=True):
            span = effect.active_span()
            if span is not None and span[1] < t_start:
                out.append(spec)
        return out

    def settled(self, t_start: float) -> dict[str, str]:
        """The model's effects that equal a simpler one on a window from ``t_start`` [s] on
        (:meth:`~ttlcore.effects.base.Effect.settled`: a coupling switched on before the
        window is the plain coupling there), as ``{spec: simpler spec}``."""
        out = {}
        for spec, effect in zip(self.effects, make_effects(self.effects, self.effect_modules), strict=True):
            simpler = effect.settled(t_start)
            if simpler is not None:
                out[spec] = simpler.spec()
        return out

    def parse_control(self, payload: bytes, window=None) -> list[str]:
        """The model a control message ``{"effects": [...]}`` asks for, validated (its
        columns built on ``window``, the newest telemetry, when given); ValueError saying
        what is wrong with the message otherwise."""
        try:
            msg = json.loads(payload)
        except ValueError as exc:
            raise ValueError(f"not JSON: {exc}") from None
        if not isinstance(msg, dict) or "effects" not in msg:
            raise ValueError('expected {"effects": [...]}')
        if set(msg) - {"effects"}:
            raise ValueError(
                f"unknown field(s) {sorted(set(msg) - {'effects'})}; plugin modules come from the "
                "stage's configuration only"
            )
        try:
            return self.check(msg["effects"], window=window)
        except ConfigError as exc:
            raise ValueError(str(exc)) from None

    def restore(self, models: list[dict], fits: set[int]) -> tuple[int, bool] | None:
        """Queue again the model changes of earlier processes (their ``model`` events, oldest
        first), given the segments they recorded a fit of: each takes effect at its own
        segment (:meth:`apply`), while the window is rebuilt and after, so that every segment
        is fitted with the model that was in force for it.  A change's ``model_change`` is
        still due when no fit was recorded from the segment it applies from on.  An event that
        cannot be read is skipped (the segments from it on keep the model before).

        Returns
        -------
        (int, bool) or None
            The segment the last change applies from and whether its change is due; None
            when no model was recorded (the configured model stays).

        Raises
        ------
        KeyError, TypeError, ValueError, ConfigError
            The last event cannot be restored (nothing is changed).
        """
        if not models:
            return None
        d = models[-1].get("details") or {}
        last = self.check(d["effects"])
        start = int(d["from_index"])
        queued: list[PendingChange] = []
        for e in models:
            try:
                d_e = e.get("details") or {}
                i = int(d_e["from_index"])
                effects = self.check(d_e["effects"])
            except (KeyError, TypeError, ValueError, ConfigError):
                continue  # a change that cannot be restored: the segments from it keep the model before
            # as the earlier process made it: reported (a transient's expiry is not) and
            # diagnosed on its first segment, or not
            report = bool(d_e.get("report", True))
            due_e = report and not any(j >= i for j in fits)
            queued.append(
                {
                    "effects": effects,
                    "from_index": i,
                    "due": due_e,
                    "report": report,
                    "diagnose": bool(d_e.get("diagnose", True)),
                    "restored": True,
                }
            )
        # by the segment each applies from; in the order asked among those of one segment
        self.pending = sorted(queued, key=lambda c: c["from_index"])
        due = self.pending[-1]["report"] and not any(i >= start for i in fits) if self.pending else False
        if not self.pending or self.pending[-1]["effects"] != last:
            raise ValueError(f"the last recorded change {last} cannot be queued again")
        return start, due

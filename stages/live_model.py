"""The fitter's model in force: its effects, its changes, and what a restarted fitter restores.

The model is a list of effect specs (``ttl diagnose``'s effects, plugins from the stage's
configuration only) that always holds ``linear-ttl``.  It changes from a given segment on, by
a control message (``ttl/<run>/control/fitter/model``, :meth:`LiveModel.parse_control`) or
by the adoption of a live diagnosis' recommendation; the change is then due in the next fit
message (``model_change``) and the new model is diagnosed on its first segment.

A restarted fitter takes the model in force from the ``model`` events of its earlier
processes' recordings (:meth:`LiveModel.restore`) and, while it rebuilds its window, the model
of each segment it pushes again (:meth:`LiveModel.replay`): its state is then the
uninterrupted run's.  The stage records the events; this class only holds the state.
"""

from __future__ import annotations

import json

from ttlcore.effects import make_effects, split_effects
from ttlcore.errors import ConfigError

#: Most effects a live model may hold (a day of glitches and gates, with room): a control
#: message with more is refused before any effect is built (docs/operations.md, "Model limits")
MAX_EFFECTS = 64
#: Most columns of a live model (the 24 linear ones included; a drift adds 24, a glitch 1)
MAX_COLUMNS = 256


class LiveModel:
    """The model in force and its recorded changes.

    Parameters
    ----------
    effects : list of str or str
        The configured model (a list of effect specs, or one comma-separated string).
    effect_modules : sequence of str
        Plugin modules or ``.py`` files defining effects (the stage's configuration).

    Attributes
    ----------
    effects : list of str
        The validated specs of the model in force.
    initial : list of str
        The configured model (what a restarted fitter replays before the first change).
    history : list of (int, list of str)
        The recorded changes of earlier processes: (segment it applies from, effects).
    change_due : dict or None
        A change not yet reported in a fit message: ``before``, ``after``, ``from_index``.
    diagnose_due : bool
        The first segment of a new model is diagnosed (cleared once it was).
    """

    def __init__(self, effects, effect_modules=()):
        self.effect_modules = tuple(effect_modules)
        self.effects = self.check(effects)
        self.initial = list(self.effects)
        self.history: list[tuple[int, list[str]]] = []
        self.change_due: dict | None = None
        self.diagnose_due = False

    @property
    def extended(self) -> bool:
        """True when the model holds more than ``linear-ttl``."""
        return self.effects != ["linear-ttl"]

    def check(self, specs) -> list[str]:
        """Validated effect specs of a model (a list, or one comma-separated string)."""
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
        n_columns = 0
        for e in effects:
            try:
                n_columns += len(e.column_names())
            except (ValueError, TypeError, KeyError) as exc:  # ConfigError is a ValueError
                raise ValueError(f"effects: {e.spec()}: {exc}") from None
        if n_columns > MAX_COLUMNS:
            raise ValueError(f"effects: {n_columns} columns, at most {MAX_COLUMNS} (docs/operations.md, model limits)")
        return [e.spec() for e in effects]

    def change(self, new: list[str], start: int, *, diagnose: bool = True) -> None:
        """The model ``new`` (validated) from segment ``start`` on: its change is due, its
        first segment diagnosed (unless ``diagnose`` is False: a transient that left the
        window takes nothing new to diagnose)."""
        self.change_due = {"before": list(self.effects), "after": new, "from_index": start}
        self.diagnose_due = self.diagnose_due or diagnose
        self.effects = new

    def only_transients_added(self, new: list[str]) -> bool:
        """Whether the model ``new`` differs from the one in force by transients alone (gates,
        glitches: effects with an :meth:`~ttlcore.effects.base.Effect.active_span`)."""
        new = [e.spec() for e in make_effects(list(new), self.effect_modules)]  # as the model prints them
        added = [e for e in new if e not in self.effects]
        removed = [e for e in self.effects if e not in new]
        effects = make_effects([*added, *removed], self.effect_modules)
        return bool(added) and all(e.active_span() is not None for e in effects)

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

    def parse_control(self, payload: bytes) -> list[str]:
        """The model a control message ``{"effects": [...]}`` asks for, validated; ValueError
        saying what is wrong with the message otherwise."""
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
            return self.check(msg["effects"])
        except ConfigError as exc:
            raise ValueError(str(exc)) from None

    def restore(self, models: list[dict], fits: set[int]) -> tuple[int, bool] | None:
        """Take the model in force from the ``model`` events of earlier processes (oldest
        first), given the segments they recorded a fit of.

        The last event's model is in force; its change is still due when no fit was recorded
        from the segment it applies from on.  Every event that can be read goes into
        :attr:`history` (one that cannot: the segments before it keep the model before).

        Returns
        -------
        (int, bool) or None
            The segment the model applies from and whether its change is due; None when no
            model was recorded (the configured model stays).

        Raises
        ------
        KeyError, TypeError, ValueError, ConfigError
            The last event cannot be restored (nothing is changed).
        """
        if not models:
            return None
        d = models[-1].get("details") or {}
        effects, before = self.check(d["effects"]), list(d["before"])
        start = int(d["from_index"])
        self.effects = effects
        for e in models:
            try:
                d_e = e.get("details") or {}
                self.history.append((int(d_e["from_index"]), self.check(d_e["effects"])))
            except (KeyError, TypeError, ValueError, ConfigError):
                continue  # a change that cannot be restored: the segments before it use the model before
        due = not any(i >= start for i in fits)
        if due:
            self.change_due = {"before": before, "after": effects, "from_index": start}
            self.diagnose_due = True
        return start, due

    def replay(self, index: int) -> None:
        """While a restarted fitter catches up: the model in force at segment ``index`` (the
        configured one, then each recorded change from its segment on), so that the rolling
        fit is rebuilt where the uninterrupted run rebuilt it."""
        effects = self.initial
        for start, changed in sorted(self.history, key=lambda c: c[0]):
            if start <= index:
                effects = changed
        self.effects = list(effects)

"""The model timeline's bookkeeping, shared by ``ttl inspect`` and the monitor; bus-free.

``ttl inspect`` builds the fitter's model timeline from the recordings
(:mod:`streamer.tools.inspect_timeline`, printed by :func:`streamer.tools.inspect_text.timeline_text`); the
monitor builds the same one from the fit messages as they come and draws it in Rerun
(:mod:`stages.monitor.timeline`).  What both need is here:

* :func:`model_delta`: what a change of model added and removed, and whether it starts a new
  *model epoch* of the trends (its couplings differ: :func:`ttlcore.diagnose.trends.model_key`);
* :func:`change_text`: the line that says so, who changed it and why (the same words in
  ``ttl inspect`` and in the monitor's model log);
* :func:`excluded_kind` and :class:`SpanMerger`: the FFT segments the rolling fit left out
  (a gap, a gate of the model, an outlier) and the gaps, merged into spans of consecutive
  segments of one cause.
"""

from __future__ import annotations

from ttlcore.diagnose.trends import model_key

#: What ``by`` of a model change says, for people.
BY_WINDOW = " (it left the one-day window)"


def model_delta(before, after) -> tuple[list[str], list[str], bool]:
    """``(added, removed, new_epoch)`` from the model ``before`` (None: the first one) to
    ``after`` (lists of effect specs): the specs added and removed, in their models' order,
    and whether the couplings changed (a new series of the monitor's trends; a change of the
    transients ``glitch`` and ``gate`` alone is none)."""
    if before is None:
        return [], [], False
    before, after = [str(e) for e in before], [str(e) for e in after]
    added = [e for e in after if e not in before]
    removed = [e for e in before if e not in after]
    old, new = model_key(before), model_key(after)
    return added, removed, bool(old is not None and new is not None and old[0] != new[0])


def change_text(
    added, removed, by: str, *, diagnosis_index=None, reason: str | None = None, new_epoch: bool = False
) -> str:
    """What a model change did, by whom and why: ``+ drift by adopt auto after the diagnosis
    of segment 23: <reason>  [new model epoch]``."""
    what = [f"+ {e}" for e in added] + [f"- {e}" for e in removed]
    why = f" after the diagnosis of segment {diagnosis_index}" if diagnosis_index is not None else ""
    why += BY_WINDOW if by == "window" else ""
    return (
        f"{'; '.join(what) or 'the same effects'} by {by}{why}"
        + (f": {reason}" if reason else "")
        + ("  [new model epoch]" if new_epoch else "")
    )


def excluded_kind(details: dict) -> str:
    """The cause of an FFT segment the rolling fit left out (a fit message's meta
    ``excluded``, the details of its recorded warning or event): ``gap`` (less than half
    valid samples), ``gated`` (over a gate of the model) or ``outlier``."""
    if details.get("gap"):
        return "gap"
    return "gated" if "gate" in details else "outlier"


class SpanMerger:
    """Items (an FFT segment left out, a segment with no data) merged into spans of one cause:
    an item extends the latest span when it has the same ``kind`` (and ``gate``) and starts
    within it or at most ``tolerance`` [s] after its end (an item of the next fit that is
    apart in mission time - one that came late - starts a span of its own).

    Each span: ``kind``, ``from_index``, ``to_index``, ``t_start``, ``t_stop`` [s], ``count``;
    ``gate`` for ``gated``; ``z_max`` (the largest excess in sigma) for ``outlier``.

    Parameters
    ----------
    keep : int or None
        The spans kept (the latest); None: all.
    tolerance : float
        How far [s] an item may start after the latest span's end and still extend it.
    """

    def __init__(self, keep: int | None = None, tolerance: float = 1e-3):
        self.keep = keep
        self.tolerance = float(tolerance)
        self.spans: list[dict] = []

    def add(self, kind: str, index: int, t_start: float, t_stop: float, *, gate=None, z=None) -> tuple[dict, bool]:
        """Add one item; returns its span and whether the span is new."""
        last = self.spans[-1] if self.spans else None
        gate = gate if kind == "gated" else None
        follows = last is not None and last["t_start"] - self.tolerance <= t_start <= last["t_stop"] + self.tolerance
        new = not (last is not None and last["kind"] == kind and last.get("gate") == gate and follows)
        if last is None or new:
            span: dict = {"kind": kind, "from_index": index, "to_index": index, "t_start": t_start, "t_stop": t_stop}
            span["count"] = 1
            if kind == "gated":
                span["gate"] = gate
            self.spans.append(span)
            if self.keep is not None and len(self.spans) > self.keep:
                del self.spans[0]
        else:
            span = last
            span["to_index"] = max(span["to_index"], index)
            span["t_stop"] = max(span["t_stop"], t_stop)
            span["count"] += 1
        if kind == "outlier" and isinstance(z, (int, float)):
            span["z_max"] = max(span.get("z_max", z), z)
        return span, new

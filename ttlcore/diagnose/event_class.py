"""The class of one event of the time-frequency map, and its evidence (docs/diagnostics.md,
"Signals, glitches, gaps and changing noise").

:func:`classify` reads an :class:`~ttlcore.diagnose.transients.Event` -- T's share of its
whitened excess against what a link or test-mass signal would put there, its coherence with
the witnesses, its duration, band and track -- and names it: ``gap``, ``missing-coupling``,
``noise-change``, ``gravitational-wave``, ``glitch`` or ``unclassified`` (an event that
lasts to the data's end becomes an ``onset`` afterwards, :mod:`ttlcore.diagnose.onsets`).
:func:`event_json` is its entry in a report.  The class of the excess as a whole is
:func:`ttlcore.diagnose.excess.excess_classification`'s.
"""

from __future__ import annotations

from .transients import BROADBAND_FRACTION, NOISE_CHANGE_HOURS, Event

__all__ = ["classify", "event_json"]


def classify(event: Event) -> tuple[str, list[str]]:
    """The class of an event and the evidence for it (module docstring)."""
    ev = []
    hours = event.duration / 3600.0
    ev.append(
        f"{hours:.2f} h long ({_clock(event.t_start)}-{_clock(event.t_stop)}), "
        f"{_f(event.f_lo)}-{_f(event.f_hi)}, carried by {', '.join(event.channels) or 'no single channel'}"
    )
    thr = event.t_share_threshold
    ev.append(
        f"T carries {100 * event.t_share:.1f} % of its whitened excess "
        f"({'instrumental' if event.t_share >= thr else 'T consistent with a null stream'}: threshold "
        f"{100 * thr:.2g} %"
        + (
            ""
            if event.t_share_expected is None
            else f", a third of the {100 * event.t_share_expected:.2g} % a single link or test mass would give"
        )
        + ")"
    )
    coh = event.coherence or {}
    if coh:
        ev.append(
            f"witnesses (24 TTL regressors) explain {100 * coh['explained_fraction']:.0f} % of the excess "
            f"(delta chi2 {coh['delta_chi2']:.0f} for {coh['expected']:.0f} expected on noise)"
        )
    ev.append(
        f"track: {event.track_kind}" + (f", {_f(event.track[0][2])} -> {_f(event.track[-1][2])}" if event.track else "")
    )
    nb = len(event.band_excess)
    broad = len(event.significant_bands) >= BROADBAND_FRACTION * nb
    if event.gap is not None:
        ev.insert(0, f"overlaps missing data {_clock(event.gap[0])}-{_clock(event.gap[1])}")
        return "gap", ev
    if coh.get("coherent"):
        return "missing-coupling", ev
    if hours >= NOISE_CHANGE_HOURS and broad:
        ev.append(f"broadband: excess significant in {len(event.significant_bands)} of {nb} bands")
        return "noise-change", ev
    ae = any(c in event.channels for c in ("A", "E"))
    if ae and event.t_share < thr and event.track_kind != "falling":
        return "gravitational-wave", ev
    if event.t_share >= thr and hours < NOISE_CHANGE_HOURS:
        return "glitch", ev
    return "unclassified", ev


def _clock(t: float) -> str:
    return f"{t / 3600:.2f} h"


def _f(f: float) -> str:
    return f"{1e3 * f:.3g} mHz" if f < 0.1 else f"{f:.3g} Hz"


def event_json(e: Event, cls: str, evidence: list) -> dict:
    return {
        "class": cls,
        "evidence": evidence,
        "t_start": e.t_start,
        "t_stop": e.t_stop,
        "t_peak": e.t_peak,
        "duration": e.duration,
        "channels": list(e.channels),
        "channel_p": e.channel_p,
        "f_lo": e.f_lo,
        "f_hi": e.f_hi,
        "track": [list(x) for x in e.track],
        "track_kind": e.track_kind,
        "t_share": e.t_share,
        "t_share_expected": e.t_share_expected,
        "t_share_threshold": e.t_share_threshold,
        "excess": e.excess,
        "snr": e.snr,
        "coherence": e.coherence,
        "gap": list(e.gap) if e.gap else None,
    }

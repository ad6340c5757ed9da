"""The meta of the telemetry and TDI segment messages as a value: :class:`SegmentMeta`.

The replayer writes it on ``ttl/<run>/telemetry/<i>`` (``source``, ``truth``, ``file``,
``dws_asd``, ``segments_total``, ``segment_duration``, ``gaps``); the tdi_builder passes it on
to ``ttl/<run>/tdi/<i>`` and adds ``names`` (of the regressors), ``ltt_mean`` and
``continuous``; the recorder adds ``recorded`` to a copy that leaves arrays out.  Its readers
(the fitter, the monitor, ``ttl refit``/``reprocess``, :mod:`streamer.bus.messages`) call
:meth:`SegmentMeta.from_header` (or :func:`segment_meta` of a header) and read attributes; :func:`segments_total_of` reads the one
field every message's meta may carry.

These messages carry no schema version (their wire is unchanged): the keys read here are
typed and checked (a value of the wrong type is a :class:`~streamer.bus.message_schema.MessageError`
naming the message and the field), other keys are not read.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ttlcore.conventions import LINKS

from .message_schema import MessageError, check, is_number

__all__ = ["MessageError", "SegmentMeta", "segment_meta", "segments_total_of"]

#: The keys of :class:`SegmentMeta` and their kinds (``ltt_mean`` and ``truth`` are checked apart).
_FIELDS = {
    "segments_total": "int",
    "segment_duration": "number",
    "source": "str",
    "file": "int",
    "dws_asd": "number",
    "names": "strs",
    "gaps": "list",
    "continuous": "bool",
}


@dataclass(frozen=True)
class SegmentMeta:
    """The meta of a telemetry or TDI segment (see the module's docstring); None where absent.

    Attributes
    ----------
    segments_total : int or None
        The run's segments.
    segment_duration : float or None
        The segments' duration [s].
    source : str or None
        Where the data come from (``simulation``, a file, ``recording``...).
    file : int or None
        Which of the run's telemetry files the segment was read from (its index among the
        files given to the replayer, in order; None for a simulation).
    truth : str or dict or None
        The truth: a file's path, or the simulation's coefficient model.
    dws_asd : float or None
        The DWS readout-noise level the replayer passes down [rad/sqrt(Hz)].
    names : tuple of str or None
        The regressors' coefficients (TDI).
    ltt_mean : tuple of float or None
        Mean light travel times [s] of the six links (TDI; given by link or as a list).
    gaps : tuple or None
        The gaps of the segment.
    continuous : bool or None
        Whether the TDI stream is continuous with the previous segment.
    """

    segments_total: int | None = None
    segment_duration: float | None = None
    source: str | None = None
    file: int | None = None
    truth: str | Mapping[str, Any] | None = None
    dws_asd: float | None = None
    names: tuple[str, ...] | None = None
    ltt_mean: tuple[float | None, ...] | None = None
    gaps: tuple | None = None
    continuous: bool | None = None

    @classmethod
    def from_header(cls, meta, message: str = "segment") -> SegmentMeta:
        """The value of a segment's ``meta`` (``message`` names it in errors)."""
        check(message, "meta", "dict", meta)
        values: dict[str, Any] = {}
        for name, kind in _FIELDS.items():
            v = meta.get(name)
            if v is not None:
                check(message, name, kind, v)
                values[name] = tuple(v) if kind in ("strs", "list") else v
        truth = meta.get("truth")
        if truth is not None and not isinstance(truth, (str, Mapping)):
            raise MessageError(message, "truth", f"expected a path or a coefficient model, got {type(truth).__name__}")
        ltt = meta.get("ltt_mean")
        if isinstance(ltt, Mapping):
            ltt = [ltt.get(link) for link in LINKS]
        if ltt is not None:
            check(message, "ltt_mean", "numbers", ltt)
            ltt = tuple(ltt)
        return cls(truth=truth, ltt_mean=ltt, **values)


def segments_total_of(meta) -> int | None:
    """The ``segments_total`` of any message's meta: a positive int, else None (not checked
    further: the plan and the validator bound it)."""
    total = meta.get("segments_total") if isinstance(meta, Mapping) else None
    return total if is_number(total) and isinstance(total, int) and total > 0 else None


def segment_meta(header) -> SegmentMeta:
    """The :class:`SegmentMeta` of a segment message's ``header`` (errors name its topic and index)."""
    topic = getattr(header, "topic", None) or "segment"
    return SegmentMeta.from_header(header.meta, f"{topic} {getattr(header, 'index', '?')}")

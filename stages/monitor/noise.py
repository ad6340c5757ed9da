"""The monitor's noise view: the ASDs of X2 of each segment (:mod:`stages.monitor.monitor`).

Per segment, from its TDI and residual messages: the data, the residual, the fitted TTL and
each other effect of the model, and the expected noise and the LISA requirement for the
segment's mean arms (once per segment, from whichever of the two comes first); the numbers
come from :mod:`ttlcore.estimate.monitoring`, the drawing from :mod:`stages.monitor.views`.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from streamer.bus.segment_record import segment_meta
from ttlcore.conventions import ARM_LENGTH, C
from ttlcore.estimate.monitoring import MIN_SAMPLES, band_ratio, channel_asd, reference_curves
from ttlcore.estimate.spectra import longest_run

from . import views


def trim(d: dict, keep: int = 8) -> None:
    """Keep the ``keep`` highest keys of ``d`` (memory flat in a long run)."""
    while len(d) > keep:
        del d[min(d)]


class NoiseCurves:
    """The curves of the noise view, drawn into the recording ``rec`` at its current time.

    Parameters
    ----------
    band : (float, float)
        The frequency band drawn and over which residual / expected is taken [Hz].
    per_decade : int
        Log-averaged ASD points per decade.
    """

    def __init__(self, band, per_decade: int = 20):
        self.band = tuple(band)
        self.per_decade = int(per_decade)
        self._ltt: dict[int, np.ndarray] = {}  # mean light travel times [s] of recent segments
        self._ref: dict[int, dict] = {}  # reference curves of recent segments

    def telemetry(self, index: int, ltt: np.ndarray) -> None:
        """A telemetry segment's light travel times (6, n) [s]: their means, kept for its curves."""
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all NaN (a gap): "Mean of empty slice"
            mean = np.nanmean(ltt, axis=1)
        if np.all(np.isfinite(mean)):
            self._ltt[index] = mean
            trim(self._ltt)

    def ltt_of(self, header) -> np.ndarray:
        """Mean light travel times [s] of a segment: its meta ``ltt_mean``, else its telemetry's,
        else the latest segment's, else the nominal arms."""
        v = segment_meta(header).ltt_mean
        try:
            arr = np.asarray(v, dtype=float)
            if arr.shape == (6,) and np.all(np.isfinite(arr)):
                return arr
        except (TypeError, ValueError):
            pass
        if header.index in self._ltt:
            return self._ltt[header.index]
        if self._ltt:
            return self._ltt[max(self._ltt)]
        return np.full(6, ARM_LENGTH / C)

    def references(self, rec, header, f_welch) -> dict:
        """The expected noise and the requirement of a segment (drawn the first time)."""
        ref = self._ref.get(header.index)
        if ref is None:
            ref = reference_curves(f_welch, self.ltt_of(header), self.per_decade)
            self._ref[header.index] = ref
            trim(self._ref)
            for name, (f, asd) in ref.items():
                views.noise_curve(rec, name, f, asd, self.band)
        return ref

    def tdi(self, rec, header, data) -> None:
        """The data's ASD of a TDI segment (``data`` (3, n)) and its reference curves."""
        f, asd, f_welch = channel_asd(data[0], header.fs, self.per_decade)
        views.noise_curve(rec, "data", f, asd, self.band)
        self.references(rec, header, f_welch)

    def residual(self, rec, header, arrays, effects: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray, float]:
        """The residual's, the fitted TTL's and the other effects' ASDs of a residual message
        (``effects``: its meta's, :attr:`streamer.bus.residual_record.ResidualMessage.effects`);
        returns the residual's ``(f, asd)`` and its in-band median ratio to the expected noise."""
        f, asd, f_welch = channel_asd(arrays["residual"][0], header.fs, self.per_decade)
        views.noise_curve(rec, "residual", f, asd, self.band)
        model = arrays["ttl_model"][0]
        model = model[longest_run(np.isfinite(model))]
        if model.size >= MIN_SAMPLES and np.any(model != 0):
            fm, am, _ = channel_asd(model, header.fs, self.per_decade)
            views.noise_curve(rec, "ttl_model", fm, am, self.band)
        self.effect_curves(rec, header, arrays, effects)
        f_ref, expected = self.references(rec, header, f_welch)["expected"]
        return f, asd, band_ratio(f, asd, f_ref, expected, self.band)

    def effect_curves(self, rec, header, arrays, specs: Sequence[str]) -> None:
        """The X2 ASD of each effect of the model beyond the linear TTL that the subtractor
        took away (array ``effect_model`` (k, 3, n), the residual's meta ``effects``
        ``specs``), labelled with the effect's name; at most :data:`views.EFFECT_COLORS` of them."""
        parts = arrays.get("effect_model")
        if parts is None or parts.ndim != 3 or parts.shape[0] != len(specs):
            return
        for k, spec in enumerate(specs[: len(views.EFFECT_COLORS)]):
            x = parts[k, 0]
            x = x[longest_run(np.isfinite(x))]
            if x.size >= MIN_SAMPLES and np.any(x != 0):
                f, asd, _ = channel_asd(x, header.fs, self.per_decade)
                views.noise_curve(
                    rec,
                    f"effect/{k}",
                    f,
                    asd,
                    self.band,
                    color=views.EFFECT_COLORS[k],
                    label=str(spec).split(",")[0],
                )

"""The monitor's output ``ttl/<run>/monitor/<i>``: the trend state and the alerts raised since.

Arrays ``drift_rate`` (24,) [mm/rad/day] and ``drift_significance`` (24,) of the latest trend
evaluation (:class:`ttlcore.diagnose.trends.TrendMonitor`; 0 where not yet defined, see meta
``drift_windows``), and the meta of :func:`status_meta`; the recording's ``monitor/summary``
holds both.
"""

from __future__ import annotations

import numpy as np

from streamer.bus.monitor_record import MonitorMessage
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.trends import Alert, TrendMonitor

#: Units of the monitor message's arrays.
UNITS = {"drift_rate": "mm/rad/day", "drift_significance": ""}


def drift_arrays(trends: TrendMonitor) -> dict[str, np.ndarray]:
    """``drift_rate`` and ``drift_significance`` of the latest trend evaluation (zeros before
    the first, 0 where not defined)."""
    est = trends.estimates
    p = len(COEFFICIENT_NAMES)
    return {
        "drift_rate": np.nan_to_num(est.rate) if est is not None else np.zeros(p),
        "drift_significance": np.nan_to_num(est.significance) if est is not None else np.zeros(p),
    }


def status_meta(
    trends: TrendMonitor,
    alerts: list[Alert],
    ratio: tuple | None,
    last_fit: dict | None,
    segments_total: int | None,
    message: str = "monitor message",
) -> MonitorMessage:
    """The meta of a monitor message (:class:`streamer.bus.monitor_record.MonitorMessage`):
    ``alerts`` (raised since the previous message), ``drifting``, ``drift_windows``,
    ``model_epoch`` (the model epoch the trends are in:
    :class:`ttlcore.diagnose.trends.ModelEpoch`, None before the first fit),
    ``residual_over_expected`` (the latest in-band median ASD ratio ``ratio`` = (segment,
    ratio)), ``fit`` (the latest fit: index, chi2_dof, window), ``segments_total``."""
    est = trends.estimates
    return MonitorMessage.build(
        message,
        names=list(COEFFICIENT_NAMES),
        alerts=[a.to_json() for a in alerts],
        drifting=sorted(trends.drifting),
        drift_windows=est.windows if est else 0,
        model_epoch=trends.epoch.to_json() if trends.epoch else None,
        residual_over_expected={"index": ratio[0], "ratio": ratio[1]} if ratio else None,
        fit=last_fit,
        segments_total=segments_total,
    )

"""Unit tests of :mod:`stages.monitor.status`: the monitor's ``monitor/<i>`` message from its
trends (a real :class:`ttlcore.diagnose.trends.TrendMonitor`; no bus in it)."""

import numpy as np
import pytest

from stages.monitor.status import UNITS, drift_arrays, status_meta
from streamer.bus.monitor_record import MonitorMessage
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.trends import TrendMonitor

P = len(COEFFICIENT_NAMES)
HOUR = 3600.0


def test_before_the_first_fit():
    trends = TrendMonitor()
    arrays = drift_arrays(trends)
    assert set(arrays) == set(UNITS)
    np.testing.assert_array_equal(arrays["drift_rate"], np.zeros(P))
    meta = status_meta(trends, [], None, None, 72, message="monitor 0")
    header = meta.to_header()
    assert header["alerts"] == [] and header["drifting"] == [] and header["drift_windows"] == 0
    assert header["model_epoch"] is None and header["residual_over_expected"] is None
    assert header["segments_total"] == 72 and header["names"] == list(COEFFICIENT_NAMES)
    assert MonitorMessage.from_header(header, "monitor 0") == meta


def test_a_drifting_coefficient_is_reported():
    trends = TrendMonitor()
    rng = np.random.default_rng(3)
    sigma = np.full(P, 1e-6)  # m/rad
    alerts = []
    for i in range(60):  # hourly fits of one-day windows; coefficient 0 drifts by 0.2 mm/rad/day
        t_stop = (i + 24) * HOUR
        c = 1e-3 + sigma * rng.standard_normal(P)
        c[0] += 0.2e-3 * t_stop / 86400.0
        alerts += trends.add(i, t_stop - 24 * HOUR, t_stop, c, sigma, model=["linear-ttl"])
    meta = status_meta(trends, alerts, (59, 1.05), {"index": 59, "chi2_dof": 1.0}, None)
    arrays = drift_arrays(trends)
    assert COEFFICIENT_NAMES[0] in meta.drifting
    assert any(a["kind"] == "drift" and a["coefficient"] == COEFFICIENT_NAMES[0] for a in meta.alerts)
    assert arrays["drift_rate"][0] == pytest.approx(0.2, rel=0.1)  # mm/rad/day
    assert arrays["drift_significance"][0] > 5 and np.isfinite(arrays["drift_significance"]).all()
    assert meta.drift_windows > 0 and meta.model_epoch["number"] == 0
    assert meta.residual_over_expected == {"index": 59, "ratio": 1.05}
    assert MonitorMessage.from_header(meta.to_header(), "monitor 59") == meta

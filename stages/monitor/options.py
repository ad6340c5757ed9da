"""The monitor's options: :class:`MonitorOptions`, and its command line (``python -m
stages.monitor``, ``ttl stage monitor``).

The command line sets the stage options of the same names (``StageConfig.options``, the
``[stages.monitor]`` table of a run's configuration), which :class:`stages.monitor.monitor.Monitor`
parses once into a :class:`MonitorOptions`.
"""

from __future__ import annotations

from dataclasses import dataclass

from streamer.runtime.stage_options import StageOptions, band_hz, option, positive_float, positive_int
from streamer.tools.viewer import check_live
from ttlcore.diagnose.trends import TrendSettings
from ttlcore.estimate.fit import DEFAULT_BAND

__all__ = ["MonitorOptions", "add_options", "options"]


def _live(value) -> str:
    check_live(value)
    return str(value)


def _trends(value) -> TrendSettings:
    return value if isinstance(value, TrendSettings) else TrendSettings.from_dict(value)


@dataclass(frozen=True)
class MonitorOptions(StageOptions):
    """The monitor's options (the command line's help in :func:`add_options`)."""

    #: Also stream to a viewer: ``spawn``, ``serve`` or a ``rerun+http://`` URL (None: no).
    live: str | None = option(None, _live)
    #: Port of the spawned viewer or server (None: a free one).
    viewer_port: int | None = option(None, positive_int)
    #: The Rerun recording to write (None: ``<recordings>/<run>/monitor.rrd``).
    rrd: str | None = option(None, str)
    #: The rerun executable (None: :func:`streamer.tools.viewer.rerun_binary` finds it).
    rerun_binary: str | None = option(None, str)
    #: Points per decade of the drawn ASDs.
    asd_per_decade: int = option(20, positive_int)
    #: Band of the residual views [Hz].
    band: tuple[float, float] = option(DEFAULT_BAND, band_hz)
    #: The trend tests' settings (:class:`ttlcore.diagnose.trends.TrendSettings` fields).
    trends: TrendSettings = option(TrendSettings(), _trends)
    #: Seconds a segment may wait for an input whose producer is gone before it is settled.
    settle_timeout: float = option(60.0, positive_float)
    #: Spacing of the trend points [s] (one fit per window hop is drawn).
    trend_spacing: float = option(3600.0, positive_float)


def add_options(p) -> None:
    p.add_argument(
        "--live",
        help="also stream to a viewer: 'spawn' (start the rerun viewer on 127.0.0.1), "
        "'serve' (headless rerun gRPC server on 127.0.0.1) or a rerun+http:// URL",
    )
    p.add_argument("--viewer-port", type=int, help="port of the spawned viewer or server (default: a free one)")
    p.add_argument("--rrd", help="Rerun recording to write (default <recordings>/<run>/monitor.rrd)")


def options(args) -> dict:
    return {"live": args.live, "viewer_port": args.viewer_port, "rrd": args.rrd}

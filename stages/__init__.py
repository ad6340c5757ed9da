"""The stage programs of the streaming pipeline, one module each, in pipeline order.

==============  ================================  ==========================================
module          inputs -> output                  what
==============  ================================  ==========================================
``replayer``    files / simulation -> telemetry   telemetry segments in mission-time order
``tdi_builder`` telemetry -> tdi                  X2, Y2, Z2 of the data and 24 regressors
``fitter``      tdi -> fit                        rolling one-day fit, refit on every segment
``subtractor``  tdi + fit -> residual             residual and TTL model estimate
``monitor``     all of them -> monitor            ASDs, trends, alerts, drawn in Rerun
==============  ================================  ==========================================

Each is a thin program: parse a message, call :mod:`ttlcore` for the science, publish and
record through :mod:`streamer`.  Each runs as its own process: ``python -m stages.<name>
[options]`` or ``ttl stage <name> [options]`` (options: :func:`streamer.runtime.stage.stage_main`
plus the stage's own).  Their base classes (:mod:`streamer.runtime.pipeline_stage`), the progress
protocol (:mod:`streamer.runtime.progress`) and the shape of the pipeline (:mod:`streamer.bus.topology`)
are in :mod:`streamer`.  The fitter and the monitor are composed of parts, modules of this
package named after them (:mod:`stages.fitter.live_model`, :mod:`stages.monitor.settling`, ...: see
``docs/architecture.md``); those are not programs.
"""

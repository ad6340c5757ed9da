"""Operations plumbing of the streaming processor.

Modules
-------
topology
    The shape of the pipeline, written once: stages in order, their output topics, upstreams.
keys
    Key expressions: ``ttl/<run>/<topic>`` (segment data), liveliness, control and progress keys.
codec
    The segment codec: JSON header (attachment) plus raw array bytes (payload).
session
    Zenoh sessions (loopback peer by default, routers, config files), segment
    publishers/subscribers (``zenoh.ext`` advanced pub/sub), liveliness, :class:`Bus`.
fit_record, residual_record, monitor_record, segment_record, diagnosis_record
    The messages' meta as values, read by attribute (``FitMessage``, ``ResidualMessage``,
    ``MonitorMessage``, ``SegmentMeta``, ``LiveDiagnosis``); their schema rule and checks in
    ``message_schema``.
recorder
    MCAP recording and salvaging reader.
stage
    The stage base class: lifecycle, validation, idempotence, errors, recording; the entry
    point of a stage process (``stage_main``).
progress
    The progress protocol and its bookkeeping (``Progress``), for the stages and the launcher.
pipeline_stage
    The base classes of the stage programs: ``PipelineStage`` (reports progress) and
    ``OrderedStage`` (handles its input in index order).
catch_up, recorded_inputs
    An input segment announced by its producer that never came: its cache, then its
    recordings (read back by ``recorded_inputs``), else given up (``input-lost``).
launcher
    ``ttl run``: starts and supervises the five stage processes around a loopback router.
inspect
    ``ttl inspect`` / ``ttl view``: a run from its MCAP files and Rerun recording alone.
cli
    The operations subcommands of ``ttl`` (run, stage, router, inspect, view).
"""

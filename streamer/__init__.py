"""Operations plumbing of the streaming processor.

Modules
-------
keys
    Key expressions ``ttl/<run>/<topic>/<index>``, liveliness and control keys.
codec
    The segment codec: JSON header (attachment) plus raw array bytes (payload).
session
    Zenoh sessions (loopback peer by default, routers, config files), segment
    publishers/subscribers (``zenoh.ext`` advanced pub/sub), liveliness, :class:`Bus`.
recorder
    MCAP recording and salvaging reader.
stage
    The stage base class: lifecycle, validation, idempotence, errors, recording.
launcher
    ``ttl run``: starts and supervises the five stage processes around a loopback router.
inspect
    ``ttl inspect`` / ``ttl view``: a run from its MCAP files and Rerun recording alone.
cli
    The operations subcommands of ``ttl`` (run, stage, router, inspect, view).
"""

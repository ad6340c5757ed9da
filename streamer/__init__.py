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
"""

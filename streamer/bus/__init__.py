"""The bus: what travels between the stages on Zenoh, and its values (the lowest wing).

Modules
-------
topology
    The shape of the pipeline, written once: stages in order, their output topics, upstreams.
keys
    Key expressions: ``ttl/<run>/<topic>`` (segment data), liveliness, control and progress keys.
bounded_json, codec
    The segment codec: JSON header (parsed with every size bounded) plus raw array bytes.
message_schema
    What every typed message's meta shares: :class:`MessageError`, field checks, ``to_jsonable``.
segment_record, fit_record, residual_record, monitor_record, diagnosis_record
    The messages' meta as values, read by attribute (``SegmentMeta``, ``FitMessage``,
    ``ResidualMessage``, ``MonitorMessage``, ``LiveDiagnosis``).
messages
    The segment messages as :mod:`ttlcore` objects (telemetry, TDI data).
security
    Credentials and access control of a run: mutual TLS and Zenoh's access-control list.
segment_stream, session, transport
    Segment publishers with caches and subscribers that catch up; Zenoh sessions, routers,
    liveliness (:class:`~streamer.bus.session.Bus`); a stage's traffic in and out.
reach
    Whether a router is there: endpoint address, TCP probe, Zenoh's error text.
"""

"""The recordings: what each stage received and sent, in MCAP files, and reading them back.

Modules
-------
record_schemas
    The JSON schemas of a recording's records; the record of an error, warning or event.
recorder
    MCAP recording of a stage (:class:`~streamer.recording.recorder.Recorder`), its layout.
recording_reader
    Reading a recording back, whole or salvaged record by record.
recorded_inputs
    Segments read back from their producers' recordings: the copy of last resort.
"""

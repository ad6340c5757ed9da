"""The commands around a run: the ``ttl`` entry point, inspection, refits, viewers (the top wing).

Modules
-------
main, parsers, cli
    The ``ttl`` entry point, the operations subcommands' options, and what runs them
    (``ttl run``, ``stage``, ``router``, ``control``, ``credentials``).
inspect, inspect_advice, inspect_interruptions, inspect_model, inspect_records, inspect_text, inspect_timeline
    ``ttl inspect`` / ``ttl view``: a run from its MCAP files and Rerun recording alone.
model_timeline
    The fitter's model timeline, shared by ``ttl inspect`` and the monitor; bus-free.
refit, reprocess
    ``ttl refit`` (recorded segments with another model) and ``ttl reprocess`` (days on Dask).
viewer, webview
    Rerun viewer processes, a live stream a lost viewer cannot stall; ``ttl view --web``.
bench
    Loopback throughput of segment messages between two processes.
"""

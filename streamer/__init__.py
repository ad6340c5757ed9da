"""Operations plumbing of the streaming processor, in five wings, from the bottom.

A wing imports its own modules and those of the wings below it, never one above
(``tests/test_import_graph.py``, ``test_streamer_wings``); ``docs/architecture.md`` draws them.

==============  ==============================================================================
wing            what
==============  ==============================================================================
``bus``         what travels on Zenoh: the pipeline's shape, keys, the segment codec, sessions,
                segment streams, credentials, and the messages' meta as typed values
``recording``   the MCAP recordings: their record schemas, the recorder, the salvaging reader,
                segments read back from them
``runtime``     one stage process: the stage base, its command line, configuration and options,
                ingest, progress, plan, catch-up, lifecycle, child processes, memory
``launch``      ``ttl run``: the run's plan and options, its router, the supervision of the
                stage processes, the journal and the final verdict
``tools``       the commands around a run: ``ttl`` itself (entry point, parsers, cli),
                ``ttl inspect`` / ``view`` / ``refit`` / ``reprocess``, the viewers, a bench
==============  ==============================================================================

Each wing's ``__init__`` lists its modules and imports nothing.  The stage programs
(:mod:`stages`) stand above all five.
"""

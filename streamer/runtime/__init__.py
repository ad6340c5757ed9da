"""The runtime of one stage process: the stage base and what it runs on.

Modules
-------
stage, pipeline_stage
    The stage base class (lifecycle, validation, idempotence, errors, recording) and the base
    classes of the stage programs (``PipelineStage``, ``OrderedStage``).
stage_cli, stage_config, stage_options, settings
    A stage's command line and entry point (``stage_main``), its configuration
    (``StageConfig``), its options as one frozen value, and the typed-settings converter.
stage_reports, stagelog
    What a stage writes about itself (errors, warnings, events), and its logging.
ingest, plan, rangeset
    What a message must fit before ``handle`` sees it; the plan of a run; index ranges.
progress, catch_up, refetch_policy
    The progress protocol; inputs announced that never came; damaged copies asked again.
lifecycle, processes, allocator, memtrace
    Signals, the launcher a stage depends on, a full disk; child processes; the C
    allocator's settings; memory segment by segment.
"""

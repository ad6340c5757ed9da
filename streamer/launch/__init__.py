"""``ttl run``: the launcher of the five stage processes and what it keeps.

Modules
-------
launch_plan
    The run's options (``RunOptions``), their checks, each stage's configuration.
launcher
    Starts, supervises and stops the stage processes around a router.
run_router
    The run's Zenoh router process and its credentials.
supervision
    The stage processes: started, restarted when they die, stopped at the end.
run_journal, input_pins
    The launcher's journal, board and lock; the pins of the run's input files.
run_verdict
    The end of the run: what happened to the plan's segments, and the exit status.
"""

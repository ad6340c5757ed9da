"""Shared test set-up: the order in which pytest-xdist hands the modules out.

The helpers of the tests (``tests/lisainstrument_sim.py``, ``tests/pytdi_reference.py``,
``tests/proc_testutil.py``, ``tests/stages/ttl_testutil.py``, ...) are imported by name: their
directories are on pytest's ``pythonpath`` (pyproject.toml).
"""

#: Wall time of the longest test modules, seconds, each module's tests run one after the other
#: in one process on a loaded 2-core machine (per-test times summed; measured for issue 13).
#: ``make test`` runs pytest-xdist with ``--dist loadscope``: a module stays on one worker and
#: the modules are handed out in collection order, so a long module collected last (the
#: alphabetical order put tests/ttlcore/sim and tdi there) keeps one worker busy while the
#: other idles.  Longest first, the short modules fill in at the end and the workers finish
#: together.  Modules not listed (all under ~20 s) keep their order, after these.
MODULE_SECONDS = {
    "tests/test_pipeline.py": 200,
    "tests/test_live_loop.py": 175,
    "tests/ttlcore/diagnose/test_diagnose.py": 170,
    "tests/ttlcore/estimate/test_analyze.py": 137,
    "tests/ttlcore/sim/test_simulator.py": 90,
    "tests/ttlcore/diagnose/test_effects.py": 81,
    "tests/ttlcore/gw/test_scenarios.py": 80,
    "tests/ttlcore/sim/test_noise.py": 79,
    "tests/ttlcore/estimate/test_rolling.py": 75,
    "tests/ttlcore/tdi/test_tdi.py": 70,
    "tests/ttlcore/gw/test_gw_sources.py": 64,
    "tests/ttlcore/estimate/test_mcmc.py": 60,
    "tests/ttlcore/estimate/test_fit.py": 59,
    "tests/ttlcore/diagnose/test_diagnose_blind.py": 54,
    "tests/test_pipeline_lisainstrument.py": 46,
    "tests/streamer/test_process_tree.py": 43,  # two ttl runs killed, three routers (load 10-15)
    "tests/ttlcore/diagnose/test_witnesses.py": 44,
    "tests/ttlcore/io/test_lisainstrument_files.py": 36,
    "tests/stages/test_monitor_web_view.py": 34,
    "tests/ttlcore/cli/test_cli.py": 32,
    "tests/streamer/test_session.py": 27,
    "tests/ttlcore/diagnose/test_noise_model.py": 23,
    "tests/streamer/test_reprocess_command.py": 22,
    "tests/streamer/test_stage.py": 32,  # with the hostile-content and full-disk tests
}


def pytest_collection_modifyitems(session, config, items):
    """Longest modules first (:data:`MODULE_SECONDS`); a stable sort, so each module's tests
    keep their order and stay together."""
    items.sort(key=lambda item: -MODULE_SECONDS.get(item.nodeid.split("::", 1)[0], 0))

"""Shared test set-up.

``tests/lisainstrument_sim.py`` (runs lisainstrument for the outside-reference tests),
``tests/pytdi_reference.py`` (pytdi's natural usage, the TDI reference) and
``tests/proc_testutil.py`` (child processes, polling) are registered as modules of those
names here, loaded by path: putting ``tests/`` on
``sys.path`` would let ``tests/ttlcore`` shadow the installed ``ttlcore`` package.
Test files then simply ``from lisainstrument_sim import simulate_lisainstrument``.
"""

import importlib.util
import sys
from pathlib import Path

for _name in ("lisainstrument_sim", "pytdi_reference", "proc_testutil"):
    if _name not in sys.modules:
        _spec = importlib.util.spec_from_file_location(_name, Path(__file__).resolve().parent / f"{_name}.py")
        _module = importlib.util.module_from_spec(_spec)
        sys.modules[_name] = _module
        _spec.loader.exec_module(_module)

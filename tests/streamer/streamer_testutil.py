"""Helpers of the streamer tests: child processes running tests/streamer/procs.py, polling."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from proc_testutil import ChildProcesses, output, wait_for  # noqa: F401 - the tests import them from here

ROOT = Path(__file__).resolve().parents[2]
PROCS = Path(__file__).with_name("procs.py")


class Children(ChildProcesses):
    """Child processes running ``tests/streamer/procs.py ROLE ARGS`` (:class:`proc_testutil.ChildProcesses`)."""

    def start(self, role: str, **args) -> subprocess.Popen:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
        cmd = [sys.executable, str(PROCS), role, json.dumps(args)]
        return super().start(cmd, f"{role}-{len(self.procs)}", env=env, cwd=ROOT)


#: The output of a child (tests/streamer's name for it).
output_of = output

"""Helpers of the stage and pipeline tests: ``ttl`` and stage processes, polling, recordings."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import psutil
from proc_testutil import ChildProcesses, finish, output, wait_for  # noqa: F401 - the tests import them from here

from streamer.recording.recorder import read_recording
from ttlcore.io.telemetry import Telemetry

ROOT = Path(__file__).resolve().parents[2]

_TTL = Path(sys.executable).with_name("ttl")
#: The monitor stage is written separately; the pipeline tests run without it until it exists.
MONITOR = (ROOT / "stages" / "monitor" / "__main__.py").exists()


def ttl_command(*args: str) -> list[str]:
    """The ``ttl`` command line (the installed script, else ``python -m streamer.tools.cli``)."""
    base = [str(_TTL)] if _TTL.exists() else [sys.executable, "-m", "streamer.tools.cli"]
    return base + [str(a) for a in args]


class Procs(ChildProcesses):
    """Child processes of a test: ``ttl`` commands and stage processes (:class:`proc_testutil.ChildProcesses`)."""

    def ttl(self, *args: str, name: str = "ttl") -> subprocess.Popen:
        return self.start(ttl_command(*args), name)

    def stage(self, stage: str, *args: str) -> subprocess.Popen:
        return self.start([sys.executable, "-m", f"stages.{stage}", *map(str, args)], stage)


def stage_processes(proc) -> dict[str, psutil.Process]:
    """The stage children of a ``ttl run`` process, by stage name."""
    out = {}
    try:
        kids = psutil.Process(proc.pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return out
    for p in kids:
        try:
            cmd = p.cmdline()
        except psutil.Error:
            continue
        for i, word in enumerate(cmd[:-1]):
            if word == "-m" and cmd[i + 1].startswith("stages."):
                out[cmd[i + 1].split(".", 1)[1]] = p
    return out


def listening(proc: psutil.Process) -> tuple[list, list]:
    """(TCP listening sockets, UDP sockets) of a process."""
    conns = proc.net_connections(kind="inet")
    return (
        [c for c in conns if c.status == psutil.CONN_LISTEN],
        [c for c in conns if c.type == __import__("socket").SOCK_DGRAM],
    )


def indices(recording, topic: str) -> list[int]:
    return [s.header.index for s in recording.segments(topic)]


def recordings_of(run_dir: Path, stage: str) -> list:
    """Every recording of ``stage`` in ``run_dir`` (``<stage>.mcap`` and kept ``<stage>.<n>.mcap``)."""
    paths = sorted(run_dir.glob(f"{stage}.mcap")) + sorted(run_dir.glob(f"{stage}.[0-9]*.mcap"))
    return [read_recording(p) for p in paths]


def progress_messages(sample) -> dict:
    return json.loads(sample.payload.to_bytes())


def noise_telemetry(t0: float, seconds: float, fs: float, seed: int) -> Telemetry:
    """Telemetry of white noise (readouts of LISA-like sizes, arms of 8.34-8.39 s held): the
    input of the fitter's parts' unit tests, where what matters is the arithmetic, not the physics."""
    rng = np.random.default_rng(seed)
    n = int(seconds * fs)
    return Telemetry(
        t0=t0,
        fs=fs,
        eta=1e-12 * rng.standard_normal((6, n)),
        dws_phi=1e-9 * rng.standard_normal((6, n)),
        dws_eta=1e-9 * rng.standard_normal((6, n)),
        ltt=np.full((6, n), 8.34) + 0.01 * np.arange(6)[:, None],
        source="test",
    )

"""Helpers of the stage and pipeline tests: ``ttl`` and stage processes, polling, recordings."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import psutil
from proc_testutil import ChildProcesses, finish, output, wait_for  # noqa: F401 - the tests import them from here

from streamer.bus.session import Bus, SessionSettings
from streamer.recording.recorder import read_recording
from streamer.runtime.stage import StageConfig
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.data import TDIData

ROOT = Path(__file__).resolve().parents[2]

_TTL = Path(sys.executable).with_name("ttl")
#: The monitor stage is written separately; the pipeline tests run without it until it exists.
MONITOR = (ROOT / "stages" / "monitor" / "__main__.py").exists()
#: The stages a ``ttl run`` starts, in the pipeline's order, and the topic each publishes.
STAGES = ["replayer", "tdi_builder", "fitter", "subtractor"] + (["monitor"] if MONITOR else [])
OUTPUT = {
    "replayer": "telemetry",
    "tdi_builder": "tdi",
    "fitter": "fit",
    "subtractor": "residual",
    "monitor": "monitor",
}


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


def run_args(
    run_id: str,
    rec,
    *extra,
    sim: str | None = None,
    telemetry=None,
    segment: str | None = "1h",
    timeout: float | None = 900,
) -> list:
    """The arguments of a ``ttl run`` of a simulation (``sim``: ``ttl simulate`` options) or of
    ``telemetry`` files, in ``segment`` segments, recorded in ``rec/run_id``, given ``timeout``
    seconds (``segment``, ``timeout`` None: ttl run's defaults); ``extra`` after them."""
    source = ["--telemetry", telemetry] if sim is None else ["--simulate", sim]
    segments = [] if segment is None else ["--segment", segment]
    timeouts = [] if timeout is None else ["--timeout", str(timeout)]
    return ["run", *source, *segments, "--run-id", run_id, "--recordings", str(rec), *timeouts, *extra]


def fits_and_residuals(run_dir: Path) -> dict:
    """``{"fit": {index: arrays}, "residual": {index: arrays}}`` of a run, from every process's
    recording (a restarted stage leaves ``<stage>.<n>.mcap``; the first copy of an index wins)."""
    out: dict = {}
    for stage, topic in (("fitter", "fit"), ("subtractor", "residual")):
        out[topic] = {}
        for path in sorted(run_dir.glob(f"{stage}*.mcap")):
            for s in read_recording(path).segments(topic):
                out[topic].setdefault(s.header.index, s.arrays)
    return out


def watch_board(bus, run: str) -> dict:
    """stage -> its latest board message (``ttl/<run>/control/board/<stage>``), kept up to date
    by a subscriber on ``bus``."""
    board: dict = {}

    def on_sample(sample):
        msg = json.loads(sample.payload.to_bytes())
        board[msg["stage"]] = msg

    bus.segment_subscriber(f"ttl/{run}/control/board/*", on_sample, history=1)
    return board


def handled_count(board: dict, stage: str) -> int:
    """How many segments ``stage`` has handled, by its latest board message (:func:`watch_board`)."""
    msg = board.get(stage)
    return sum(b - a + 1 for a, b in (msg or {}).get("done", ())) if msg else 0


@contextlib.contextmanager
def control_session(endpoint: str, credentials: Path):
    """A client session on a run's router at ``endpoint`` as the ``control`` identity (mutual
    TLS with the run's ``credentials``), given half a second to connect before it is used."""
    settings = SessionSettings(mode="client", connect=(endpoint,), credentials=credentials, identity="control")
    with Bus.open(settings) as bus:
        time.sleep(0.5)
        yield bus


def local_stage_config(run: str, port: int, recordings: Path, **fields) -> StageConfig:
    """A stage's configuration in a test: a client of the test's router on 127.0.0.1:``port``
    that polls every 50 ms and records into ``recordings``; ``fields``: the rest."""
    zenoh = SessionSettings(connect=(f"tcp/127.0.0.1:{port}",))
    return StageConfig(run=run, zenoh=zenoh, recordings=recordings, poll_interval=0.05, **fields)


def wait_alive(bus, run: str, stage: str, proc, timeout: float) -> None:
    """Until ``stage``'s liveliness token is on ``bus`` (or ``proc`` has ended)."""
    wait_for(
        lambda: stage in bus.alive_stages(run, timeout=0.5) or proc.poll() is not None,
        timeout,
        f"the {stage}'s liveliness token",
    )


def start_monitor_stage(procs: Procs, run: str, port: int, tmp: Path, **fields) -> subprocess.Popen:
    """A monitor stage process on the test's router (:func:`local_stage_config`; its
    configuration in ``tmp/monitor.json``, its recordings in ``tmp/rec``)."""
    cfg = tmp / "monitor.json"
    cfg.write_text(json.dumps(local_stage_config(run, port, tmp / "rec", **fields).to_dict()))
    return procs.stage("monitor", "--config", cfg)


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


def router_process(launcher: subprocess.Popen) -> psutil.Process | None:
    """The ``ttl router`` child of a ``ttl run`` process (None: none, or the launcher is gone)."""
    try:
        kids = psutil.Process(launcher.pid).children()
    except psutil.NoSuchProcess:
        return None
    for p in kids:
        try:
            if "router" in p.cmdline():
                return p
        except psutil.Error:
            continue
    return None


def run_to_the_end(tmp: Path, args: list, timeout: float = 900) -> None:
    """``ttl *args`` (its output in ``tmp``) to its end, exit status 0 asserted."""
    procs = Procs(tmp)
    try:
        proc = procs.ttl(*args)
        code = finish(proc, timeout)
        assert code == 0, output(proc)[-3000:]
    finally:
        procs.close()


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


def noise_tdi_segment(rng, index: int, n: int, fs: float) -> tuple[SimpleNamespace, TDIData]:
    """Segment ``index`` of ``n`` samples at ``fs`` [Hz]: the header a stage reads (index, t0,
    segment duration) and TDI of white noise from ``rng`` (X2, Y2, Z2, then the 24 regressors)."""
    header = SimpleNamespace(index=index, t0=index * n / fs, meta={"segment_duration": n / fs})
    td = TDIData(
        t0=header.t0,
        fs=fs,
        channels=("X2", "Y2", "Z2"),
        data=rng.standard_normal((3, n)),
        regressors=rng.standard_normal((3, len(COEFFICIENT_NAMES), n)),
        ltt_mean=np.full(6, 8.3),
    )
    return header, td

"""Replayer stage: telemetry segments in mission-time order, from files or a simulation.

Sources (exactly one):

``telemetry``
    One or more telemetry files, ours or lisainstrument's (``ttlcore.io.reader.read_telemetry``
    detects which).  They are replayed in order of their start time; a segment never spans
    two files (the last one of a file may be shorter).  Our files are read one segment at a
    time; lisainstrument files are reduced to ``eta`` once, at start.
``simulate``
    ``ttl simulate`` options (without ``--out``), e.g. ``"--duration 12h --orbit unequal
    --seed 1"``: each segment is simulated when its turn comes
    (:meth:`ttlcore.sim.simulator.Simulator.chunk`, random access, so the result does not depend
    on the segment length).

Output ``ttl/<run>/telemetry/<i>``: arrays ``eta``, ``dws_phi``, ``dws_eta``, ``ltt``, each
(6, n) float64 with channels the six links; header t0 (first sample) and fs; meta
``source`` (path or ``"simulation"``), ``segments_total``, ``truth`` (the truth file
beside the source file, ``{"coefficients": <coefficient model description>}`` for a
simulation on the fly, else null; only the monitor reads it, to draw the truth), ``segment_duration`` [s] (nominal), ``dws_asd`` (DWS
readout-noise level of the source, for the fitter's errors-in-variables term), ``file``.

Pace
----
Segments go out as fast as the consumers take them: congestion control BLOCK holds a put
while a live subscriber's transport is full, and, on top, the replayer stays at most
``window`` segments ahead of the slowest stage that reports progress
(:mod:`streamer.runtime.progress`), so that a stage that dies finds what it missed in the publishers' caches when
it is restarted (``cache`` > ``window`` + 1).  With ``pace`` X > 0, segment ``i`` goes
out no earlier than ``i * segment_duration / X`` seconds after the first: X times real time.

Before the first segment the replayer waits until the stages in ``wait_for`` are alive
(liveliness tokens).  A restarted replayer resumes one segment before the first one that
some stage reporting progress still lacks.

Pinned inputs
-------------
The files are pinned in the run's plan (``Plan.inputs``, :mod:`streamer.launch.input_pins`): a
replayer started or restarted with a plan refuses files that are not those, unchanged, and
checks a file's size and modification time before and after reading each segment.  A file
changed under the run is an ``input-changed`` error naming it and what changed, and the
replayer stops (exit status 2): no segment is read from a file the run was not planned with.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streamer.launch.input_pins import InputChanged, check_pins, check_stat, pin
from streamer.runtime.pipeline_stage import PipelineStage
from streamer.runtime.plan import Plan
from streamer.runtime.progress import REPLAY_WINDOW
from streamer.runtime.stage import Output, stage_main
from streamer.runtime.stage_options import StageOptions, duration_s, names, nonnegative_float, option, positive_int
from ttlcore.cli.simulation import simulation_config
from ttlcore.conventions import LINKS
from ttlcore.errors import ConfigError, TelemetryError
from ttlcore.estimate.fit import dws_asd_from_config
from ttlcore.io.atomic import write_text
from ttlcore.io.reader import file_kind, read_telemetry
from ttlcore.io.telemetry import Telemetry, read_header
from ttlcore.io.truth import truth_path
from ttlcore.sim.simulator import Simulator

#: Units of the telemetry arrays.
UNITS = {"eta": "fractional frequency", "dws_phi": "rad/s", "dws_eta": "rad/s", "ltt": "s"}
#: Default segment length [s].
DEFAULT_SEGMENT = 3600.0


# ---------------------------------------------------------------------------- sources


@dataclass
class _Piece:
    file: int
    start: int
    stop: int


def _file_entry(path: Path) -> dict:
    """What the replayer keeps of a telemetry file: ``path``, ``kind`` (``ttl`` or
    lisainstrument's), ``t0``, ``fs``, ``size``, ``config``, ``data`` (a lisainstrument file
    read whole, reduced to eta once; None for ours, read segment by segment), ``truth`` (the
    truth file beside it, or None) and its ``pin``."""
    if not path.exists():
        raise TelemetryError(path, "no such file")
    pinned = pin(path)
    kind = file_kind(path)
    if kind == "truth":
        raise TelemetryError(path, "this is a truth file; give the telemetry file beside it")
    if kind == "ttl":
        head = read_header(path)
        entry: dict = {
            "path": path,
            "kind": kind,
            "t0": head["t0"],
            "fs": head["fs"],
            "size": head["size"],
            "config": head["config"] or {},
            "data": None,
        }
    else:  # lisainstrument: reduced to eta once
        tm = read_telemetry(path)
        entry = {
            "path": path,
            "kind": kind,
            "t0": tm.t0,
            "fs": tm.fs,
            "size": tm.size,
            "config": tm.config or {},
            "data": tm,
        }
    tp = truth_path(path)
    entry["truth"] = str(tp) if tp.exists() else None
    check_stat(pinned)  # not changed while its header was read
    entry["pin"] = pinned
    return entry


class FileSource:
    """Segments of one or more telemetry files, in mission-time order.

    Every file is pinned when opened (:func:`streamer.launch.input_pins.pin`: size, modification
    time, sampled digest); with ``planned`` (the pins of the run's plan) the files must be
    those, unchanged, and before each segment is read its file is checked again (one
    ``stat``): :class:`streamer.launch.input_pins.InputChanged` otherwise.
    """

    def __init__(self, paths, segment_duration: float, planned=None):
        if not paths:
            raise ConfigError("--telemetry: no file given")
        if planned:  # a run's replayer, started or restarted: the files it was planned with
            check_pins(planned, paths)
        self.files = sorted((_file_entry(Path(p)) for p in paths), key=lambda e: e["t0"])
        fs = self.files[0]["fs"]
        for e in self.files[1:]:
            if e["fs"] != fs:
                raise TelemetryError(
                    e["path"], f"sampling rate {e['fs']} Hz differs from {fs} Hz of {self.files[0]['path']}"
                )
        for a, b in zip(self.files, self.files[1:]):
            if b["t0"] < a["t0"] + a["size"] / fs - 0.5 / fs:
                raise TelemetryError(
                    b["path"],
                    f"starts at t0={b['t0']} s, before {a['path']} ends "
                    f"({a['t0'] + a['size'] / fs} s): overlapping files",
                )
        self.fs = fs
        self.segment_duration = float(segment_duration)
        n = int(round(self.segment_duration * fs))
        if n < 1:
            raise ConfigError(f"--segment: {segment_duration} s is less than one sample at {fs} Hz")
        self.pieces = [
            _Piece(k, s, min(s + n, e["size"])) for k, e in enumerate(self.files) for s in range(0, e["size"], n)
        ]

    @property
    def segments_total(self) -> int:
        return len(self.pieces)

    def plan(self) -> Plan:
        """The run's plan (:class:`streamer.runtime.plan.Plan`): regular for one file, a table of the
        segments' starts and lengths for several."""
        first = self.files[0]
        n = int(round(self.segment_duration * self.fs))
        table = None
        if len(self.files) > 1:
            table = tuple((self.files[p.file]["t0"] + p.start / self.fs, p.stop - p.start) for p in self.pieces)
        inputs = tuple(e["pin"] for e in self.files)
        return Plan(self.segments_total, self.fs, float(first["t0"]), n, int(first["size"]), table, inputs=inputs)

    def describe(self) -> str:
        names = ", ".join(str(e["path"]) for e in self.files)
        return f"{self.segments_total} segments of {self.segment_duration:g} s from {names}"

    def segment(self, i: int) -> tuple[Telemetry, dict]:
        piece = self.pieces[i]
        e = self.files[piece.file]
        if e["data"] is not None:  # read whole at open (and pinned then)
            tm = e["data"].slice(piece.start, piece.stop)
        else:  # the file as pinned, before and after the read (replaced while read)
            check_stat(e["pin"])
            tm = read_telemetry(e["path"], piece.start, piece.stop)
            check_stat(e["pin"])
        meta = {
            "source": str(e["path"]),
            "truth": e["truth"],
            "file": piece.file,
            "dws_asd": dws_asd_from_config(e["config"]),
        }
        return tm, meta


class SimulationSource:
    """Segments simulated on demand (``ttl simulate`` options)."""

    def __init__(self, options: str, segment_duration: float):

        self.config = simulation_config(options)
        self.sim = Simulator(self.config)
        # Segments are read in order, each reaching back into the previous one only by the
        # delays' history (about a minute): one cached output block per noise stream is
        # enough.  The default two (for random access) double the noise cache when the
        # second block (~36 h into the run) is computed, ~280 MB at 4 Hz, a step in the
        # replayer's memory a day and a half into every run.  The output does not change
        # (a block is a function of its index alone); a block is computed again only when a
        # segment's history reaches back across a block boundary the previous segment
        # crossed, at most once per block.
        for stream in self.sim.streams.values():
            if stream is not None:
                stream.cache_blocks = 1
        self.fs = self.config.fs
        self.segment_duration = float(segment_duration)
        self.n = int(round(self.segment_duration * self.fs))
        if self.n < 1:
            raise ConfigError(f"--segment: {segment_duration} s is less than one sample at {self.fs} Hz")
        self.dws_asd = dws_asd_from_config(self.config.to_dict())

    @property
    def segments_total(self) -> int:
        return -(-self.sim.size // self.n)

    def plan(self) -> Plan:
        """The run's plan (:class:`streamer.runtime.plan.Plan`), regular."""
        return Plan(self.segments_total, self.fs, float(self.config.t0), self.n, int(self.sim.size))

    def describe(self) -> str:
        return (
            f"{self.segments_total} segments of {self.segment_duration:g} s simulated on the fly "
            f"({self.config.duration:g} s, orbit {self.config.orbit}, seed {self.config.seed})"
        )

    def segment(self, i: int) -> tuple[Telemetry, dict]:
        n0 = i * self.n
        tm, _ = self.sim.chunk(n0, min(self.n, self.sim.size - n0))
        # truth of a simulation on the fly: its coefficient model (for the monitor's truth
        # overlay; the fitter and subtractor never read it)
        truth = {"coefficients": self.config.coefficients.describe()}
        return tm, {"source": "simulation", "truth": truth, "file": None, "dws_asd": self.dws_asd}


def _files(value) -> tuple[str, ...]:
    return (value,) if isinstance(value, str) else tuple(str(f) for f in value)


@dataclass(frozen=True)
class ReplayerOptions(StageOptions):
    """The replayer's options (their command-line help in :func:`add_options`)."""

    #: Telemetry files (ours or lisainstrument's), or None.
    telemetry: tuple[str, ...] | None = option(None, _files)
    #: ``ttl simulate`` options of a simulation replayed on the fly, or None.
    simulate: str | None = option(None, str)
    #: Segment length [s].
    segment: float = option(DEFAULT_SEGMENT, duration_s)
    #: Multiple of real time (0: as fast as the consumers take them).
    pace: float = option(0.0, nonnegative_float)
    #: Segments the replay may run ahead of the slowest stage.
    window: int = option(REPLAY_WINDOW, positive_int)
    #: Stages to wait for (liveliness) before the first segment.
    wait_for: tuple[str, ...] = option((), names)
    #: Stages reporting progress to stay within ``window`` of.
    pace_on: tuple[str, ...] = option((), names)
    #: With ``--check``: write the run's plan (JSON) to this file.
    plan_out: str | None = option(None, str)

    def __post_init__(self):
        if self.telemetry and self.simulate:
            raise ValueError("give either --telemetry or --simulate, not both")


def make_source(options: ReplayerOptions | Mapping, planned=None):
    """The source described by the replayer's options (``telemetry`` or ``simulate``,
    ``segment``; a mapping is parsed first); ``planned``: the pins of the run's plan
    (``Plan.inputs``) the files must match."""
    o = options if isinstance(options, ReplayerOptions) else ReplayerOptions.parse(options, "replayer")
    if o.simulate:
        return SimulationSource(o.simulate, o.segment)
    if o.telemetry:
        return FileSource(list(o.telemetry), o.segment, planned)
    raise ConfigError('no telemetry source: give --telemetry FILE... or --simulate "<ttl simulate options>"')


# ---------------------------------------------------------------------------- the stage


class Replayer(PipelineStage[ReplayerOptions]):
    """Publishes telemetry segments in mission-time order (files or simulation)."""

    name = "replayer"
    options_type = ReplayerOptions
    inputs = ()
    follow = ("*",)
    default_poll_interval = 0.01

    def __init__(self, config):
        super().__init__(config)
        o = self.options
        # the files as the run was planned (restarted too): a changed file stops it here
        self.source = make_source(o, (config.plan or {}).get("inputs"))
        self.segments_total = self.source.segments_total
        self.segment_duration = self.source.segment_duration
        self.pace = o.pace
        self.window = o.window
        self.wait_for = o.wait_for
        self.pace_on = o.pace_on
        self.next: int | None = None
        self.first = 0
        self._t_start = 0.0
        self._last_check = 0.0
        self._last_log = 0.0
        #: Why the replayer stopped on its own: an input file changed under the run.
        self.input_changed: InputChanged | None = None

    def run(self) -> int:
        """:meth:`streamer.runtime.stage.Stage.run`; exit status 2 with one line naming the file when
        an input file changed under the run (the recording closed as on any stop)."""
        code = super().run()
        if self.input_changed is not None:
            print(f"ttl stage {self.name}: error: {self.input_changed}", file=sys.stderr, flush=True)
            return 2
        return code

    def setup(self) -> None:
        super().setup()
        self.log.info("source: %s", self.source.describe())

    # ------------------------------------------------------------------ flow control
    def _consumers_alive(self) -> bool:
        if not self.wait_for:
            return True
        alive = self.live_bus.alive_stages(self.run_id, timeout=0.3)
        missing = [s for s in self.wait_for if s not in alive]
        if missing and time.monotonic() - self._last_log > 10:
            self._last_log = time.monotonic()
            self.log.info("waiting for %s to be alive before the first segment", ", ".join(missing))
        return not missing

    def lagging(self, index: int) -> list[str]:
        """Stages that have not yet handled ``index - window`` (the replayer waits for them)."""
        board = self.board.snapshot()
        names = (set(board) | set(self.pace_on)) - {self.stage_name}
        need = index - self.window
        out = []
        for name in sorted(names):
            peer = board.get(name)
            if peer is not None and (peer.covers(self.source.segments_total) or peer.complete):
                continue
            if (peer.highest if peer is not None else -1) < need:
                out.append(name)
        return out

    def _resume_index(self) -> int:
        """Where a (re)started replayer begins: one before the first segment a stage lacks."""
        board = self.board.snapshot()
        peers = [p for name, p in board.items() if name != self.stage_name]
        if not peers or any(name not in board for name in self.pace_on):
            return 0
        first_missing = min(
            min(set(range(self.source.segments_total)) - p.handled, default=self.source.segments_total) for p in peers
        )
        return max(0, first_missing - 1)

    # ------------------------------------------------------------------ source loop
    def tick(self):
        i = self.next if self.next is not None else self._start()
        if i is None:
            return ()
        if i >= self.source.segments_total:
            self.check_complete()
            return ()
        if self.lagging(i) or not self._due(i):
            return ()
        try:
            out = self._telemetry_output(i)
            if out is None:  # no data: a gap, reported; downstream moves on
                self.next = i + 1
                self.mark_gap(i)
                return ()
            self.publish(out)
        except InputChanged as exc:  # the run's input is not what it was planned with: stop
            self.report_error("input-changed", f"{exc}: the replayer stops (segment {i} not read)", index=i)
            self.input_changed = exc
            self.stop()  # (the stage loop reports any exception of a tick and goes on)
            return ()
        except Exception as exc:  # reported, and the replay goes on
            self.log.exception("segment %d failed", i)
            self.report_error("failed", f"{type(exc).__name__}: {exc}", index=i)
            self.next = i + 1
            self.mark_failed(i)
            return ()
        self.next = i + 1
        self.log.info("published telemetry segment %d/%d (t0=%.1f s)", i + 1, self.segments_total, out.fields["t0"])
        self.mark_done(i)
        return ()

    def _start(self) -> int | None:
        """The first segment to publish, once the consumers are alive (checked every 0.2 s;
        None until then): where the stages' progress says the run stands."""
        now = time.monotonic()
        if now - self._last_check < 0.2:
            return None
        self._last_check = now
        if not self._consumers_alive():
            return None
        time.sleep(0.2)  # let the progress caches of restarted runs arrive
        self.first = self.next = self._resume_index()
        if self.first:
            self.log.info("resuming at segment %d (stages report %d.. missing)", self.first, self.first + 1)
        self._t_start = time.monotonic()
        return self.next

    def _due(self, i: int) -> bool:
        """Whether segment ``i`` is due at the replay's pace (always, at pace 0)."""
        if self.pace <= 0:
            return True
        return time.monotonic() >= self._t_start + (i - self.first) * self.segment_duration / self.pace

    def _telemetry_output(self, i: int) -> Output | None:
        """The telemetry message of segment ``i`` (its NaN stretches flagged, a ``gap``
        event); None when it holds no finite sample (reported as a gap)."""
        tm, meta = self.source.segment(i)
        gaps = tm.nan_stretches()
        if not np.isfinite(tm.eta).any():
            self.report_error(
                "gap",
                f"telemetry segment {i} (t0={tm.t0} s) has no finite eta sample: no data, published as a gap",
                index=i,
            )
            return None
        if not np.isfinite(tm.ltt).all():
            raise ValueError("light travel times (ltt) are not finite everywhere")
        if gaps:
            self.event(
                "gap",
                index=i,
                message=f"telemetry segment {i}: {len(gaps)} NaN stretch(es) "
                f"({sum(b - a for a, b in gaps)} samples), published flagged",
                stretches=gaps,
            )
        return Output(
            self.output_topic,
            {"eta": tm.eta, "dws_phi": tm.dws_phi, "dws_eta": tm.dws_eta, "ltt": tm.ltt},
            fields={
                "t0": float(tm.t0),
                "fs": float(tm.fs),
                "channels": list(LINKS),
                "units": UNITS,
                "meta": {
                    **meta,
                    "segments_total": self.segments_total,
                    "segment_duration": self.segment_duration,
                    "gaps": gaps,
                },
            },
            index=i,
            allow_nonfinite=bool(gaps),
        )


# ---------------------------------------------------------------------------- entry point


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--telemetry", nargs="+", metavar="FILE", help="telemetry files (ours or lisainstrument's)")
    p.add_argument("--simulate", metavar="OPTIONS", help="'ttl simulate' options, e.g. \"--duration 12h --seed 1\"")
    p.add_argument("--segment", help="segment length, e.g. 1h, 30min or seconds (default 1h)")
    p.add_argument("--pace", type=float, help="multiple of real time (default: as fast as consumers take them)")
    p.add_argument(
        "--window", type=int, help=f"segments the replay may run ahead of the slowest stage (default {REPLAY_WINDOW})"
    )
    p.add_argument("--wait-for", help="stages to wait for (liveliness) before the first segment, comma-separated")
    p.add_argument("--plan-out", help="with --check: write the run's plan (JSON) to this file")
    p.add_argument(
        "--pace-on",
        help="stages reporting progress to stay within --window of, comma-separated "
        "(stages that report progress are followed anyway once seen)",
    )


def options(args) -> dict:
    def split(s):
        return [x for x in s.split(",") if x] if s else None

    return {
        "telemetry": args.telemetry,
        "simulate": args.simulate,
        "segment": args.segment,
        "pace": args.pace,
        "window": args.window,
        "wait_for": split(args.wait_for),
        "pace_on": split(args.pace_on),
        "plan_out": args.plan_out,
    }


def check(config) -> str:
    """Validate the source options (``--check``): one line describing the replay; with option
    ``plan_out`` the run's plan is written there as JSON (``ttl run`` gives it to every stage)."""
    options = ReplayerOptions.parse(config.options, "replayer")
    source = make_source(options)
    if options.plan_out:
        write_text(Path(options.plan_out), json.dumps(source.plan().to_dict()))
    return source.describe()


def main(argv=None) -> int:
    return stage_main(Replayer, argv, add_options, options, check)


if __name__ == "__main__":
    sys.exit(main())

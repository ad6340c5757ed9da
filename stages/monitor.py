"""Monitor stage: ASDs, coefficient trends, model adequacy and alerts, drawn in Rerun.

Inputs ``ttl/<run>/telemetry/<i>``, ``tdi/<i>``, ``fit/<i>`` and ``residual/<i>``; it draws
whatever it receives, so it may start late (it then draws from the publishers' caches on)
or miss a topic.  A message that does not fit is rejected by the stage base (reported on
``errors``); an exception while drawing one is reported as that segment's failure; the
monitor goes on in both cases.

What it computes
----------------
* ASD of X2 per segment (Welch, Hann, log-averaged 20 per decade, in displacement
  m/sqrt(Hz)): the data (with TTL), the residual, the TTL model, the expected secondary
  noise (:func:`ttlcore.estimate.noise_psd.tdi_noise_csd` for the segment's mean arms, X channel)
  and the LISA requirement; and per segment the in-band (fit band) median of
  residual / expected, a one-number adequacy check beside the fit's chi^2/dof.
* Coefficient trends: every fit's 24 coefficients with +-1 sigma, at the centre of its
  window (the estimate is the window's average); when the telemetry meta names a truth
  file, the true coefficients averaged over the same window.
* Step and drift alerts from :class:`ttlcore.diagnose.trends.TrendMonitor` (thresholds and their
  false-alarm reasoning in :mod:`ttlcore.diagnose.trends`).  Each alert is logged as a Rerun text
  entry, written to the MCAP recording as JSON (topic ``alerts``, schema ``ttl.Alert``)
  and published with the fit's index on ``ttl/<run>/monitor/<i>``.

Output ``ttl/<run>/monitor/<i>``, one per segment, once the segment is drawn: its TDI, and
its fit and residual from a fitter / subtractor that reports progress (they are waited for
until that stage has passed the segment, at most ``settle_timeout`` = 60 s; a stage that is
skipped or not started blocks nothing).  The segment is then done for the progress protocol
(:mod:`streamer.progress`), so the replayer paces on the monitor too and ``ttl run`` stops it only once
it has drawn everything.  Arrays ``drift_rate`` (24,) [mm/rad/day] and
``drift_significance`` (24,) of the latest trend evaluation (0 where not yet defined, see
meta ``drift_windows``); meta ``names``, ``alerts`` (the alerts raised since the previous
monitor message, each :meth:`ttlcore.diagnose.trends.Alert.to_json` with the index of the fit that
raised it), ``drifting``, ``drift_windows``, ``residual_over_expected`` (latest in-band
median ASD ratio and its segment), ``fit`` (index, chi2_dof and window of the latest fit),
``segments_total``.  The same goes to the recording on ``monitor/summary``.

Rerun recording ``<recordings>/<run>/monitor.rrd`` (an existing one is kept as
``monitor.<n>.rrd``, like the MCAP files), flushed after every message, with a blueprint
that shows everything at once; the views, their entities and the drawing functions are in
:mod:`stages.monitor_views`.  Timelines: ``mission_time`` (duration, seconds of mission
time) and ``segment`` (sequence).  A fit that did not converge is a WARN entry of the
alerts log here, and a ``warnings`` message in the fitter's MCAP file (``ttl inspect``).

Live viewing (option ``live``): ``"spawn"`` starts the ``rerun`` viewer binary with
``--bind 127.0.0.1`` on a free (or ``viewer_port``) port and streams to it as well (the
window outlives the monitor); ``"serve"`` starts ``rerun --serve-grpc --bind 127.0.0.1``
(headless, stopped with the monitor; a viewer connects with ``rerun --connect
rerun+http://127.0.0.1:<port>/proxy``); a ``rerun+http://`` URL streams to a viewer already
running there.  The SDK's own web-viewer server (which listens on every interface) is never
used.  The live stream is a recording stream of its own, flushed with a short timeout: a
viewer that cannot start (no display), is unreachable or goes away is dropped with a
warning and the file goes on.

Options (``StageConfig.options`` or the command line): ``rrd`` (path), ``live``,
``viewer_port``, ``rerun_binary``, ``trends`` (:class:`ttlcore.diagnose.trends.TrendSettings`
fields), ``asd_per_decade`` (20), ``band`` ([fmin, fmax], default the fit band),
``settle_timeout`` (60 s), ``trend_spacing`` (3600 s: the trends get at most one fit per
hour of window end, so that their cost per segment stays bounded with short segments).
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path
from urllib.parse import urlparse

import numpy as np

from streamer.codec import Expect
from streamer.inspect import rerun_binary
from streamer.keys import topic_pattern
from streamer.pipeline_stage import PipelineStage
from streamer.recorder import to_jsonable
from streamer.session import free_port
from streamer.stage import Output, stage_main
from ttlcore.conventions import (
    ARM_LENGTH,
    COEFFICIENT_NAMES,
    LINKS,
    C,
    ffd_to_displacement_asd,
)
from ttlcore.diagnose.trends import Alert, TrendMonitor, TrendSettings
from ttlcore.estimate.fit import DEFAULT_BAND
from ttlcore.estimate.noise_psd import requirement_x2, tdi_noise_csd
from ttlcore.estimate.spectra import default_nperseg, log_average, welch_asd
from ttlcore.io.truth import read_truth
from ttlcore.sim.coefficients import CoefficientModel

from . import monitor_views as views

P = len(COEFFICIENT_NAMES)
LOOPBACK = "127.0.0.1"
#: Application id of the Rerun recording.
APPLICATION_ID = "ttl_monitor"
#: JSON schema of an alert in the MCAP recording.
ALERT_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "ttl.Alert",
    "type": "object",
    "required": ["kind", "coefficient", "t", "value", "significance", "message"],
    "properties": {
        "run": {"type": "string"},
        "kind": {"type": "string", "description": "step | drift"},
        "coefficient": {"type": "string"},
        "t": {"type": ["number", "null"], "description": "step time or end of the drift span [s]"},
        "value": {"type": ["number", "null"], "description": "step [mm/rad] or drift rate [mm/rad/day]"},
        "significance": {"type": ["number", "null"]},
        "message": {"type": "string"},
        "t_detected": {"type": ["number", "null"]},
        "index": {"type": ["integer", "null"], "description": "fit that raised it"},
        "units": {"type": "string"},
        "details": {"type": "object"},
    },
}
def _wait_port(port: int, timeout: float = 10.0, proc=None) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            return False
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.settimeout(0.2)
            if s.connect_ex((LOOPBACK, port)) == 0:
                return True
        time.sleep(0.1)
    return False


def _reachable(url: str, timeout: float = 1.0) -> bool:
    """Whether something listens at the host and port of a ``rerun+http://host:port/proxy`` URL."""

    u = urlparse(url.replace("rerun+", "", 1).replace("rerun://", "https://", 1))
    port = u.port or (443 if u.scheme == "https" else 9876)
    try:
        with socket.create_connection((u.hostname or LOOPBACK, port), timeout=timeout):
            return True
    except OSError:
        return False


class Fanout:
    """Logs to the file recording and, while it works, to a live viewer's recording.

    The live stream is flushed with a short timeout; when it fails (the viewer closed or
    unreachable) it is dropped, so a lost viewer never stalls the monitor or the file.
    """

    def __init__(self, file_rec, live_rec=None, on_live_failure=None, live_timeout: float = 2.0):
        self.file = file_rec
        self.live = live_rec
        self.on_live_failure = on_live_failure
        self.live_timeout = live_timeout

    def _both(self, name, *args, **kwargs):
        getattr(self.file, name)(*args, **kwargs)
        if self.live is not None:
            getattr(self.live, name)(*args, **kwargs)

    def log(self, *args, **kwargs):
        self._both("log", *args, **kwargs)

    def set_time(self, *args, **kwargs):
        self._both("set_time", *args, **kwargs)

    def send_recording_name(self, name: str):
        self._both("send_recording_name", name)

    def flush(self) -> None:
        self.file.flush()
        if self.live is not None:
            try:
                self.live.flush(timeout_sec=self.live_timeout)
            except RuntimeError as exc:
                self._drop_live(exc)

    def _drop_live(self, exc) -> None:

        live, self.live = self.live, None
        threading.Thread(target=live.disconnect, daemon=True).start()  # may wait for a last attempt
        if self.on_live_failure is not None:
            self.on_live_failure(exc)

    def disconnect(self) -> None:
        self.file.disconnect()  # writes the file's footer
        if self.live is not None:
            try:
                self.live.flush(timeout_sec=self.live_timeout)
            except RuntimeError:
                pass
            self.live.disconnect()


def _die_with_parent() -> None:  # in the child, before exec (Linux): SIGTERM when the monitor dies
    try:

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except Exception:
        pass


def spawn_viewer(mode: str, port: int | None = None, binary: str | None = None):
    """Start the ``rerun`` binary on 127.0.0.1 only; returns ``(process, url)``.

    ``mode`` ``"spawn"``: the native viewer (which serves gRPC on ``port``);
    ``"serve"``: a headless gRPC server that viewers connect to later.
    """
    port = int(port or free_port(LOOPBACK))
    cmd = [rerun_binary(binary), "--bind", LOOPBACK, "--port", str(port)]
    cmd += ["--serve-grpc"] if mode == "serve" else ["--expect-data-soon"]
    # the viewer window outlives the monitor (its own session); the headless server dies with it
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True,
                            preexec_fn=_die_with_parent if mode == "serve" else None)
    if not _wait_port(port, proc=proc):
        code = proc.poll()
        if code is None:
            proc.terminate()
        raise RuntimeError(f"{cmd[0]}: the Rerun viewer did not listen on {LOOPBACK}:{port}"
                           + (f" (exited with status {code}; no display?)" if code is not None else " within 10 s"))
    return proc, f"rerun+http://{LOOPBACK}:{port}/proxy"


def rrd_path(recordings: Path, run: str, explicit=None) -> Path:
    """``<recordings>/<run>/monitor.rrd``; an existing file is first renamed ``monitor.<n>.rrd``."""
    path = Path(explicit) if explicit else Path(recordings) / run / "monitor.rrd"
    if path.exists():
        n = 1
        while (old := path.with_name(f"{path.stem}.{n}{path.suffix}")).exists():
            n += 1
        path.rename(old)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


# ---------------------------------------------------------------------------- science helpers

def finite_stretch(x: np.ndarray) -> np.ndarray:
    """The longest run of finite samples of a 1-D series."""
    ok = np.isfinite(x)
    if ok.all():
        return x
    edges = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    if starts.size == 0:
        return x[:0]
    k = int(np.argmax(stops - starts))
    return x[starts[k]:stops[k]]


def x_asd(x: np.ndarray, fs: float, per_decade: int = 20):
    """Log-averaged displacement ASD of one TDI channel in fractional frequency.

    Returns ``(f [Hz], asd [m/sqrt(Hz)], f_welch)`` (``f_welch`` the Welch grid without DC,
    for curves that must be averaged on the same bins).
    """

    x = finite_stretch(np.asarray(x, dtype=float))
    if x.size < 64:
        raise ValueError(f"too few finite samples ({x.size}) for an ASD")
    f, asd = welch_asd(x, fs, default_nperseg(x.size, fs))
    fc, psd = log_average(f[1:], asd[1:] ** 2, per_decade=per_decade)
    good = psd > 0
    return fc[good], ffd_to_displacement_asd(np.sqrt(psd[good]), fc[good]), f[1:]


def reference_curves(f_welch: np.ndarray, ltt, per_decade: int = 20) -> dict:
    """Expected secondary noise of X2 for the arms ``ltt`` (six values [s]) and the
    requirement, log-averaged like the data: ``{name: (f, asd [m/sqrt(Hz)])}``."""

    expected = np.real(tdi_noise_csd(f_welch, ltt, aet=False)[:, 0, 0])
    out = {}
    for name, psd in (("expected", expected), ("requirement", requirement_x2(f_welch))):
        fc, p = log_average(f_welch, psd, per_decade=per_decade)
        good = p > 0
        out[name] = (fc[good], ffd_to_displacement_asd(np.sqrt(p[good]), fc[good]))
    return out


def band_ratio(f, a, f_ref, ref, band) -> float:
    """Median of ``a / ref`` over ``band`` (``ref`` interpolated in log-log onto ``f``)."""
    sel = (f >= band[0]) & (f <= band[1])
    if not sel.any():
        return float("nan")
    r = np.interp(np.log10(f[sel]), np.log10(f_ref), np.log10(ref))
    return float(np.median(a[sel] / 10 ** r))


class ModelTruth:
    """True coefficients of a simulation on the fly, averaged over time spans from its
    coefficient model (:meth:`ttlcore.sim.coefficients.CoefficientModel.mean`)."""

    path = "simulation"

    def __init__(self, model):
        self.model = model

    def mean(self, t_start: float, t_stop: float) -> np.ndarray:
        return self.model.mean(t_start, t_stop)


class TruthAverager:
    """True coefficients averaged over time spans, read block by block from a truth file.

    Blocks of ``block`` seconds are read once with :func:`ttlcore.io.truth.read_truth` and
    kept as sums; a span's average adds whole blocks and reads its partial edges.
    """

    def __init__(self, path, block: float = 3600.0):

        self.path = Path(path)
        head = read_truth(self.path, 0, 1)
        self.t0, self.fs = float(head.t0), float(head.fs)
        self.block = max(1, int(round(block * self.fs)))
        self._sums: dict[int, tuple[np.ndarray, int]] = {}

    def _read(self, a: int, b: int) -> tuple[np.ndarray, int]:

        if b <= a:
            return np.zeros(P), 0
        c = read_truth(self.path, a, b).coefficients
        return c.sum(axis=1), c.shape[1]

    def mean(self, t_start: float, t_stop: float) -> np.ndarray | None:
        """Average true coefficients over ``[t_start, t_stop)`` [m/rad], None if outside the file."""
        a = max(0, int(math.ceil((t_start - self.t0) * self.fs - 1e-9)))
        b = int(math.ceil((t_stop - self.t0) * self.fs - 1e-9))
        total, count = np.zeros(P), 0
        first_full = -(-a // self.block)
        last_full = b // self.block
        if first_full >= last_full:
            s, n = self._read(a, b)
            total, count = total + s, count + n
        else:
            s, n = self._read(a, first_full * self.block)
            total, count = total + s, count + n
            for k in range(first_full, last_full):
                if k not in self._sums:
                    self._sums[k] = self._read(k * self.block, (k + 1) * self.block)
                s, n = self._sums[k]
                total, count = total + s, count + n
            s, n = self._read(last_full * self.block, b)
            total, count = total + s, count + n
        return total / count if count else None


# ---------------------------------------------------------------------------- the stage

class Monitor(PipelineStage):
    """Draws ASDs, coefficient trends, chi^2/dof and alerts in Rerun (module docstring)."""

    name = "monitor"
    inputs = ("telemetry", "tdi", "fit", "residual")
    follow = ("tdi_builder", "fitter", "subtractor")

    def __init__(self, config):
        super().__init__(config)
        o = self.options
        self.live = o.get("live")
        if self.live not in (None, "", "spawn", "serve") and not str(self.live).startswith(("rerun://", "rerun+http://", "rerun+https://")):
            raise ValueError(f"option live: {self.live!r} is not 'spawn', 'serve' or a rerun+http:// URL")
        self.per_decade = int(o.get("asd_per_decade", 20))
        self.band = tuple(float(x) for x in (o.get("band") or DEFAULT_BAND))
        self.trends = TrendMonitor(settings=TrendSettings.from_dict(o.get("trends")))
        self.rec = None
        self.rrd: Path | None = None
        self.viewer = None
        self.viewer_url: str | None = None
        self._ltt: dict[int, np.ndarray] = {}
        self._data_asd: dict[int, tuple] = {}
        self._ref: dict[int, dict] = {}
        self._truth: TruthAverager | None = None
        self._model: list | None = None
        self._fit_windows: dict[int, tuple[float, float]] = {}  # fit index -> window drawn
        self._styled: set[str] = set()
        self._truth_source: str | None = None
        self._errors: queue.Queue = queue.Queue()
        self._pending_alerts: list[Alert] = []
        self._last_fit: dict | None = None
        self._ratio: tuple | None = None
        self._drawn: dict[str, set[int]] = {t: set() for t in self.inputs}
        self._tdi_at: dict[int, float] = {}
        self._segment_time: dict[int, tuple[float, float]] = {}
        self.settle_timeout = float(o.get("settle_timeout", 60.0))
        self.trend_spacing = float(o.get("trend_spacing", 3600.0))
        self._trend_t: deque = deque(maxlen=64)  # window ends given to the trends lately

    # ------------------------------------------------------------------ lifecycle
    def setup(self) -> None:
        import rerun as rr

        super().setup()
        self.rrd = rrd_path(self.config.recordings, self.run_id, self.options.get("rrd"))
        recording_id = f"{self.run_id}-{os.getpid()}-{int(time.time())}"
        file_rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        file_rec.set_sinks(rr.FileSink(str(self.rrd)), default_blueprint=views.blueprint(self.band))
        viewer_problem = None
        if self.live in ("spawn", "serve"):
            try:
                self.viewer, self.viewer_url = spawn_viewer(self.live, self.options.get("viewer_port"),
                                                            self.options.get("rerun_binary"))
            except (OSError, RuntimeError) as exc:  # no display, no binary: the file is still written
                viewer_problem = f"live viewer not started: {exc}"
                self.log.warning("%s", viewer_problem)
        elif self.live:
            self.viewer_url = str(self.live)
            if not _reachable(self.viewer_url):
                viewer_problem = f"live viewer {self.viewer_url} not reachable: writing the file only"
                self.log.warning("%s", viewer_problem)
                self.viewer_url = None
        live_rec = None
        if self.viewer_url:  # a stream of its own: a viewer that goes away must not stall the file
            live_rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
            live_rec.set_sinks(rr.GrpcSink(self.viewer_url), default_blueprint=views.blueprint(self.band))
        self.rec = Fanout(file_rec, live_rec, on_live_failure=self._live_failed)
        self.rec.send_recording_name(f"ttl {self.run_id}")
        self._static_styles()
        self.text("log", f"monitor of run {self.run_id} started; recording {self.rrd}"
                  + (f", live viewer {self.viewer_url}" if self.viewer_url else ""))
        if viewer_problem:
            self.text("log", viewer_problem, "WARN")
        self.bus.subscriber(topic_pattern(self.run_id, "errors"), self._on_error)
        self.flush()
        self.log.info("rerun recording %s%s", self.rrd, f", live {self.viewer_url}" if self.viewer_url else "")

    def _live_failed(self, exc) -> None:
        self.log.warning("live viewer %s lost (%s): writing the file only", self.viewer_url, exc)
        self.text("log", f"live viewer {self.viewer_url} lost: {exc}", "WARN")

    def teardown(self) -> None:
        self._drain_errors()
        if self.rec is not None:
            self.text("log", "monitor stopped")
            self.flush()
            self.rec.disconnect()  # writes the file's footer
        if self.viewer is not None and self.live == "serve":
            self.viewer.terminate()  # the headless server; a spawned viewer window stays for the user
            try:
                self.viewer.wait(5)
            except subprocess.TimeoutExpired:
                self.viewer.kill()

    def tick(self):
        self._drain_errors()
        self._settle()
        return ()

    def flush(self) -> None:
        if self.rec is not None:
            self.rec.flush()

    # ------------------------------------------------------------------ inputs
    def expect(self, topic, index):
        arrays = {
            "telemetry": {"ltt": ("<f8", (6, None))},
            "tdi": {"data": ("<f8", (3, None))},
            "fit": {"coefficients": ("<f8", (P,)), "sigma": ("<f8", (P,))},
            "residual": {"residual": ("<f8", (3, None)), "ttl_model": ("<f8", (3, None))},
        }[topic]
        return Expect(run=self.run_id, index=index, arrays=arrays, allow_nonfinite=topic != "fit")

    def handle(self, header, arrays):
        self.note_meta(header.meta)
        topic = header.topic
        try:
            out = getattr(self, f"on_{topic}")(header, arrays)
            self._drawn[topic].add(header.index)
        except Exception:
            if topic == "tdi":
                self.mark_failed(header.index)
            raise
        finally:
            self._drain_errors()
            self.flush()
        self._settle()
        return out

    # ------------------------------------------------------------------ progress
    def _waiting_for(self, i: int, board: dict) -> str | None:
        """What segment ``i`` (its TDI drawn) still waits for before it is done, or None.

        The fit and the residual of ``i`` are waited for only from a fitter / subtractor
        that reports progress, so a skipped or not yet started stage blocks nothing: until
        it has passed ``i``, and then for what it published (the subtractor's residual, the
        fitter's fit if it made one, ``fits`` of its progress).
        """
        for stage, topic, made in (("fitter", "fit", lambda p: p.extra.get("fits", set())),
                                   ("subtractor", "residual", lambda p: p.done)):
            peer = board.get(stage)
            if peer is None:
                continue
            if i in made(peer) and i not in self._drawn[topic]:
                return topic
            if not peer.complete and i not in peer.handled:
                return topic
        return None

    def _settle(self) -> None:
        """Publish the status of every drawn segment that waits for nothing more (or waited
        longer than ``settle_timeout``), mark it done; give up segments upstream gave up."""
        now = time.monotonic()
        board = self.board.snapshot()
        changed = False
        for i in sorted(self._drawn["tdi"] - self.done - self.failed):
            since = self._tdi_at.setdefault(i, now)
            waiting = self._waiting_for(i, board)
            if waiting is not None and now - since < self.settle_timeout:
                continue
            if waiting is not None:
                self.text("log", f"segment {i}: its {waiting} did not come within {self.settle_timeout:g} s", "WARN")
            self.publish(self.status(i))
            self.mark_done(i)  # after the output is out (progress protocol)
            changed = True
        tdi = board.get(self.upstream)
        if tdi is not None:
            for i in sorted(tdi.failed - self.done - self.failed - self._drawn["tdi"]):
                (self.mark_gap if i in tdi.gaps else self.mark_failed)(i)
        self.check_complete()
        if changed:
            self.flush()

    def pending(self) -> int:
        return len(self._drawn["tdi"] - self.done - self.failed)

    def _time(self, t: float, index: int) -> None:
        self.rec.set_time("mission_time", duration=float(t))
        self.rec.set_time("segment", sequence=int(index))

    def text(self, entity: str, message: str, level: str = "INFO") -> None:
        import rerun as rr

        self.rec.log(entity, rr.TextLog(message, level=level))

    def _on_error(self, sample) -> None:  # Zenoh thread: queue, log in the main thread
        try:
            self._errors.put_nowait(bytes(sample.payload.to_bytes()))
        except Exception:
            pass

    def _drain_errors(self) -> None:

        while True:
            try:
                raw = self._errors.get_nowait()
            except queue.Empty:
                return
            try:
                e = json.loads(raw)
                msg = f"error from {e.get('stage')}: {e.get('kind')} segment {e.get('index')}: {e.get('message')}"
            except ValueError:
                msg = f"unreadable error message ({len(raw)} bytes)"
            if self.rec is not None:
                self.text("log", msg, "ERROR")

    # ------------------------------------------------------------------ telemetry
    def on_telemetry(self, header, arrays):
        ltt = arrays["ltt"]
        with np.errstate(all="ignore"):
            mean = np.nanmean(ltt, axis=1)
        if np.all(np.isfinite(mean)):
            self._ltt[header.index] = mean
            self._trim(self._ltt)
        truth = header.meta.get("truth")
        if truth and truth != self._truth_source:
            self._truth_source = truth
            self._time(header.t0, header.index)
            try:
                if isinstance(truth, dict):  # a simulation on the fly: its coefficient model
                    self._truth = ModelTruth(CoefficientModel.from_description(truth["coefficients"]))
                    self.text("log", "simulated on the fly: the simulation's true coefficients drawn beside the fits")
                else:
                    self._truth = TruthAverager(truth, block=float(header.meta.get("segment_duration") or 3600.0))
                    self.text("log", f"truth file {truth}: true coefficients drawn beside the fits")
                self._draw_truth(self._fit_windows)  # fits drawn before the truth was known (a late joiner)
            except Exception as exc:  # a bad truth file must not stop the monitor
                self._truth = None
                self.text("log", f"truth file {truth} unusable: {exc}", "WARN")
                self.report_error("truth", f"{truth}: {exc}", index=header.index)
        return ()

    # ------------------------------------------------------------------ ASDs
    def _ltt_of(self, header) -> np.ndarray:
        v = header.meta.get("ltt_mean")
        if isinstance(v, dict):
            v = [v.get(link) for link in LINKS]
        try:
            arr = np.asarray(v, dtype=float)
            if arr.shape == (6,) and np.all(np.isfinite(arr)):
                return arr
        except (TypeError, ValueError):
            pass
        if header.index in self._ltt:
            return self._ltt[header.index]
        if self._ltt:
            return self._ltt[max(self._ltt)]
        return np.full(6, ARM_LENGTH / C)

    def _curve(self, name: str, f, asd) -> None:
        views.noise_curve(self.rec, name, f, asd, self.band)

    def _references(self, header, f_welch) -> dict:
        ref = self._ref.get(header.index)
        if ref is None:  # once per segment (from its tdi or its residual, whichever comes first)
            ref = reference_curves(f_welch, self._ltt_of(header), self.per_decade)
            self._ref[header.index] = ref
            self._trim(self._ref)
            for name, (f, asd) in ref.items():
                self._curve(name, f, asd)
        return ref

    def on_tdi(self, header, arrays):
        self._segment_time[header.index] = (header.t0, header.fs)
        f, asd, f_welch = x_asd(arrays["data"][0], header.fs, self.per_decade)
        self._time(header.t0, header.index)
        self._curve("data", f, asd)
        self._references(header, f_welch)
        self._data_asd[header.index] = (f, asd)
        self._trim(self._data_asd)
        return ()

    def on_residual(self, header, arrays):
        import rerun as rr

        f, asd, f_welch = x_asd(arrays["residual"][0], header.fs, self.per_decade)
        self._time(header.t0, header.index)
        self._curve("residual", f, asd)
        model = finite_stretch(arrays["ttl_model"][0])
        if model.size >= 64 and np.any(model != 0):
            fm, am, _ = x_asd(model, header.fs, self.per_decade)
            self._curve("ttl_model", fm, am)
        ref = self._references(header, f_welch)
        ratio = band_ratio(f, asd, *ref["expected"], self.band)
        if np.isfinite(ratio) and ratio > 0:
            self.rec.log("adequacy/log10_residual_over_expected", rr.Scalars(math.log10(ratio)))
        self._ratio = (header.index, ratio if math.isfinite(ratio) else None)
        return ()

    # ------------------------------------------------------------------ fits and trends
    def _static_styles(self) -> None:
        views.static_styles(self.rec, self.band)

    def on_fit(self, header, arrays):
        import rerun as rr

        meta = header.meta
        names = tuple(meta.get("names") or COEFFICIENT_NAMES)
        if names != COEFFICIENT_NAMES:
            raise ValueError(f"meta.names: expected the 24 canonical coefficient names, got {list(names)[:3]}...")
        C = arrays["coefficients"]
        S = arrays["sigma"]
        t_start, t_stop = meta.get("t_start"), meta.get("t_stop")
        if not (isinstance(t_start, (int, float)) and isinstance(t_stop, (int, float)) and t_stop > t_start):
            raise ValueError(f"meta t_start/t_stop: the fitted window is needed, got {t_start!r}, {t_stop!r}")
        centre = 0.5 * (t_start + t_stop)
        self._time(centre, header.index)
        views.fit_point(self.rec, C, S)
        self._fit_windows[header.index] = (float(t_start), float(t_stop))
        self._draw_truth({header.index: (t_start, t_stop)})
        chi2 = meta.get("chi2_dof")
        chi2 = float(chi2) if isinstance(chi2, (int, float)) and math.isfinite(chi2) else None
        if chi2 is not None:
            self.rec.log("adequacy/chi2_dof", rr.Scalars(float(chi2)))
        if meta.get("converged") is False:  # the fitter records it in its MCAP too (warnings)
            self.text("alerts", f"fit {header.index}: did not converge", "WARN")
        self.draw_model(header.index, meta)

        # the trend monitor gets at most one fit per trend_spacing of window end (10-min segments
        # give six nearly identical one-day windows an hour): its work per fit stays bounded
        near = [t for t in self._trend_t if abs(t - t_stop) < self.trend_spacing - 1e-6]
        if not near:
            self._trend_t.append(float(t_stop))
            alerts = self.trends.add(header.index, float(t_start), float(t_stop), C, S)
        else:
            alerts = []
        self._time(t_stop, header.index)
        for a in alerts:
            self.text("alerts", a.message, "WARN")
            self.recorder.write_json("alerts", {"run": self.run_id, **a.to_json()}, schema=ALERT_SCHEMA)
            self.log.warning("alert: %s", a.message)
        self._pending_alerts.extend(alerts)
        self._last_fit = {"index": header.index, "chi2_dof": chi2,
                          "t_start": t_start, "t_stop": t_stop}
        return ()

    def _draw_truth(self, windows: dict[int, tuple[float, float]]) -> None:
        """The true coefficients averaged over each fit window, at the fit's time."""

        if self._truth is None:
            return
        for index, (t_start, t_stop) in sorted(windows.items()):
            try:
                truth = self._truth.mean(t_start, t_stop)
            except Exception as exc:
                self.text("log", f"truth file {self._truth.path}: {exc}; no more truth drawn", "WARN")
                self._truth = None
                return
            if truth is None:
                continue
            self._time(0.5 * (t_start + t_stop), index)
            views.truth_point(self.rec, truth)

    def draw_model(self, index: int, meta: dict) -> None:
        """Adequacy against the instrument noise model, model changes and candidates of a fit."""
        import rerun as rr

        model = meta.get("model")
        if isinstance(model, list) and model != self._model:
            if self._model is not None or model != ["linear-ttl"]:
                self.text("model/log", f"fit {index}: model {','.join(map(str, model))}")
            self._model = model
        adequacy = meta.get("adequacy")
        if isinstance(adequacy, dict) and isinstance(adequacy.get("chi2_dof"), (int, float)):
            self.rec.log("adequacy/instrument/chi2_dof", rr.Scalars(float(adequacy["chi2_dof"])))
            for g, band in enumerate(adequacy.get("bands") or ()):
                if isinstance(band, dict) and isinstance(band.get("chi2_dof"), (int, float)):
                    views.band_series(self.rec, g, band, self._styled)
            if adequacy.get("fails"):
                self.text("model/log", f"fit {index}: the model fails against the instrument noise model: "
                                       + "; ".join(map(str, adequacy.get("summary") or ())), "WARN")
        change = meta.get("model_change")
        if isinstance(change, dict):
            def fmt(x):
                return f"{x:.3f}" if isinstance(x, (int, float)) else "?"
            self.text("model/log", f"fit {index}: model {','.join(change.get('before') or ())} -> "
                                   f"{','.join(change.get('after') or ())}: χ²/dof {fmt(change.get('chi2_dof_before'))}"
                                   f" -> {fmt(change.get('chi2_dof_after'))}, Δχ² {fmt(change.get('delta_chi2'))}, "
                                   f"log Bayes factor {fmt(change.get('log_bayes_factor'))}")
            for part in ("before", "after"):
                values = change.get(f"bands_{part}")
                if isinstance(values, list) and values:
                    self.rec.log(f"model/{part}", rr.BarChart(np.array([v if isinstance(v, (int, float)) else np.nan
                                                                         for v in values], dtype=float)))
        candidates = meta.get("candidates")
        if isinstance(candidates, list) and candidates:
            lines = [f"{c.get('effect')}: Δχ² {c.get('delta_chi2', 0):.1f}, log BF {c.get('log_bayes_factor', 0):.1f}"
                     f"{' (significant)' if c.get('significant') else ''}" for c in candidates if isinstance(c, dict)]
            self.text("model/log", f"fit {index}: top candidates: " + "; ".join(lines))
            self.rec.log("model/candidates", rr.BarChart(np.array([float(c.get("delta_chi2") or 0.0)
                                                                   for c in candidates if isinstance(c, dict)])))

    def status(self, index: int) -> Output:
        """The ``monitor/<i>`` message of segment ``i``: trend state and the alerts raised since the last one."""
        est = self.trends.estimates
        rate = np.nan_to_num(est.rate) if est is not None else np.zeros(P)
        sig = np.nan_to_num(est.significance) if est is not None else np.zeros(P)
        alerts, self._pending_alerts = self._pending_alerts, []
        t0, fs = self._segment_time.get(index, (0.0, 1.0))
        meta = {"names": list(COEFFICIENT_NAMES), "alerts": [a.to_json() for a in alerts],
                "drifting": sorted(self.trends.drifting), "drift_windows": est.windows if est else 0,
                "residual_over_expected": {"index": self._ratio[0], "ratio": self._ratio[1]} if self._ratio else None,
                "fit": self._last_fit, "segments_total": self.segments_total}
        return Output(self.output_topic, {"drift_rate": rate, "drift_significance": sig}, index=index,
                      fields={"t0": t0, "fs": fs, "units": {"drift_rate": "mm/rad/day", "drift_significance": ""},
                              "meta": to_jsonable(meta)},
                      summary=to_jsonable({"run": self.run_id, "index": index, **meta,
                                        "drift_rate": rate, "drift_significance": sig}))

    @staticmethod
    def _trim(d: dict, keep: int = 8) -> None:
        while len(d) > keep:
            del d[min(d)]


# ---------------------------------------------------------------------------- entry point

def add_options(p) -> None:
    p.add_argument("--live", help="also stream to a viewer: 'spawn' (start the rerun viewer on 127.0.0.1), "
                                  "'serve' (headless rerun gRPC server on 127.0.0.1) or a rerun+http:// URL")
    p.add_argument("--viewer-port", type=int, help="port of the spawned viewer or server (default: a free one)")
    p.add_argument("--rrd", help="Rerun recording to write (default <recordings>/<run>/monitor.rrd)")


def options(args) -> dict:
    return {"live": args.live, "viewer_port": args.viewer_port, "rrd": args.rrd}


def check(config) -> str:
    m = Monitor(config)
    return (f"monitor of run {config.run}: recording {Path(config.recordings) / config.run / 'monitor.rrd'}, "
            f"live {m.live or 'off'}, band {m.band}, trends {m.trends.settings}")


def main(argv=None) -> int:
    return stage_main(Monitor, argv, add_options, options, check)


if __name__ == "__main__":
    sys.exit(main())

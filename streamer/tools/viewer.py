"""Rerun viewer processes, on 127.0.0.1 only: the binary, a spawned viewer or headless
server, and a live stream that a lost viewer cannot stall.

The monitor (``stages/monitor/monitor.py``) writes its recording to a file and, on request, streams
it live as well (:class:`LiveFanout`): to a native viewer it starts (``"spawn"``: the window
outlives the monitor), to a headless gRPC server it starts (``"serve"``: stopped with the
monitor; a viewer connects later with ``rerun --connect rerun+http://127.0.0.1:<port>/proxy``),
or to a viewer already running at a ``rerun+http://`` URL.  The SDK's own web-viewer server
(which listens on every interface) is never used; ``ttl view --web`` is
:mod:`streamer.tools.webview`.
"""

from __future__ import annotations

import datetime
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from urllib.parse import urlparse

from ..bus.session import LOOPBACK, free_port
from ..runtime.processes import tied_to_parent, wait_port

#: Live modes that start a ``rerun`` process (else a ``rerun+http://`` URL is expected).
SPAWN_MODES = ("spawn", "serve")


def rerun_binary(explicit: str | None = None) -> str:
    """The ``rerun`` executable itself (not the pip wrapper script, which would leave it
    orphaned when stopped): ``explicit``, ``$RERUN_CLI_PATH``, the one bundled with
    rerun-sdk (``rerun_cli``), else ``rerun`` on PATH.

    Raises
    ------
    FileNotFoundError
        If there is none.
    """
    if explicit:
        return str(explicit)
    if os.environ.get("RERUN_CLI_PATH"):
        return os.environ["RERUN_CLI_PATH"]
    try:
        import rerun_cli

        base = Path(rerun_cli.__file__).parent
        for candidate in (base / "Rerun.app" / "Contents" / "MacOS" / "Rerun", base / "rerun", base / "rerun.exe"):
            if candidate.exists():
                return str(candidate)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if not found:
        raise FileNotFoundError("rerun: the Rerun viewer binary is not installed (pip install rerun-sdk)")
    return found


def no_display() -> str | None:
    """Why a native viewer cannot open a window here, or None: on Linux and the other X11 /
    Wayland systems, neither ``DISPLAY`` nor ``WAYLAND_DISPLAY`` (nor ``WAYLAND_SOCKET``) is
    set (macOS and Windows always have a display)."""
    if sys.platform in ("darwin", "win32"):
        return None
    if any(os.environ.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")):
        return None
    return "neither DISPLAY nor WAYLAND_DISPLAY is set"


_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def run_native_viewer(cmd: list[str]) -> tuple[int, str]:
    """Run the native viewer ``cmd`` until it is closed; returns ``(exit status, the last
    line of its log)``, the line without colours or Rust source paths.  Its log (stderr, Rust's
    coloured lines) is kept from the terminal: a failure is said in one line by the caller."""
    with tempfile.TemporaryFile() as log, subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stderr=log) as proc:
        try:
            code = proc.wait()
        except BaseException:  # Ctrl-C: the viewer goes too
            proc.kill()
            raise
        log.seek(0)
        lines = [ln for ln in _ANSI.sub("", log.read().decode(errors="replace")).splitlines() if ln.strip()]
    last = re.sub(r"\s+at\s+\S+\.rs:\d+(:\d+)?:?", ":", lines[-1]).strip() if lines else ""
    return code, last[:300]


def check_live(live) -> None:
    """Raise ValueError unless ``live`` is empty, ``"spawn"``, ``"serve"`` or a Rerun URL."""
    if live not in (None, "", *SPAWN_MODES) and not str(live).startswith(
        ("rerun://", "rerun+http://", "rerun+https://")
    ):
        raise ValueError(f"option live: {live!r} is not 'spawn', 'serve' or a rerun+http:// URL")


def reachable(url: str, timeout: float = 1.0) -> bool:
    """Whether something listens at the host and port of a ``rerun+http://host:port/proxy`` URL."""
    u = urlparse(url.replace("rerun+", "", 1).replace("rerun://", "https://", 1))
    port = u.port or (443 if u.scheme == "https" else 9876)
    try:
        with socket.create_connection((u.hostname or LOOPBACK, port), timeout=timeout):
            return True
    except OSError:
        return False


def spawn_viewer(mode: str, port: int | None = None, binary: str | None = None):
    """Start the ``rerun`` binary on 127.0.0.1 only; returns ``(process, url)``.

    ``mode`` ``"spawn"``: the native viewer (which serves gRPC on ``port``), in a session of
    its own so that its window outlives the caller; ``"serve"``: a headless gRPC server that
    viewers connect to later, which dies with the caller.

    Raises
    ------
    RuntimeError
        If it does not listen within 10 s (no display, for a native viewer).
    """
    port = int(port or free_port(LOOPBACK))
    cmd = [rerun_binary(binary), "--bind", LOOPBACK, "--port", str(port)]
    cmd += ["--serve-grpc"] if mode == "serve" else ["--expect-data-soon"]
    proc = subprocess.Popen(
        cmd,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
        preexec_fn=tied_to_parent(signal.SIGTERM) if mode == "serve" else None,
    )
    if not wait_port(port, proc=proc):
        code = proc.poll()
        if code is None:
            proc.terminate()
        raise RuntimeError(
            f"{cmd[0]}: the Rerun viewer did not listen on {LOOPBACK}:{port}"
            + (f" (exited with status {code}; no display?)" if code is not None else " within 10 s")
        )
    return proc, f"rerun+http://{LOOPBACK}:{port}/proxy"


def start_live(live, port: int | None = None, binary: str | None = None):
    """The live viewer of option ``live`` (:func:`check_live`): ``(process, url, problem)``.

    ``"spawn"``/``"serve"`` start one (:func:`spawn_viewer`); a URL is used if something
    listens there.  When that fails (no display, no binary, nothing listening), ``url`` is
    None and ``problem`` says why: the caller goes on with its file alone.
    """
    if not live:
        return None, None, None
    if live in SPAWN_MODES:
        try:
            proc, url = spawn_viewer(live, port, binary)
        except (OSError, RuntimeError) as exc:
            return None, None, f"live viewer not started: {exc}"
        return proc, url, None
    if not reachable(str(live)):
        return None, None, f"live viewer {live} not reachable: writing the file only"
    return None, str(live), None


#: Wall-clock time for which the file stream gathers rows before it writes them as chunks
#: (one chunk per entity and batch, not one per logged row). What a killed monitor loses
#: at most; every stage's MCAP file keeps what the monitor was drawing from.
FILE_BATCH_SECONDS = 60.0


def file_batcher(seconds: float = FILE_BATCH_SECONDS):
    """The chunk batcher of a recording file: rows gathered for ``seconds`` of wall clock
    (or 8 MiB, or 65536 rows), then written as one chunk per entity.

    Rerun's default (a chunk every 200 ms, or at every ``flush``) wrote one-row chunks:
    7,722 of them for a 3-day monitor run, which the web viewer ingested at about 2 hours of
    mission time a minute.
    """
    import rerun as rr  # the viewer's SDK, loaded by the processes that draw only

    return rr.ChunkBatcherConfig(
        flush_tick=datetime.timedelta(seconds=float(seconds)), flush_num_bytes=8 << 20, flush_num_rows=65536
    )


def compact_rrd(rrd: Path, binary: str | None = None, timeout: float = 300.0) -> str | None:
    """Rewrite the closed recording ``rrd`` with its chunks merged (``rerun rrd optimize``:
    one chunk per entity as far as the size limits allow, and a footer); returns None, or
    why the file was left as it was.

    Batching bounds the chunks by the wall-clock time a run takes; a run whose segments come
    slower than a batch (real time: an hour a segment) still writes a chunk per entity and
    segment.  Merged, a week of 1-h segments is a few hundred chunks whatever the pace
    (~1 s for a week's file).  The file is replaced atomically, only once the merged copy is
    whole; a failure leaves the original, which is complete and has its footer.
    """
    rrd = Path(rrd)
    tmp = rrd.with_name(rrd.name + ".optimizing")
    try:
        cmd = [rerun_binary(binary), "rrd", "optimize", str(rrd), "-o", str(tmp)]
        done = subprocess.run(cmd, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=timeout)
        if done.returncode != 0 or not tmp.exists() or tmp.stat().st_size == 0:
            last = (done.stderr or done.stdout).strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
            return f"rerun rrd optimize failed: {last[0]}"
        os.replace(tmp, rrd)
        return None
    except (OSError, subprocess.SubprocessError) as exc:
        return f"rerun rrd optimize: {exc}"
    finally:
        tmp.unlink(missing_ok=True)


class LiveFanout:
    """Logs to the file recording and, while it works, to a live viewer's recording.

    Both are Rerun recording streams (``rerun.RecordingStream``).  The file stream batches
    its rows (:func:`file_batcher`) and writes an RRD footer when closed
    (:meth:`disconnect`); the live stream is flushed at every :meth:`flush` with a short
    timeout, and when it fails (the viewer closed or unreachable) it is dropped, so a lost
    viewer never stalls the caller or the file.
    """

    def __init__(self, file_rec, live_rec=None, on_live_failure=None, live_timeout: float = 2.0):
        self.file = file_rec
        self.live = live_rec
        self.on_live_failure = on_live_failure
        self.live_timeout = live_timeout
        self.closed = False

    @classmethod
    def open(
        cls,
        application_id: str,
        recording_id: str,
        rrd: Path,
        url: str | None = None,
        blueprint=None,
        on_live_failure=None,
        batch_seconds: float = FILE_BATCH_SECONDS,
    ) -> LiveFanout:
        """A recording written to ``rrd`` and, when ``url`` is given, streamed to the viewer
        there as a stream of its own (both with the default ``blueprint``).

        The file's rows are gathered for ``batch_seconds`` and written as one chunk per entity
        (:func:`file_batcher`), and the file ends with an RRD footer (a manifest of its chunks,
        which lets a viewer open it without a scan) written by :meth:`disconnect`.  The sink
        keeps that manifest in memory until then, ~0.3 kB per chunk: batching keeps it small
        (a 7-day run of 1-h segments replayed at full speed: a few hundred chunks; replayed in
        real time, about one chunk per drawn entity and segment, ~15 kB per segment).  A file
        whose writer was killed has no footer and lacks the last batch; the viewer and
        ``rerun.chunk.RrdReader(...).stream()`` still read it whole.
        """
        import rerun as rr

        file_rec = rr.RecordingStream(
            application_id, recording_id=recording_id, batcher_config=file_batcher(batch_seconds)
        )
        file_rec.set_sinks(rr.FileSink(str(rrd), write_footer=True), default_blueprint=blueprint)
        live_rec = None
        if url:  # a stream of its own: a viewer that goes away must not stall the file
            live_rec = rr.RecordingStream(application_id, recording_id=recording_id)
            live_rec.set_sinks(rr.GrpcSink(url), default_blueprint=blueprint)
        return cls(file_rec, live_rec, on_live_failure=on_live_failure)

    def _both(self, name, *args, **kwargs):
        getattr(self.file, name)(*args, **kwargs)
        if self.live is not None:
            getattr(self.live, name)(*args, **kwargs)

    def log(self, *args, **kwargs):
        self._both("log", *args, **kwargs)

    def send_columns(self, *args, **kwargs):
        self._both("send_columns", *args, **kwargs)

    def set_time(self, *args, **kwargs):
        self._both("set_time", *args, **kwargs)

    def send_recording_name(self, name: str):
        self._both("send_recording_name", name)

    def flush(self) -> None:
        """Send what was logged to the live viewer now.  The file is left to its batcher:
        flushing it here would write a chunk per entity and message again."""
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
        """Write the last batch and the footer, close the file; let the live viewer go.
        Idempotent (the monitor calls it on every way out)."""
        if self.closed:
            return
        self.closed = True
        self.file.flush()
        self.file.disconnect()  # closes the file sink: the RRD footer is written here
        if self.live is not None:
            try:
                self.live.flush(timeout_sec=self.live_timeout)
            except RuntimeError:
                pass
            self.live.disconnect()

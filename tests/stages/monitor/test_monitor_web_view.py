"""The monitor's Rerun recording opened by Rerun's web viewer in a headless browser.

A monitor stage process (the real one) draws a recording from crafted messages published on
a loopback Zenoh session the way the pipeline stages publish them: 1-h segments of
telemetry, TDI and residual, and rolling one-day fits whose coefficients step on one
coefficient and drift on another (so that the monitor's trend monitor raises its alerts),
with the fitter's adequacy per band and a diagnosis in their meta.  ``ttl view --web``
serves the recording on 127.0.0.1; headless Chromium (driven over the DevTools protocol)
opens it, and the frames it draws are followed (its screencast) until the view is complete:
the time cursor, which follows the data, reads the recording's last mission time, and a
screenshot shows what the last frame drew (:func:`open_in_browser`).
The complete screenshot must show the ASD curves (their colours in the noise panel), every
alert the monitor raised and the last segment in the run summary (read with tesseract).

* ``test_web_viewer_shows_the_monitor_recording`` (``make test``): 36 segments; the load
  time and Chromium's CPU seconds to it (:func:`process_tree_cpu`: less sensitive than the
  wall clock to what else runs) are measured and printed, not judged (a loaded machine must
  not fail it).
* ``test_a_week_of_monitor_recording_opens_in_seconds`` (``-m science``): 168 segments,
  7 days: the content checks always, and it must open in under 10 s (``WEEK_LOAD_LIMIT``)
  when the machine is quiet (1-min load average at most ``QUIET_LOAD`` before the open;
  otherwise the time is printed and the test skipped with it).

Skipped with a message when Chromium or tesseract is not installed
(``apt-get install -y chromium tesseract-ocr``).  Set ``TTL_SCREENSHOT_DIR`` to keep the
frames (JPEG, named by their time) and the final screenshot for a look.
"""

from __future__ import annotations

import base64
import io
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from ttl_testutil import finish, output, start_monitor_stage, wait_alive, wait_for  # noqa: F401  (also puts the project first on sys.path)

from streamer.bus.codec import decode, encode
from streamer.bus.keys import control_key, topic_pattern
from streamer.bus.session import Bus, SessionSettings, free_port
from streamer.recording.recorder import read_recording
from streamer.runtime.processes import stop_process
from ttlcore.conventions import COEFFICIENT_NAMES, C
from ttlcore.io.truth import CORE_DATASETS, TruthWriter

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
TESSERACT = shutil.which("tesseract")
needs_browser = pytest.mark.skipif(
    CHROMIUM is None or TESSERACT is None,
    reason="chromium or tesseract not installed (apt-get install -y chromium tesseract-ocr): "
    "no headless rendering of the Rerun web viewer to check",
)
WIDTH, HEIGHT = 1920, 1080
#: The acceptance target of a 7-day recording of 1-h segments [s] (issue 21).
WEEK_LOAD_LIMIT = 10.0

RUN = "web-view"
HOUR = 3600.0
DAY = 86400.0
FS = 4.0
STEP_COEF, DRIFT_COEF = "23.phi.tx", "12.phi.rx"
STEP = 0.3e-3  # [m/rad]
DRIFT = 0.05e-3  # [m/rad/day]
SIGMA = 0.01e-3  # uncertainty of a one-day window's coefficient [m/rad]
TRUTH_FS = 1 / 60.0
BANDS = np.geomspace(3e-3, 0.9, 7)  # six adequacy bands


# ---------------------------------------------------------------------------- the recording


def truth_coefficients(t, step_at: float) -> np.ndarray:
    """True coefficients [m/rad] at times ``t`` [s] (24, n): paper-like constants, a drift
    on ``DRIFT_COEF`` and a step on ``STEP_COEF`` at ``step_at``."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    base = (2.3e-3 + np.linspace(-0.1e-3, 0.1e-3, 24))[:, None] * np.ones(t.size)
    base[COEFFICIENT_NAMES.index(DRIFT_COEF)] += DRIFT * t / DAY
    base[COEFFICIENT_NAMES.index(STEP_COEF)] += STEP * (t >= step_at)
    return base


def write_truth(path: Path, segments: int, step_at: float) -> Path:
    size = int(segments * HOUR * TRUTH_FS)
    t = np.arange(size) / TRUTH_FS
    w = TruthWriter(path, t0=0.0, fs=TRUTH_FS, size=size, config={"test": True})
    for name, (rows, _) in CORE_DATASETS.items():
        w.append(name, truth_coefficients(t, step_at) if name == "coefficients" else np.zeros((len(rows), size)))
    return w.close()


class WeekDriver:
    """Publishes a run's segments to a monitor: what the replayer, TDI builder, fitter and
    subtractor would publish, with made-up but plausible numbers."""

    def __init__(self, tmp: Path, segments: int, step_at: float):
        self.segments, self.step_at = segments, step_at
        self.port = free_port()
        self.bus = Bus.open(SessionSettings(listen=(f"tcp/127.0.0.1:{self.port}",)))
        self.pubs = {t: self.bus.segment_publisher(RUN, t, cache=16) for t in ("telemetry", "tdi", "fit", "residual")}
        self.statuses: list[int] = []
        self.bus.segment_subscriber(
            topic_pattern(RUN, "monitor"),
            lambda s: self.statuses.append(
                decode(s.payload.to_bytes(), s.attachment.to_bytes(), key=str(s.key_expr))[0].index
            ),
            history=0,
        )
        self.truth = write_truth(tmp / "week.truth.h5", segments + 1, step_at)
        self.rng = np.random.default_rng(21)
        n = int(HOUR * FS)
        self.n = n
        # one-hour estimates of the coefficients (truth averaged over the hour, plus noise)
        hours = np.arange(segments)
        self.hourly = np.array(
            [truth_coefficients(h * HOUR + np.arange(0, HOUR, 60.0), step_at).mean(axis=1) for h in hours]
        ) + self.rng.normal(0.0, SIGMA * math.sqrt(24), (segments, 24))

    def _message(self, topic, index, arrays, meta, t0, fs=FS):
        fields = {"run": RUN, "index": index, "t0": t0, "fs": fs, "producer": "driver", "meta": meta}
        if topic in ("tdi", "residual"):
            fields.update(channels=["X2", "Y2", "Z2"], channel_axis=0)
        return encode(arrays, fields, allow_nonfinite=True)

    def segment(self, i: int) -> None:
        t0, n = i * HOUR, self.n
        common = {"segments_total": self.segments}
        ltt = np.full((6, n), 2.5e9 / C) + np.arange(6)[:, None] * 1e-3
        self.pubs["telemetry"].put(
            i,
            *self._message(
                "telemetry",
                i,
                {"ltt": ltt},
                {**common, "source": "test", "truth": str(self.truth), "segment_duration": HOUR},
                t0,
            ),
        )
        self.fit(i)
        white = self.rng.normal(0.0, 1e-21, (3, n))
        ttl = np.cumsum(self.rng.normal(0.0, 1e-22, (3, n)), axis=1)
        data = white + ttl
        self.pubs["tdi"].put(
            i,
            *self._message(
                "tdi", i, {"data": data}, {**common, "names": list(COEFFICIENT_NAMES), "ltt_mean": [2.5e9 / C] * 6}, t0
            ),
        )
        self.pubs["residual"].put(
            i, *self._message("residual", i, {"residual": white, "ttl_model": ttl}, {**common, "fit_index": i}, t0)
        )

    def fit(self, k: int) -> None:
        """The rolling one-day fit ending with segment ``k``, its adequacy per band and, once
        the step is in its window, a diagnosis."""
        a = max(0, k - 23)
        t_start, t_stop = a * HOUR, (k + 1) * HOUR
        coefficients = self.hourly[a : k + 1].mean(axis=0)
        sigma = np.full(24, SIGMA * math.sqrt(24 / (k + 1 - a)))
        stepped = t_start < self.step_at < t_stop
        bands = [
            {
                "f_lo": float(lo),
                "f_hi": float(hi),
                "p_value": 0.5,
                "fails": False,
                "chi2_dof": float(1.0 + 0.02 * self.rng.standard_normal() + (0.3 if stepped and g == 0 else 0.0)),
            }
            for g, (lo, hi) in enumerate(zip(BANDS[:-1], BANDS[1:]))
        ]
        meta = {
            "names": list(COEFFICIENT_NAMES),
            "chi2_dof": float(1.0 + 0.01 * self.rng.standard_normal()),
            "t_start": t_start,
            "t_stop": t_stop,
            "segments": k + 1 - a,
            "band": [3e-3, 0.9],
            "converged": True,
            "model": ["linear-ttl"],
            "adequacy": {
                "chi2_dof": float(np.mean([b["chi2_dof"] for b in bands])),
                "fails": stepped,
                "summary": [],
                "bands": bands,
            },
        }
        if stepped:
            meta["diagnosis"] = {
                "text": (
                    f"The residual exceeds the instrument noise model in the lowest band since "
                    f"{self.step_at / DAY:.2f} d; a step in {STEP_COEF} explains it best."
                ),
                "recommendation": {"spec": f"step:t_step={self.step_at / DAY:.2f}d"},
            }
        arrays = {"coefficients": coefficients, "sigma": sigma, "covariance": np.diag(sigma**2)}
        self.pubs["fit"].put(k, *self._message("fit", k, arrays, meta, t_stop - HOUR, 1 / HOUR))

    def close(self) -> None:
        self.bus.close()


def monitor_recording(procs, tmp: Path, segments: int, step_at: float) -> tuple[Path, list[dict]]:
    """A monitor stage process draws ``segments`` 1-h segments; returns its ``monitor.rrd``
    and the alerts it raised (from its MCAP file)."""
    driver = WeekDriver(tmp, segments, step_at)
    try:
        proc = start_monitor_stage(procs, RUN, driver.port, tmp, history=16)
        wait_alive(driver.bus, RUN, "monitor", proc, 60)
        assert proc.poll() is None, output(proc)
        started = time.monotonic()
        for i in range(segments):
            driver.segment(i)
            # at most four segments ahead of the monitor, like the replayer
            wait_for(
                lambda i=i: len(driver.statuses) >= i - 3 or proc.poll() is not None, 120, f"segment {i - 3} drawn"
            )
            assert proc.poll() is None, output(proc)
        wait_for(lambda: len(set(driver.statuses)) >= segments, 120, "every segment drawn")
        mcap = tmp / "rec" / RUN / "monitor.mcap"
        wait_for(lambda: len(read_recording(mcap).segments("fit")) >= segments, 60, "every fit drawn")
        print(f"monitor drew {segments} segments in {time.monotonic() - started:.1f} s")
        driver.bus.session.put(control_key(RUN, "stop"), b"")
        assert finish(proc, 60) == 0, output(proc)
    finally:
        driver.close()
    return tmp / "rec" / RUN / "monitor.rrd", read_recording(mcap).json("alerts")


def last_mission_time(rrd: Path) -> float:
    """The largest mission time [s] of the recording (where the viewer's cursor ends)."""
    from rerun.chunk import RrdReader

    last = 0.0
    for chunk in RrdReader(rrd).stream():
        rb = chunk.to_record_batch()
        if "mission_time" in rb.schema.names:
            last = max(last, max(v.total_seconds() for v in rb.column("mission_time").to_pylist() if v is not None))
    return last


def rrd_stats(rrd: Path) -> dict:
    """Chunk count and footer of a recording, from ``rerun rrd stats`` and ``rerun rrd verify``."""
    from streamer.tools.viewer import rerun_binary

    stats = subprocess.run([rerun_binary(), "rrd", "stats", str(rrd)], capture_output=True, text=True, timeout=120)
    verify = subprocess.run([rerun_binary(), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    chunks = re.search(r"num_chunks = ([\d\s]+)\n", stats.stdout)
    return {
        "chunks": int(re.sub(r"\s", "", chunks.group(1))) if chunks else None,
        "footer": "Missing RRD footer" not in verify.stdout + verify.stderr,
        "verify_rc": verify.returncode,
        "bytes": rrd.stat().st_size,
    }


# ---------------------------------------------------------------------------- the browser


class DevTools:
    """A headless Chromium driven over the DevTools protocol (websocket-client)."""

    def __init__(self, tmp: Path):
        import websocket

        port = free_port()
        self.proc = subprocess.Popen(
            [
                CHROMIUM,
                "--headless=new",
                "--no-sandbox",
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                f"--window-size={WIDTH},{HEIGHT}",
                # frames as in a browser on a desk: a headless page is otherwise treated as hidden
                # and its animation frames throttled, and the viewer then ingests only when
                # something (a screenshot, an input event) asks for a frame
                "--disable-background-timer-throttling",
                "--disable-renderer-backgrounding",
                "--disable-backgrounding-occluded-windows",
                f"--remote-debugging-port={port}",
                "--remote-debugging-address=127.0.0.1",
                f"--user-data-dir={tmp / 'chromium-profile'}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + 60
        pages = []
        while time.monotonic() < deadline and not pages:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=2) as r:
                    pages = [p for p in json.load(r) if p.get("type") == "page"]
            except OSError:
                time.sleep(0.3)
        if not pages:
            self.close()
            raise RuntimeError("chromium's DevTools endpoint did not come up")
        self.ws = websocket.create_connection(pages[0]["webSocketDebuggerUrl"], timeout=60, suppress_origin=True)
        self._id = 0
        self.events: list[dict] = []

    def call(self, method: str, **params) -> dict:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            if "method" in msg:  # an event that came before the answer: kept for :meth:`event`
                self.events.append(msg)

    def event(self, timeout: float) -> dict | None:
        """The next event the page sends (``{"method": ..., "params": ...}``), or None when
        none comes within ``timeout`` seconds."""
        import websocket

        if self.events:
            return self.events.pop(0)
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            self.ws.settimeout(left)
            try:
                msg = json.loads(self.ws.recv())
            except websocket.WebSocketTimeoutException:
                break
            finally:
                self.ws.settimeout(60)
            if "method" in msg:
                return msg
        return None

    def screenshot(self) -> bytes:
        return base64.b64decode(self.settled("Page.captureScreenshot", format="png")["data"])

    def settled(self, method: str, **params) -> dict:
        """:meth:`call`, retried while the page is between renderer processes (right after a
        navigation away from about:blank, Chromium answers "Not attached to an active page")."""
        for _ in range(40):
            try:
                return self.call(method, **params)
            except RuntimeError as exc:
                if "Not attached to an active page" not in str(exc):
                    raise
                time.sleep(0.5)
        return self.call(method, **params)

    def close(self) -> None:
        try:
            self.ws.close()
        except Exception:
            pass
        stop_process(self.proc)


def process_tree_cpu(pid: int) -> float:
    """CPU seconds (user + system) used so far by process ``pid`` and its descendants, from
    /proc: their own times and those of their children already reaped (0.0 without /proc)."""
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    stats = {}
    for d in Path("/proc").glob("[0-9]*"):
        try:
            fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        # after the name: state ppid ... utime(12) stime(13) cutime(14) cstime(15), 0-based from state
        stats[int(d.name)] = (int(fields[1]), sum(int(x) for x in fields[11:15]))
    tree, grew = {pid}, True
    while grew:
        grew = False
        for p, (ppid, _) in stats.items():
            if ppid in tree and p not in tree:
                tree.add(p)
                grew = True
    return sum(stats[p][1] for p in tree) / tick


def pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)


def ocr(img: np.ndarray, box: tuple[float, float, float, float], scale: int = 2, psm: int = 6) -> str:
    """Text in ``box`` (fractions of the width and height: x0, y0, x1, y1) of a screenshot."""
    from PIL import Image

    h, w = img.shape[:2]
    x0, y0, x1, y1 = int(box[0] * w), int(box[1] * h), int(box[2] * w), int(box[3] * h)
    crop = Image.fromarray(img[y0:y1, x0:x1].astype(np.uint8)).convert("L")
    crop = crop.resize((crop.width * scale, crop.height * scale), Image.LANCZOS)
    buf = io.BytesIO()
    crop.save(buf, format="PNG")
    done = subprocess.run(
        [TESSERACT, "stdin", "stdout", "--psm", str(psm)], input=buf.getvalue(), capture_output=True, timeout=60
    )
    return done.stdout.decode(errors="replace")


#: Where the views are on a 1920x1080 screenshot (fractions; the blueprint's shares in
#: :func:`stages.monitor.views.blueprint`, with some margin).
TIME_FIELD = (0.86, 1 - 34 / HEIGHT, 1.0, 1.0)  # the time panel's current time, bottom right
NOISE_PANEL = (0.0, 0.05, 0.49, 0.66)
COEFFICIENT_GRID = (0.5, 0.04, 1.0, 0.70)  # 4 columns of plots
SUMMARY_PANEL = (0.5, 0.73, 0.75, 0.97)


def time_shown(img: np.ndarray) -> int | None:
    """The mission time [s] the viewer's time cursor is at (``+601 200s``), or None."""
    digits = re.sub(r"\D", "", ocr(img, TIME_FIELD, scale=3, psm=7))
    return int(digits) if digits else None


#: Seconds without a new frame from the page after which the view is checked for completeness.
QUIET = 4.0


def open_in_browser(rrd: Path, tmp: Path, last_time: float, timeout: float):
    """Open ``rrd`` with ``ttl view --web`` in headless Chromium and follow the frames the
    page draws until the view is complete; returns ``(seconds to complete, final screenshot
    png, frames drawn, Chromium's CPU seconds by then)``, the seconds None when it did not complete within ``timeout``.

    The frames come from the browser's screencast: a JPEG of each frame the compositor
    draws, sent as it is drawn, which costs the page nothing it would not do anyway.  (A
    screenshot makes the page draw a frame of its own: ~2 s of CPU each, in software at
    1920x1080; polled every few seconds they slowed the load they measured and resolved its
    time no finer than their own.)  When no frame has come for ``QUIET`` seconds, a
    screenshot checks the view: complete when the time cursor reads the recording's last
    mission time and the screenshot shows what the last frame showed; otherwise the
    pointer is moved over the top bar (which makes the viewer draw a frame) and the frames
    are followed on.  The load time is that of the first frame identical to the last one:
    the view was complete then."""
    web_port = free_port()
    view = subprocess.Popen(
        [str(Path(sys.executable).with_name("ttl")), "view", "--web", "--port", str(web_port), str(rrd)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=Path(__file__).resolve().parents[3],
    )
    browser = None
    try:
        line = view.stdout.readline()
        assert "http://127.0.0.1:" in line, line
        url = line.split(": ", 1)[1].split()[0]
        assert url.startswith(f"http://127.0.0.1:{web_port}/")
        browser = DevTools(tmp)
        browser.call("Page.enable")
        browser.call(
            "Emulation.setDeviceMetricsOverride", width=WIDTH, height=HEIGHT, deviceScaleFactor=1, mobile=False
        )
        browser.call("Emulation.setFocusEmulationEnabled", enabled=True)
        browser.call("Page.startScreencast", format="jpeg", quality=90, everyNthFrame=1)
        frames, cpu, checks, final = _follow_frames(browser, url, rrd.stem, int(round(last_time)), timeout)
        browser.call("Page.stopScreencast")
        last = pixels(frames[-1][1]) if frames else None
        k = next((k for k, (_, data) in enumerate(frames) if same(pixels(data), last)), None) if final else None
        first, first_cpu = (frames[k][0], cpu[k]) if k is not None else (None, None)
        print(
            f"{len(frames)} frames drawn at (s): {[round(t, 1) for t, _ in frames]}; "
            f"Chromium CPU (s) by then: {[round(c, 1) for c in cpu]}; "
            f"checks (s, time cursor, difference to the last frame): {checks}"
        )
        if final is None:
            final = browser.screenshot()
        return first, final, len(frames), first_cpu
    finally:
        if browser is not None:
            browser.close()
        view.send_signal(signal.SIGINT)  # ttl view stops its rerun server
        try:
            view.wait(10)
        except subprocess.TimeoutExpired:
            view.kill()
            view.wait(10)


def _follow_frames(browser, url: str, stem: str, target: int, timeout: float):
    """Navigate ``browser`` to ``url`` and follow the frames the page draws until the view
    is complete (:func:`open_in_browser`): the time cursor at ``target`` [s] and a
    screenshot showing what the last frame showed, at most ``timeout`` [s].

    Returns the frames ``(seconds since the navigation, JPEG)``, Chromium's CPU seconds at
    each, the checks made ``(s, time cursor, difference to the last frame)`` and the final
    screenshot (None when the view did not complete)."""
    cpu0, cpu = process_tree_cpu(browser.proc.pid), []
    start = time.monotonic()
    browser.call("Page.navigate", url=url)
    frames: list[tuple[float, bytes]] = []
    checks: list[tuple[float, int | None, float]] = []
    final = None
    while time.monotonic() - start < timeout and final is None:
        ev = browser.event(QUIET)
        if ev is not None:
            if ev.get("method") == "Page.screencastFrame":
                params = ev["params"]
                browser.settled("Page.screencastFrameAck", sessionId=params["sessionId"])
                frames.append((time.monotonic() - start, base64.b64decode(params["data"])))
                cpu.append(process_tree_cpu(browser.proc.pid) - cpu0)
                keep(f"{stem}-{frames[-1][0]:05.1f}s.jpg", frames[-1][1])  # how the view fills in
            continue
        if not frames:
            continue
        png = browser.screenshot()
        img = pixels(png)
        shown, differs = time_shown(img), float(np.abs(img - pixels(frames[-1][1])).mean())
        checks.append((round(time.monotonic() - start, 1), shown, round(differs, 2)))
        if shown == target and differs < JPEG_SAME:
            final = png
        else:  # not complete: a frame asked for, and the frames followed on
            browser.settled("Input.dispatchMouseEvent", type="mouseMoved", x=WIDTH // 2 + len(checks) % 2, y=4)
    return frames, cpu, checks, final


#: Mean grey-level difference below which a screenshot and a JPEG screencast frame show the
#: same view (the JPEG's loss: 1.26 measured on the complete view; a view still filling in
#: differs from the complete one by 1.5 or more). Frames are compared with each other with
#: :func:`same`'s own tolerance: the same view gives the same JPEG.
JPEG_SAME = 2.0


def same(a: np.ndarray, b: np.ndarray, tol: float = 0.3) -> bool:
    """Two images show the same (the mean grey-level difference is below ``tol``)."""
    return a.shape == b.shape and float(np.abs(a - b).mean()) < tol


def colour_pixels(img: np.ndarray, box, rgb, tol: float = 40.0) -> int:
    """Pixels within ``tol`` (per channel) of ``rgb`` in ``box`` (fractions)."""
    h, w = img.shape[:2]
    region = img[int(box[1] * h) : int(box[3] * h), int(box[0] * w) : int(box[2] * w)]
    return int((np.abs(region - np.asarray(rgb, dtype=float)).max(axis=2) < tol).sum())


def keep(name: str, png: bytes) -> None:
    where = os.environ.get("TTL_SCREENSHOT_DIR")
    if where:
        Path(where).mkdir(parents=True, exist_ok=True)
        (Path(where) / name).write_bytes(png)


def check_screenshot(png: bytes, alerts: list[dict], segments: int) -> str:
    """What must be visible: the ASD curves, the last segment and every alert; returns the
    run summary's text as read."""
    from stages.monitor.views import CURVES

    img = pixels(png)
    assert img.shape[:2] == (HEIGHT, WIDTH)
    # a curve is a line across the panel, ~3 px wide: far more pixels than its legend marker (~80)
    for name in ("data", "residual", "requirement"):
        n = colour_pixels(img, NOISE_PANEL, CURVES[name][1])
        assert n > 400, f"the {CURVES[name][0]} curve is not drawn in the noise panel ({n} pixels of its colour)"
    # the fits drawn over the time range: in every column of coefficient plots, from the left
    # of the x axis to past its middle (a fit is drawn at the centre of its one-day window, so
    # the lines end half a day before the axis does)
    from stages.monitor.views import FIT_COLOR

    x0, y0, x1, y1 = COEFFICIENT_GRID
    cell = (x1 - x0) / 4
    for c in range(4):
        left = colour_pixels(img, (x0 + c * cell + 0.10 * cell, y0, x0 + c * cell + 0.25 * cell, y1), FIT_COLOR)
        mid = colour_pixels(img, (x0 + c * cell + 0.50 * cell, y0, x0 + c * cell + 0.70 * cell, y1), FIT_COLOR)
        assert left > 50 and mid > 50, f"coefficient plots of column {c}: fit pixels {left} left, {mid} middle"
    summary = ocr(img, SUMMARY_PANEL)
    assert f"segment {segments - 1}" in summary, summary
    assert f"Alerts ({len(alerts)})" in summary, (summary, alerts)
    text = summary.replace(" ", "")
    for a in alerts:
        assert a["coefficient"] in text, (a, summary)
    return summary


def run_and_open(procs, tmp: Path, segments: int, step_at: float, timeout: float):
    rrd, alerts = monitor_recording(procs, tmp, segments, step_at)
    stats = rrd_stats(rrd)
    stats["loadavg_before"] = round(os.getloadavg()[0], 2)  # the monitor's own work included
    load, png, drawn, cpu = open_in_browser(rrd, tmp, last_mission_time(rrd), timeout)
    keep(f"monitor-web-{segments}.png", png)
    (tmp / "monitor-web.png").write_bytes(png)
    stats.update(frames=drawn, cpu=cpu, loadavg=round(os.getloadavg()[0], 1))
    print(
        f"web view of {segments} 1-h segments: {stats['chunks']} chunks, footer {stats['footer']}, "
        f"{stats['bytes'] / 1e6:.2f} MB; complete after {load} s, {cpu and round(cpu, 1)} s of Chromium CPU "
        f"({drawn} frames drawn, load average {stats['loadavg']})"
    )
    return rrd, alerts, stats, load, png


# ---------------------------------------------------------------------------- tests


@needs_browser
def test_web_viewer_shows_the_monitor_recording(procs, tmp_path):
    """36 segments: the recording has a footer and few chunks, and opens complete; the load
    time is printed (no threshold: a loaded machine must not fail the fast suite)."""
    rrd, alerts, stats, load, png = run_and_open(procs, tmp_path, 36, 20 * HOUR, timeout=240)
    assert stats["footer"] and stats["verify_rc"] == 0, stats
    # rows batched: one chunk per entity and batch (a few hundred), not one per row (~3,800 here)
    assert stats["chunks"] < 600, stats
    assert [a["coefficient"] for a in alerts if a["kind"] == "step"] == [STEP_COEF], alerts
    assert load is not None, f"the view did not complete within 240 s (time cursor or screenshot): {tmp_path}"
    check_screenshot(png, alerts, 36)


#: 1-min load average before the week is opened above which its load time is not judged: the
#: 10-s target is for the 2-core machine otherwise idle (the monitor that drew the recording
#: just before leaves ~1-1.5); on a loaded machine the viewer draws more frames (each ~0.5-1.2 s
#: of software rendering at 1920x1080) for the same data: 25-60 s at load 6-15
QUIET_LOAD = 2.5


@pytest.mark.science
@needs_browser
def test_a_week_of_monitor_recording_opens_in_seconds(procs, tmp_path):
    """Issue 21's target: a 7-day recording of 1-h segments opens fully in the web viewer
    in under 10 s on the project's 2-core machine."""
    segments = 7 * 24
    rrd, alerts, stats, load, png = run_and_open(procs, tmp_path, segments, 3.5 * DAY, timeout=180)
    assert stats["footer"] and stats["verify_rc"] == 0, stats
    kinds = sorted({(a["kind"], a["coefficient"]) for a in alerts})
    assert ("step", STEP_COEF) in kinds and ("drift", DRIFT_COEF) in kinds, alerts
    assert load is not None, f"the view did not complete within 180 s: {tmp_path}"
    check_screenshot(png, alerts, segments)
    if stats["loadavg_before"] > QUIET_LOAD:
        pytest.skip(
            f"content checks passed; load time {load:.1f} s not judged: load average {stats['loadavg_before']} "
            f"before the open (the {WEEK_LOAD_LIMIT:g}-s target is for a quiet machine, below {QUIET_LOAD})"
        )
    assert load < WEEK_LOAD_LIMIT, (
        f"complete after {load:.1f} s (target {WEEK_LOAD_LIMIT:g} s; "
        f"{stats['frames']} frames drawn, load average {stats['loadavg_before']} before, {stats['loadavg']} after)"
    )

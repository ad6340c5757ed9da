"""The monitor's Rerun recording rendered by Rerun's web viewer in a headless browser.

A recording is drawn with the monitor's drawing functions (:mod:`stages.monitor_views`)
from a simulated stretch of data, served by ``ttl view --web`` on 127.0.0.1, opened in
headless Chromium (driven over the DevTools protocol), and screenshotted; the screenshot
must show the laid-out views (not a blank or loading page). Skipped with a message when
Chromium is not installed (``apt-get install -y chromium``).

Set ``TTL_SCREENSHOT_DIR`` to keep the screenshot for a look.
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from ttl_testutil import wait_for  # noqa: F401  (also puts the project first on sys.path)

from streamer.processes import stop_process
from streamer.session import free_port

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)),
                None)
WIDTH, HEIGHT = 1920, 1080


def draw_recording(path: Path) -> None:
    """A monitor recording: 12 hourly points of fits (the truth plus noise, a step on one
    coefficient) and the ASDs of a simulated 3-h stretch, with alerts and candidates."""
    import rerun as rr

    from stages import monitor_views as views
    from ttlcore.conventions import COEFFICIENT_NAMES
    from ttlcore.estimate.fit import DEFAULT_BAND
    from ttlcore.estimate.monitoring import band_ratio, channel_asd, reference_curves
    from ttlcore.sim.coefficients import paper_set
    from ttlcore.sim.simulator import SimulationConfig, simulate
    from ttlcore.tdi.data import compute_tdi

    tm, _ = simulate(SimulationConfig(duration=3 * 3600, orbit="keplerian", seed=3))
    td = compute_tdi(tm)
    truth = paper_set()
    rec = rr.RecordingStream("ttl_monitor", recording_id="web-view-test")
    rec.set_sinks(rr.FileSink(str(path)), default_blueprint=views.blueprint(DEFAULT_BAND))
    views.static_styles(rec, DEFAULT_BAND)
    rng = np.random.default_rng(1)
    styled: set = set()
    step = 3e-4 * (np.arange(24) == COEFFICIENT_NAMES.index("23.phi.tx"))
    data = td.data[0]
    residual = (td.data - td.model(truth))[0]
    f, asd, f_welch = channel_asd(data, td.fs)
    fr, ar, _ = channel_asd(residual, td.fs)
    ref = reference_curves(f_welch, tm.ltt.mean(axis=1))
    for i in range(12):
        rec.set_time("mission_time", duration=3600.0 * i + 1800.0)
        rec.set_time("segment", sequence=i)
        views.noise_curve(rec, "data", f, asd, DEFAULT_BAND)
        views.noise_curve(rec, "residual", fr, ar, DEFAULT_BAND)
        views.noise_curve(rec, "ttl_model", f, np.sqrt(np.maximum(asd**2 - ar[:asd.size]**2, 1e-40)), DEFAULT_BAND)
        for name, (fc, a) in ref.items():
            views.noise_curve(rec, name, fc, a, DEFAULT_BAND)
        sigma = np.full(24, 3e-5)
        views.fit_point(rec, truth + sigma * rng.standard_normal(24) + (i > 6) * step, sigma)
        views.truth_point(rec, truth + (i > 6) * step)
        rec.log("adequacy/chi2_dof", rr.Scalars(1.0 + 0.05 * rng.standard_normal()))
        rec.log("adequacy/instrument/chi2_dof", rr.Scalars(1.1 + 0.05 * rng.standard_normal()))
        rec.log("adequacy/log10_residual_over_expected",
                rr.Scalars(np.log10(band_ratio(fr, ar, *ref["expected"], DEFAULT_BAND))))
        for g, (lo, hi) in enumerate(((3e-3, 3e-2), (3e-2, 0.3), (0.3, 0.9))):
            views.band_series(rec, g, {"f_lo": lo, "f_hi": hi, "chi2_dof": 1 + 0.1 * g + 0.05 * rng.standard_normal()},
                              styled)
    views.text(rec, "alerts", "step of +0.30 mm/rad in 23.phi.tx at 6.5 h (8.1 sigma)", "WARN")
    views.text(rec, "model/log", "fit 11: top candidates: step: Δχ² 65.2, log BF 28.1 (significant)")
    views.text(rec, "log", "monitor of run web-test started")
    rec.flush()
    rec.disconnect()


class DevTools:
    """A headless Chromium driven over the DevTools protocol (websocket-client)."""

    def __init__(self, tmp: Path):
        import websocket

        port = free_port()
        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--no-first-run",
             "--use-angle=swiftshader", "--enable-unsafe-swiftshader", f"--window-size={WIDTH},{HEIGHT}",
             f"--remote-debugging-port={port}", "--remote-debugging-address=127.0.0.1",
             f"--user-data-dir={tmp / 'chromium-profile'}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
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
        self.ws = websocket.create_connection(pages[0]["webSocketDebuggerUrl"], timeout=60,
                                              suppress_origin=True)
        self._id = 0

    def call(self, method: str, **params) -> dict:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def close(self) -> None:
        try:
            self.ws.close()
        except Exception:
            pass
        stop_process(self.proc)


def pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)


def drawn(img: np.ndarray) -> dict:
    """What a screenshot shows: grey-level spread and the share of saturated (curve) pixels."""
    grey = img.mean(axis=2)
    colourful = (img.max(axis=2) - img.min(axis=2)) > 60
    return {"grey_std": float(grey.std()), "colour_fraction": float(colourful.mean())}


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt-get install -y chromium): "
                                               "no headless rendering of the Rerun web viewer")
def test_web_viewer_renders_the_monitor_recording(tmp_path):
    rrd = tmp_path / "monitor.rrd"
    draw_recording(rrd)
    web_port = free_port()
    view = subprocess.Popen([str(Path(sys.executable).with_name("ttl")), "view", "--web", "--port", str(web_port), str(rrd)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=Path(__file__).resolve().parents[2])
    browser = None
    try:
        line = view.stdout.readline()
        assert "http://127.0.0.1:" in line, line
        url = line.split(": ", 1)[1].split()[0]
        assert url.startswith(f"http://127.0.0.1:{web_port}/")
        browser = DevTools(tmp_path)
        browser.call("Page.enable")
        browser.call("Emulation.setDeviceMetricsOverride", width=WIDTH, height=HEIGHT, deviceScaleFactor=1,
                     mobile=False)
        browser.call("Page.navigate", url=url)
        # the viewer is a wasm app rendering in software here: wait until the views are drawn
        # (measured: a drawn layout has grey std ~29 and ~1.7 % coloured pixels; the loading
        # and welcome pages below 19 and 0.25 %); mouse moves make it repaint
        deadline = time.monotonic() + 240
        seen, png = {}, b""
        while time.monotonic() < deadline:
            for k in range(5):
                browser.call("Input.dispatchMouseEvent", type="mouseMoved", x=WIDTH // 2 + k, y=HEIGHT // 2)
                time.sleep(1)
            png = browser.screenshot()
            seen = drawn(pixels(png))
            if seen["colour_fraction"] > 0.008 and seen["grey_std"] > 20:
                time.sleep(5)  # let the last views settle
                png = browser.screenshot()
                seen = drawn(pixels(png))
                break
        out = tmp_path / "monitor-web.png"
        out.write_bytes(png)
        keep = os.environ.get("TTL_SCREENSHOT_DIR")
        if keep:
            Path(keep).mkdir(parents=True, exist_ok=True)
            shutil.copy(out, Path(keep) / out.name)
        img = pixels(png)
        assert img.shape[:2] == (HEIGHT, WIDTH)
        # not blank: a spread of grey levels (text, grids, panels) and coloured curves
        assert seen["grey_std"] > 20 and seen["colour_fraction"] > 0.008, (seen, out)
    finally:
        if browser is not None:
            browser.close()
        view.send_signal(signal.SIGINT)  # ttl view stops its rerun server
        try:
            view.wait(10)
        except subprocess.TimeoutExpired:
            view.kill()
            view.wait(10)

"""``ttl view --web``: a run's Rerun recording in Rerun's web viewer, on 127.0.0.1 only.

Two servers, both bound to 127.0.0.1:

* the ``rerun`` binary with ``--serve-web --bind 127.0.0.1`` serves the web viewer's
  application (and an idle gRPC server) on ``web_port``;
* a static HTTP server (:mod:`http.server`) serves the ``.rrd`` file on a free port, with
  the CORS header that lets the viewer's page (another port, hence another origin) fetch it.

The viewer's URL, ``http://127.0.0.1:<web_port>/?url=http://127.0.0.1:<port>/<file>.rrd``,
opens the recording in any browser on the machine (no display needed on the server).
"""

from __future__ import annotations

import functools
import http.server
import signal
import subprocess
import threading
from pathlib import Path
from urllib.parse import quote

from ..bus.session import LOOPBACK, free_port
from ..runtime.processes import stop_process, tied_to_parent


class _CorsHandler(http.server.SimpleHTTPRequestHandler):
    def end_headers(self):
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def log_message(self, *args):  # quiet
        pass


class WebView:
    """The web viewer of the recording ``rrd`` served on 127.0.0.1 by the ``rerun``
    executable ``binary`` (:func:`streamer.tools.viewer.rerun_binary`).

    Attributes
    ----------
    url : str
        Where to point a browser.
    """

    def __init__(self, rrd, binary: str, web_port: int | None = None):
        self.rrd = Path(rrd)
        self.web_port = int(web_port or free_port())
        handler = functools.partial(_CorsHandler, directory=str(self.rrd.parent))
        self.files = http.server.ThreadingHTTPServer((LOOPBACK, 0), handler)
        self._thread = threading.Thread(target=self.files.serve_forever, name="rrd-http", daemon=True)
        self._thread.start()
        file_url = f"http://{LOOPBACK}:{self.files.server_address[1]}/{quote(self.rrd.name)}"
        self.command = [
            str(binary),
            "--serve-web",
            "--bind",
            LOOPBACK,
            "--port",
            str(free_port()),
            "--web-viewer-port",
            str(self.web_port),
        ]
        # the viewer server goes with `ttl view --web`, however that ends (SIGKILL included)
        self.proc = subprocess.Popen(
            self.command,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=tied_to_parent(signal.SIGTERM),
            process_group=0,  # not the terminal's Ctrl-C: ttl view stops it (close)
        )
        self.url = f"http://{LOOPBACK}:{self.web_port}/?url={quote(file_url, safe='')}"

    def wait(self) -> int:
        return self.proc.wait()

    def close(self) -> None:
        stop_process(self.proc)
        self.files.shutdown()
        self.files.server_close()

    def __enter__(self) -> WebView:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

"""A hostile process of the security tests: ``python intruder.py '<json args>'``.

Connects to a run's router as told (``credentials`` + ``identity``: a certificate of the
run's CA for another role; ``ca_only``: the run's CA but no certificate of its own;
``plain``: TCP without TLS to the TLS port; ``foreign``: a certificate of another CA) and,
for ``duration`` seconds, publishes forged telemetry segments (eta x3), forged fits,
a forged ``control/progress/replayer`` claiming the run is 3 segments long and a forged
``control/stop``, and asks the fitter for a model change as ``ttl control`` does (a query on
``control/fitter/model``).  Writes ``{"connected": bool, "error": str, "puts": n,
"answers": n}`` to ``out`` (``answers``: verdicts the fitter sent back).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import zenoh  # noqa: E402

from streamer.bus.codec import encode  # noqa: E402
from streamer.bus.keys import control_key, stream_key  # noqa: E402
from streamer.bus.session import SessionSettings, make_config  # noqa: E402


def config(args: dict) -> zenoh.Config:
    endpoint = args["endpoint"]
    if args.get("credentials"):  # a certificate of the run's CA (another role's)
        return make_config(
            SessionSettings(
                mode="client", connect=(endpoint,), credentials=args["credentials"], identity=args["identity"]
            )
        )
    cfg = make_config(
        SessionSettings(mode="client", connect=(endpoint.replace("tls/", "tcp/") if args.get("plain") else endpoint,))
    )
    if not args.get("plain"):
        # it trusts the run's CA (to get as far as it can), and presents another CA's
        # certificate or none at all (a TLS client without a certificate of its own)
        tls = {"root_ca_certificate": args["ca"], "enable_mtls": bool(args.get("foreign"))}
        if args.get("foreign"):
            tls.update(connect_certificate=args["foreign"] + ".pem", connect_private_key=args["foreign"] + ".key")
        cfg.insert_json5("transport/link/tls", json.dumps(tls))
    return cfg


def main(args: dict) -> None:
    run, out = args["run"], Path(args["out"])
    cfg = config(args)
    cfg.insert_json5("connect/timeout_ms", "3000")
    report = {"connected": False, "error": None, "puts": 0, "answers": 0}
    try:
        session = zenoh.open(cfg)
    except Exception as exc:  # refused: that is the point
        report["error"] = str(exc)
        out.write_text(json.dumps(report))
        return
    report["connected"] = True
    rng = np.random.default_rng(7)
    deadline = time.monotonic() + float(args["duration"])
    i = 0
    try:
        while time.monotonic() < deadline:
            index = i % 6
            payload, attachment = encode(
                {"eta": 3.0 * rng.standard_normal((6, 14400)), "dws": rng.standard_normal((6, 2, 14400))},
                {"run": run, "index": index, "t0": 3600.0 * index, "fs": 4.0, "producer": "replayer"},
            )
            session.put(stream_key(run, "telemetry"), payload, attachment=attachment)
            payload, attachment = encode(
                10.0 * rng.standard_normal(24),
                {"run": run, "index": index, "t0": 3600.0 * index, "fs": 4.0, "producer": "fitter"},
            )
            session.put(stream_key(run, "fit"), payload, attachment=attachment)
            session.put(
                control_key(run, "progress", "replayer"),
                json.dumps({"stage": "replayer", "segments_total": 3, "done": [[0, 2]], "failed": []}),
            )
            session.put(control_key(run, "stop"), b"{}")
            report["puts"] += 4
            for reply in session.get(
                control_key(run, "fitter", "model"), payload=b'{"effects": ["linear-ttl", "drift"]}', timeout=0.5
            ):
                report["answers"] += reply.ok is not None
            i += 1
            time.sleep(0.5)
    finally:
        session.close()
        out.write_text(json.dumps(report))


if __name__ == "__main__":
    main(json.loads(sys.argv[1]))

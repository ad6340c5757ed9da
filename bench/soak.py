"""Soak run: a long ``ttl run`` (7 simulated days in 1-h segments by default), the memory
(RSS) of every stage sampled while it runs and the per-segment latency of every stage.

Prints JSON: per stage the slope of RSS against segment index [MB per segment] and of the
latency against segment index [s per segment] (least squares), with the first and last
values; flat within noise is the target (``docs/operations.md``).  The latency of a stage
for segment i is the time between its upstream's and its own report of i in the progress
the launcher verified (``ttl/<run>/control/board/<stage>``); the replayer's is the time
between consecutive segments.

    python bench/soak.py                      # 7 days, 1-h segments (~168 segments)
    python bench/soak.py --days 3 --segment 10min
    python bench/soak.py --days 0.5           # a quick look
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from streamer.keys import from_ranges  # noqa: E402
from streamer.session import Bus, SessionSettings, free_port  # noqa: E402

UPSTREAM = {"tdi_builder": "replayer", "fitter": "tdi_builder", "subtractor": "fitter", "monitor": "subtractor"}


def slope(x, y) -> float | None:
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3:
        return None
    return float(np.polyfit(x[ok], y[ok], 1)[0])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--days", type=float, default=7.0)
    p.add_argument("--segment", default="1h")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--interval", type=float, default=2.0, help="RSS sampling period [s]")
    p.add_argument("--keep", type=Path, help="keep the recordings in this directory")
    args = p.parse_args(argv)

    rec = args.keep or Path(tempfile.mkdtemp(prefix="ttl-soak-"))
    port = free_port()
    run = "soak"
    cmd = [str(Path(sys.executable).with_name("ttl")), "run", "--simulate",
           f"--duration {args.days * 24:g}h --orbit unequal --seed {args.seed}", "--segment", args.segment,
           "--run-id", run, "--recordings", str(rec), "--listen", f"tcp/127.0.0.1:{port}", "--quiet",
           "--insecure"]  # plain TCP on loopback: the bench's own client only reads
    t_start = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    done_at: dict[str, dict[int, float]] = {}
    lock = threading.Lock()

    def on_board(sample):
        msg = json.loads(sample.payload.to_bytes())
        now = time.monotonic()
        with lock:
            seen = done_at.setdefault(msg["stage"], {})
            for i in from_ranges(msg.get("done")) | from_ranges(msg.get("failed")):
                seen.setdefault(i, now)

    rss: dict[str, list[tuple[int, float]]] = {}
    bus = None
    while bus is None and proc.poll() is None:
        try:
            bus = Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
        except Exception:  # noqa: BLE001 - the router is not up yet
            time.sleep(1.0)
    if bus is None:
        print(json.dumps({"exit_status": proc.wait(), "output_tail": proc.stdout.read().decode(errors="replace")[-2000:]}))
        return 1
    with bus:
        bus.segment_subscriber(f"ttl/{run}/control/board/*", on_board, history=1)
        while proc.poll() is None:
            with lock:
                index = max(done_at.get("replayer", {0: 0}) or [0])
            try:
                kids = psutil.Process(proc.pid).children(recursive=True)
            except psutil.NoSuchProcess:
                break
            for k in kids:
                try:
                    cmdline = k.cmdline()
                    name = next((w.split(".", 1)[1] for w in cmdline if w.startswith("stages.")), None)
                    if name:
                        rss.setdefault(name, []).append((index, k.memory_info().rss / 2 ** 20))
                except psutil.Error:
                    continue
            time.sleep(args.interval)
    out = proc.stdout.read().decode(errors="replace")
    result = {"days": args.days, "segment": args.segment, "exit_status": proc.returncode,
              "seconds": round(time.monotonic() - t_start, 1), "recordings": str(rec), "stages": {}}
    for stage, samples in sorted(rss.items()):
        idx = [i for i, _ in samples]
        mb = [m for _, m in samples]
        mine = done_at.get(stage, {})
        up = done_at.get(UPSTREAM.get(stage, ""), {})
        if stage == "replayer":
            ks = sorted(mine)
            lat = {k: mine[k] - mine[k - 1] for k in ks if k - 1 in mine}
        else:
            lat = {k: mine[k] - up[k] for k in mine if k in up}
        ks = sorted(lat)
        result["stages"][stage] = {
            "rss_mb_first": round(mb[0], 1) if mb else None, "rss_mb_last": round(mb[-1], 1) if mb else None,
            "rss_mb_max": round(max(mb), 1) if mb else None,
            # skip the first tenth: imports, caches and the window filling up
            "rss_slope_mb_per_segment": slope(idx[len(idx) // 10:], mb[len(mb) // 10:]),
            "latency_s_median": float(np.median([lat[k] for k in ks])) if ks else None,
            "latency_slope_s_per_segment": slope(ks[len(ks) // 10:], [lat[k] for k in ks][len(ks) // 10:]),
            "segments": len(mine)}
    if proc.returncode != 0:
        result["output_tail"] = out[-2000:]
    print(json.dumps(result, indent=2))
    return 0 if proc.returncode == 0 else 1


if __name__ == "__main__":
    sys.exit(main())

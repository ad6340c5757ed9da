"""Loopback throughput of segment messages between two processes.

``python -m streamer.tools.bench --segments 20 --size-mb 8 --repeat 3`` runs a publisher and a
subscriber process (peer mode on 127.0.0.1, :class:`~streamer.bus.segment_stream.SegmentPublisher`
with congestion control BLOCK), once with Zenoh's shared-memory transport disabled and
once enabled, and prints one JSON object per run: bytes, seconds from the first ``put``
to the last arrival, MB/s, and whether every segment arrived once with a valid checksum.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time

import numpy as np

from ..bus.codec import CodecError, decode, encode
from ..bus.keys import topic_pattern
from ..bus.session import Bus, SessionSettings, free_port

RUN = "bench"
MB = 2**20


def _subscriber(port: int, n: int, shm: bool, ready, results) -> None:
    arrivals = []
    with Bus.open(SessionSettings(listen=(f"tcp/127.0.0.1:{port}",), shared_memory=shm)) as bus:
        bus.segment_subscriber(
            topic_pattern(RUN, "telemetry"),
            lambda s: arrivals.append((time.time(), str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes())),
            history=0,
        )
        bus.declare_alive(RUN, "bench-subscriber")
        ready.set()
        deadline = time.monotonic() + 120
        while len(arrivals) < n and time.monotonic() < deadline:
            time.sleep(0.005)
        indices, valid = [], True
        for _, key, payload, attachment in arrivals:
            try:
                indices.append(decode(payload, attachment, key=key)[0].index)
            except CodecError:
                valid = False
        results.put(
            {
                "t_last": max((a[0] for a in arrivals), default=None),
                "received": len(arrivals),
                "intact": valid and sorted(indices) == list(range(n)),
            }
        )


def _publisher(port: int, n: int, size: int, shm: bool, results) -> None:
    data = [np.random.default_rng(i).standard_normal(size // 8) for i in range(n)]
    messages = [encode(d, {"run": RUN, "index": i, "t0": 0.0, "fs": 4.0}) for i, d in enumerate(data)]
    with Bus.open(SessionSettings(connect=(f"tcp/127.0.0.1:{port}",), shared_memory=shm)) as bus:
        while "bench-subscriber" not in bus.alive_stages(RUN, timeout=0.5):
            time.sleep(0.05)
        pub = bus.segment_publisher(RUN, "telemetry", cache=1)
        t_first = time.time()
        for i, (payload, attachment) in enumerate(messages):
            pub.put(i, payload, attachment)
        results.put(
            {"t_first": t_first, "put_seconds": time.time() - t_first, "bytes": sum(len(p) for p, _ in messages)}
        )
        time.sleep(2.0)  # let the subscriber drain before the session closes


def measure(segments: int = 20, size: int = 8 * MB, shm: bool = False) -> dict:
    """One publisher -> subscriber run over loopback; returns the timings."""
    ctx = mp.get_context("spawn")
    port = free_port()
    ready, sub_results, pub_results = ctx.Event(), ctx.Queue(), ctx.Queue()
    sub = ctx.Process(target=_subscriber, args=(port, segments, shm, ready, sub_results))
    sub.start()
    ready.wait(30)
    pub = ctx.Process(target=_publisher, args=(port, segments, size, shm, pub_results))
    pub.start()
    published, received = pub_results.get(timeout=180), sub_results.get(timeout=180)
    sub.join(30)
    pub.join(30)
    seconds = received["t_last"] - published["t_first"]
    return {
        "shared_memory": shm,
        "segments": segments,
        "segment_bytes": size,
        "bytes": published["bytes"],
        "seconds": round(seconds, 4),
        "MB_per_s": round(published["bytes"] / MB / seconds, 1),
        "put_seconds": round(published["put_seconds"], 4),
        "received": received["received"],
        "intact": received["intact"],
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m streamer.tools.bench", description=__doc__.splitlines()[0])
    p.add_argument("--segments", type=int, default=20)
    p.add_argument("--size-mb", type=float, default=8.0)
    p.add_argument("--repeat", type=int, default=1)
    args = p.parse_args(argv)
    for _ in range(args.repeat):
        for shm in (False, True):
            print(json.dumps(measure(args.segments, int(args.size_mb * MB), shm)), flush=True)


if __name__ == "__main__":
    main()

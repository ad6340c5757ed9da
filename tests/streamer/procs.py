"""Child processes of the streamer tests: ``python procs.py <role> '<json args>'``.

Roles
-----
publisher
    Publishes ``n`` telemetry segments of ``size`` bytes with :class:`SegmentPublisher`
    (BLOCK, cache) once the stage ``wait_for`` is alive, declares ``<name>-done``, then
    keeps its caches alive until ``ttl/<run>/control/stop``; writes timings to ``out``.
subscriber
    Receives segments with the advanced subscriber, decodes each (checksum checked; a
    damaged copy is asked for again from the publishers' caches, as a stage does) and,
    after ``n`` distinct indices or ``timeout``, writes what it got to ``out``.
stage
    Runs :class:`Doubler` (a :class:`streamer.runtime.stage.Stage`) with the StageConfig ``config``.
"""

from __future__ import annotations

import json
import logging
import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from streamer.bus.codec import CodecError, Expect, decode, encode, parse_header  # noqa: E402
from streamer.bus.keys import control_key, topic_pattern  # noqa: E402
from streamer.bus.session import Bus, SessionSettings  # noqa: E402
from streamer.runtime.stage import Output, Stage, StageConfig, configure_logging  # noqa: E402

log = logging.getLogger("procs")


def segment(index: int, size: int) -> np.ndarray:
    """Deterministic test segment of ``size`` bytes, shape (2, size / 16)."""
    return np.random.default_rng(index).standard_normal((2, size // 16))


def settings(args: dict) -> SessionSettings:
    return SessionSettings(
        mode=args.get("mode"),
        listen=tuple(args["listen"]) if args.get("listen") else None,
        connect=tuple(args.get("connect") or ()),
        shared_memory=args.get("shm"),
    )


def publisher(args: dict) -> None:
    run, n, size = args["run"], args["n"], args["size"]
    stop = threading.Event()
    with Bus.open(settings(args)) as bus:
        bus.subscriber(control_key(run, "stop"), lambda sample: stop.set())
        deadline = time.monotonic() + 30
        while args.get("wait_for") and args["wait_for"] not in bus.alive_stages(run, timeout=0.5):
            if time.monotonic() > deadline:
                raise SystemExit(f"{args['wait_for']} never appeared")
            time.sleep(0.1)
        pub = bus.segment_publisher(run, "telemetry", cache=args.get("cache", 4))
        messages = []
        for i in range(n):
            payload, attachment = encode(
                segment(i, size),
                {"run": run, "index": i, "t0": 3600.0 * i, "fs": 4.0, "channels": ["a", "b"], "producer": "publisher"},
            )
            messages.append((payload, attachment))
        times = []
        t_start = time.perf_counter()
        for i, (payload, attachment) in enumerate(messages):
            t = time.perf_counter()
            pub.put(i, payload, attachment)
            times.append(time.perf_counter() - t)
            time.sleep(args.get("interval", 0))
        elapsed = time.perf_counter() - t_start
        bus.declare_alive(run, args.get("name", "publisher") + "-done")
        Path(args["out"]).write_text(
            json.dumps({"put_seconds": times, "elapsed": elapsed, "bytes": sum(len(p) for p, _ in messages)})
        )
        stop.wait(args.get("linger", 60))


def subscriber(args: dict) -> None:
    run, n = args["run"], args["n"]
    samples: queue.Queue = queue.Queue()
    received, errors, arrival, missed, refetched = {}, [], {}, [], []

    def on_sample(s) -> None:
        samples.put((time.perf_counter(), str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes()))

    with Bus.open(settings(args)) as bus:
        bus.segment_subscriber(
            topic_pattern(run, "telemetry"),
            on_sample,
            history=args.get("history", 4),
            on_miss=lambda source, count: missed.append({"source": source, "count": count, "t": time.perf_counter()}),
        )
        bus.declare_alive(run, args.get("name", "subscriber"))
        deadline = time.monotonic() + args.get("timeout", 60)
        while len(received) < n and time.monotonic() < deadline:
            try:
                t, key, payload, attachment = samples.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                header, arrays = decode(payload, attachment, Expect(run=run), key=key)
            except CodecError as exc:
                errors.append(str(exc))
                if exc.field in ("payload", "checksum"):  # damaged on the way: the cache has it
                    index = parse_header(attachment, key).index
                    refetched.append(index)
                    bus.refetch(key, index, attachment, on_sample)
                continue
            intact = bool(np.array_equal(arrays["data"], segment(header.index, args["size"])))
            received.setdefault(header.index, []).append(intact)
            arrival.setdefault(header.index, t)
        Path(args["out"]).write_text(
            json.dumps(
                {
                    "received": {str(k): v for k, v in received.items()},
                    "errors": errors,
                    "missed": missed,
                    "refetched": refetched,
                    "t_first": min(arrival.values(), default=None),
                    "t_last": max(arrival.values(), default=None),
                }
            )
        )


class Doubler(Stage):
    """Test stage: ``telemetry`` (2, n) -> ``tdi`` = 2 x data; fails when ``meta.fail`` is set."""

    name = "doubler"
    inputs = ("telemetry",)

    #: A header index whose checks meet an exception that is not a CodecError (a stand-in for
    #: a bug met by an unforeseen message): the stage must record it and go on.
    POISON_INDEX = 99

    def expect(self, topic, index):
        if index == self.POISON_INDEX:
            raise LookupError(f"expect() cannot handle index {index}")
        return Expect(run=self.run_id, index=index, arrays={"data": ("<f8", (2, None))})

    factor = 2.0
    commands = ("factor",)

    def control(self, command, payload):
        if command != "factor":
            return super().control(command, payload)
        factor = json.loads(payload)["factor"]
        if not isinstance(factor, (int, float)):
            raise ValueError(f"factor: expected a number, got {factor!r}")
        self.factor = float(factor)

    def handle(self, header, arrays):
        if header.meta.get("fail"):
            raise RuntimeError(f"asked to fail on segment {header.index}")
        # meta.busy [s]: a long step with checkpoints (as the fitter's live diagnosis), at
        # which the control commands come meanwhile are queued, not handled
        end = time.monotonic() + float(header.meta.get("busy") or 0.0)
        while time.monotonic() < end and not self.stopping:
            self.controls.defer(f"busy with segment {header.index}")
            time.sleep(0.05)
        return [
            Output(
                "tdi",
                {"data": self.factor * arrays["data"]},
                fields={"channels": list(header.channels), "units": "test units"},
                summary={"index": header.index, "mean": float(arrays["data"].mean())},
            )
        ]


def stage(args: dict) -> int:
    return Doubler(StageConfig.from_dict(args["config"])).run()


if __name__ == "__main__":
    configure_logging("INFO")
    role, arguments = sys.argv[1], json.loads(sys.argv[2])
    sys.exit({"publisher": publisher, "subscriber": subscriber, "stage": stage}[role](arguments) or 0)

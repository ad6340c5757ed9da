"""Operations under faults and bad actors (``make test-ops``; marker ``ops``): real ``ttl run``
processes on a loopback Zenoh, real MCAP files read back.

* clean: a 6 h simulation in 1 h segments, the reference.
* fuzz: the same run while a hostile client of the run's router publishes >= 1000 malformed
  or hostile messages (random bytes, wrong checksums, huge declared sizes and indices, wrong
  dtypes, NaN payloads, identical and altered duplicates, forged producers, wrong fs / t0 /
  length, forged progress): no stage crashes or stalls, every message is recorded as
  rejected (or, an identical copy, as a duplicate) by every stage it reached, and the fits and
  residuals equal the clean run's bit for bit.  Altered duplicates are sent of segments every
  stage has handled (a conflict within the hold keeps the genuine copy out too, which
  tests/streamer/runtime/test_stage.py checks): each is recorded as a conflict whose first copy
  had been used, and ``ttl run`` exits 1 for them.
* NaN gap: ten minutes of NaN in eta: the run ends on its own, the gap is reported, and the
  fit after the gap is within 1 sigma of the clean run's.
* launcher killed: every stage stops by itself (exit status 3, recording closed with the
  reason), nothing orphaned; and the same command with ``--resume`` completes the run.
* router killed: restarted by the launcher, the results equal the clean run's.
"""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
import zlib
from pathlib import Path

import numpy as np
import psutil
import pytest
import zenoh
from ttl_testutil import (
    STAGES,
    Procs,
    finish,
    fits_and_residuals,
    handled_count,
    output,
    router_process,
    run_to_the_end,
    stage_processes,
    ttl_command,
    wait_for,
    watch_board,
)
from ttl_testutil import run_args as ttl_run_args

from streamer.bus.codec import encode
from streamer.bus.session import Bus, SessionSettings, free_port
from streamer.recording.recorder import read_recording

pytestmark = pytest.mark.ops

SEGMENTS = 6
SIM = f"--duration {SEGMENTS}h --orbit unequal --seed 1"
INPUTS = {
    "tdi_builder": ("telemetry",),
    "fitter": ("tdi",),
    "subtractor": ("tdi", "fit"),
    "monitor": ("telemetry", "tdi", "fit", "residual"),
}
REFUSALS = ("rejected", "forged", "conflict")


def run_args(run_id: str, rec: Path, *extra, sim: str = SIM) -> list[str]:
    # plain TCP (--insecure): the plan checks must hold without the access control, and the
    # hostile client of the fuzz must reach the stages
    return ttl_run_args(run_id, rec, "--insecure", *extra, sim=sim, timeout=600)


def assert_same_results(a: dict, b: dict, rtol: float = 0.0) -> None:
    for topic in ("fit", "residual"):
        assert sorted(a[topic]) == sorted(b[topic]), topic
        for i in a[topic]:
            for name, arr in a[topic][i].items():
                np.testing.assert_allclose(
                    b[topic][i][name], arr, rtol=rtol, atol=0, equal_nan=True, err_msg=f"{topic} {i} {name}"
                )


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("clean")
    run_to_the_end(tmp, run_args("clean", tmp / "rec"))
    return tmp / "rec" / "clean"


# ---------------------------------------------------------------------------- the hostile client


class Fuzzer:
    """A client of the run's router that publishes hostile messages, built from the genuine
    ones it sees (so that they look right but for the one thing that is wrong)."""

    KINDS = (
        "random_bytes",
        "bad_checksum",
        "huge_size",
        "huge_index",
        "wrong_dtype",
        "nan_payload",
        "identical_duplicate",
        "altered_duplicate",
        "forged_producer",
        "wrong_fs",
        "wrong_t0",
        "short_segment",
        "bad_key",
        "forged_progress",
    )

    def __init__(self, bus: Bus, run: str, seed: int = 7):
        self.bus, self.run = bus, run
        self.rng = np.random.default_rng(seed)
        self.genuine: dict[str, list] = {t: [] for t in ("telemetry", "tdi", "fit", "residual")}
        self.sent: dict[str, int] = {}  # topic -> hostile messages sent on it
        self.identical: dict[str, int] = {}
        self.progress = 0
        self.lock = threading.Lock()
        self.mine: set = set()
        self.by_kind: dict[str, int] = {}
        self.kind = ""
        self.board = watch_board(bus, run)
        for topic in self.genuine:
            bus.subscriber(f"ttl/{run}/{topic}", self._keep(topic))

    def _keep(self, topic):
        def on_sample(sample):
            key, payload = str(sample.key_expr), sample.payload.to_bytes()
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else b""
            with self.lock:
                if (key, zlib.crc32(payload), zlib.crc32(attachment)) in self.mine:
                    return  # one of ours
                self.genuine[topic].append((json.loads(attachment)["index"], payload, attachment))

        return on_sample

    def put(
        self, topic: str, payload: bytes, attachment: bytes | None, identical: bool = False, key: str | None = None
    ) -> None:
        """Publish on the topic's stream key ``ttl/<run>/<topic>`` (or on ``key``)."""
        key = key or f"ttl/{self.run}/{topic}"
        with self.lock:
            self.mine.add((key, zlib.crc32(payload), zlib.crc32(attachment or b"")))
        self.bus.session.put(key, payload, attachment=attachment, congestion_control=zenoh.CongestionControl.BLOCK)
        self.sent[topic] = self.sent.get(topic, 0) + 1
        self.by_kind[f"{topic}/{self.kind}"] = self.by_kind.get(f"{topic}/{self.kind}", 0) + 1
        if identical:
            self.identical[topic] = self.identical.get(topic, 0) + 1

    def one(self, k: int) -> None:
        kind = self.KINDS[k % len(self.KINDS)]
        self.kind = kind
        with self.lock:
            # small messages mostly: the fit; a telemetry / tdi copy now and then
            topics = [t for t in ("fit", "residual", "telemetry", "tdi") if self.genuine[t]]
            if not topics:
                return
            heavy = [t for t in topics if t != "tdi" or k % 100 == 0]  # a TDI copy is 8.6 MB
            topic = topics[0] if k % 10 else heavy[int(self.rng.integers(len(heavy)))]
            index, payload, attachment = self.genuine[topic][-1]
        header = json.loads(attachment)
        getattr(self, kind)(topic, index, payload, header)

    # each builder publishes one message that some rule must refuse
    def _reencode(self, topic, index, payload, header, **changes):
        h = {**header, **changes}
        return payload, json.dumps(h).encode()

    def random_bytes(self, topic, index, payload, header):
        self.put(topic, self.rng.bytes(int(self.rng.integers(0, 4096))), self.rng.bytes(64))

    def bad_checksum(self, topic, index, payload, header):
        p = bytearray(payload)
        p[len(p) // 2] ^= 0xFF
        self.put(topic, bytes(p), json.dumps(header).encode())

    def huge_size(self, topic, index, payload, header):
        arrays = [{**a, "shape": [2**40], "nbytes": 2**43} for a in header["arrays"]]
        self.put(topic, payload[:64], json.dumps({**header, "payload_bytes": 2**50, "arrays": arrays}).encode())

    def huge_index(self, topic, index, payload, header):
        big = int(2**40 + self.rng.integers(1000))
        self.put(topic, payload, json.dumps({**header, "index": big}).encode())

    def _arrays(self, payload, header):
        return {
            a["name"]: np.frombuffer(
                payload, dtype=a["dtype"], count=int(np.prod(a["shape"])), offset=a["offset"]
            ).reshape(a["shape"])
            for a in header["arrays"]
        }

    def _publish(self, topic, index, arrays, header, allow_nonfinite=False, **changes):
        fields = {k: header[k] for k in ("run", "index", "t0", "fs", "channels", "producer", "meta")}
        fields.update(
            units={a["name"]: a["units"] for a in header["arrays"]},
            channel_axis={a["name"]: a["channel_axis"] for a in header["arrays"]},
        )
        fields.update(changes)
        self.put(topic, *encode(arrays, fields, allow_nonfinite=True))

    def wrong_dtype(self, topic, index, payload, header):
        self._publish(topic, index, {k: v.astype("<f4") for k, v in self._arrays(payload, header).items()}, header)

    def nan_payload(self, topic, index, payload, header):
        self._publish(
            topic, index, {k: np.full(v.shape, np.nan) for k, v in self._arrays(payload, header).items()}, header
        )

    def identical_duplicate(self, topic, index, payload, header):
        self.put(topic, payload, json.dumps(header, separators=(",", ":")).encode(), identical=True)

    def settled(self) -> int:
        """Highest index every stage has handled (-1: none yet)."""
        return min(handled_count(self.board, s) for s in STAGES) - 1

    def altered_duplicate(self, topic, index, payload, header):
        # of a segment every stage has handled: the genuine copy was used (a conflict within
        # the hold would keep it out, and the results would differ from the clean run's)
        settled = self.settled()
        with self.lock:
            old = [g for g in self.genuine[topic] if g[0] <= settled]
        if not old:  # none yet: another hostile message instead
            if header:
                self.kind = "forged_producer"
                self.forged_producer(topic, index, payload, header)
            return
        _, payload, attachment = old[-1]
        header = json.loads(attachment)
        arrays = {k: v * (1.0 + 1e-3) for k, v in self._arrays(payload, header).items()}
        self._publish(topic, header["index"], arrays, header)

    def forged_producer(self, topic, index, payload, header):
        self._publish(topic, index + 1, self._arrays(payload, header), header, producer="intruder")

    def wrong_fs(self, topic, index, payload, header):
        self._publish(topic, index + 1, self._arrays(payload, header), header, fs=1e6)

    def wrong_t0(self, topic, index, payload, header):
        self._publish(topic, index + 1, self._arrays(payload, header), header, t0=header["t0"])

    def short_segment(self, topic, index, payload, header):
        arrays = self._arrays(payload, header)
        if topic == "fit":  # the fit has no time axis: a fit of 23 coefficients instead
            arrays = {k: v[..., :23] for k, v in arrays.items()}
        else:
            arrays = {k: v[..., :10] for k, v in arrays.items()}
        cut = {**header, "channels": header["channels"]}
        self._publish(topic, index + 1, arrays, cut)

    def bad_key(self, topic, index, payload, header):
        # a genuine copy on a key under the topic's stream key (the stages subscribe to
        # ttl/<run>/<topic>/**, so it reaches them and is refused for its key)
        self.put(topic, payload, json.dumps(header).encode(), key=f"ttl/{self.run}/{topic}/x{index}")

    def forged_progress(self, topic, index, payload, header):
        stage = ["replayer", "tdi_builder", "fitter", "subtractor", "monitor"][self.progress % 5]
        msg = {
            "run": self.run,
            "stage": stage,
            "pid": 1,
            "time": time.time(),
            "index": SEGMENTS - 1,
            "done": [[0, SEGMENTS - 1]],
            "failed": [],
            "gaps": [],
            "segments_total": SEGMENTS,
            "complete": True,
            "fits_ranges": [[0, 2**40]],
        }
        if self.progress % 3 == 1:
            msg["segments_total"] = 3
        self.bus.session.put(
            f"ttl/{self.run}/control/progress/{stage}",
            json.dumps(msg).encode(),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self.progress += 1


def test_fuzz_of_hostile_messages_changes_nothing(clean, tmp_path):
    port = free_port()
    procs = Procs(tmp_path)
    n_messages = 1400
    try:
        # paced (a segment every 8 s) so that the hostile messages meet a run in progress
        proc = procs.ttl(*run_args("fuzz", tmp_path / "rec", "--listen", f"tcp/127.0.0.1:{port}", "--pace", "450"))
        with Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as bus:
            fuzz = Fuzzer(bus, "fuzz")
            wait_for(lambda: fuzz.genuine["fit"] or proc.poll() is not None, 600, "the first fit")
            k = 0
            while k < n_messages and proc.poll() is None:
                fuzz.one(k)
                k += 1
                if k % 50 == 0:
                    time.sleep(0.05)
            # altered duplicates of segments every stage has handled (the loop may come too early)
            wait_for(lambda: fuzz.settled() >= 0 or proc.poll() is not None, 600, "a segment every stage handled")
            for j in range(24):
                fuzz.kind = "altered_duplicate"
                fuzz.altered_duplicate(("fit", "residual", "telemetry", "fit")[j % 4], 0, b"", {})
            code = finish(proc, 900)
            out = output(proc)
        assert k == n_messages, f"the run ended after {k} hostile messages: {out[-2000:]}"
    finally:
        procs.close()
    # the altered duplicates are conflicting copies: the run exits 1 (docs/operations.md), and
    # nothing else goes wrong (no stage died, none gave up a segment)
    assert code == 1 and "conflicting copies of" in out, out[-4000:]
    assert "died" not in out and "gave up" not in out and "did not handle" not in out, out[-4000:]
    run_dir = tmp_path / "rec" / "fuzz"
    # every stage recorded every hostile message that reached it: refused, or ignored as identical
    for stage, topics in INPUTS.items():
        if stage not in STAGES:
            continue
        rec = read_recording(run_dir / f"{stage}.mcap")
        assert rec.complete and rec.problem is None, stage
        refused = [e for e in rec.json("errors") if e["kind"] in REFUSALS]
        dup = [e for e in rec.json("events") if e["kind"] == "duplicate"]
        for topic in topics:
            on_topic = [e for e in refused if (e.get("key") or "").split("/")[2:3] == [topic]]
            dups = [e for e in dup if f"/{topic}/" in e["message"]]
            sent = fuzz.sent.get(topic, 0)
            assert len(on_topic) + len(dups) >= sent, (
                stage,
                topic,
                len(on_topic),
                len(dups),
                sent,
                fuzz.by_kind,
                sorted({e["field"] for e in on_topic}),
            )
        assert not [e for e in rec.json("errors") if e["kind"] == "failed"], (stage, rec.json("errors")[:3])
        first = [e for e in refused if e["kind"] == "conflict" and e["field"] == "payload"]
        assert all(e["details"]["first_copy"] == "used" for e in first), (stage, first[:3])
    assert sum(fuzz.sent.values()) + fuzz.progress >= 1000
    assert sum(n for k, n in fuzz.by_kind.items() if k.endswith("/altered_duplicate")) >= 20, fuzz.by_kind
    m = re.search(r"(\d+) progress message\(s\) refused", out)
    assert m and int(m.group(1)) >= fuzz.progress, out[-2000:]
    # and the science is untouched
    assert_same_results(fits_and_residuals(clean), fits_and_residuals(run_dir))
    print(json.dumps({"hostile": fuzz.sent, "identical": fuzz.identical, "forged_progress": fuzz.progress}))


# ---------------------------------------------------------------------------- kills and restarts


@pytest.mark.parametrize("stage", STAGES)
def test_stage_killed_mid_run_restarts_exactly(stage, clean, tmp_path):
    """SIGKILL of one stage after it handled 3 segments: restarted by the launcher, it
    recovers its state (the fitter its window, from the tdi_builder's recordings) and the
    fits and residuals equal the clean run's to 1e-9."""
    port = free_port()
    procs = Procs(tmp_path)
    run = f"kill-{stage.replace('_', '-')}"
    try:
        proc = procs.ttl(
            *run_args(run, tmp_path / "rec", "--listen", f"tcp/127.0.0.1:{port}", "--restart", "1", "--pace", "450")
        )
        with Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as bus:
            board = watch_board(bus, run)
            wait_for(lambda: handled_count(board, stage) >= 3 or proc.poll() is not None, 600, f"{stage} at segment 3")
            victim = stage_processes(proc)[stage]
            victim.send_signal(signal.SIGKILL)
            code = finish(proc, 900)
        out = output(proc)
    finally:
        procs.close()
    assert code == 0, out[-4000:]
    assert f"stage {stage} died (killed by SIGKILL)" in out and f"restarting {stage}" in out
    run_dir = tmp_path / "rec" / run
    assert (run_dir / f"{stage}.1.mcap").exists() and read_recording(run_dir / f"{stage}.mcap").complete
    assert_same_results(fits_and_residuals(clean), fits_and_residuals(run_dir), rtol=1e-9)
    if stage == "fitter":  # its window rebuilt: from the caches (a short run) or the tdi_builder's recordings
        events = [e["kind"] for e in read_recording(run_dir / "fitter.mcap").json("events")]
        assert "restored" in events or "replayed" in events, events
    # nothing orphaned: no stage process of this run is left
    assert not [p for p in psutil.process_iter(["cmdline"]) if run in " ".join(p.info["cmdline"] or ())]


def _journal(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "launcher.jsonl").read_text().splitlines()]


def test_router_killed_mid_run_is_restarted(clean, tmp_path):
    """SIGKILL of the run's Zenoh router after the fitter's second segment: the launcher
    starts it again on the same endpoint (``--restart 1``), the stages reconnect and recover
    what was published meanwhile, the run completes, the results equal the clean run's to
    1e-9, and the journal and ``ttl inspect`` say so.  (Before, the launcher stopped the
    run: "the Zenoh router died".)"""
    import subprocess

    port = free_port()
    procs = Procs(tmp_path)
    run = "kill-router"
    try:
        proc = procs.ttl(
            *run_args(run, tmp_path / "rec", "--listen", f"tcp/127.0.0.1:{port}", "--restart", "1", "--pace", "450")
        )
        with Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as bus:
            board = watch_board(bus, run)
            wait_for(lambda: handled_count(board, "fitter") >= 2 or proc.poll() is not None, 600, "fitter at segment 2")
        router = router_process(proc)
        assert router is not None, output(proc)[-2000:]
        router.kill()
        code = finish(proc, 900)
        out = output(proc)
    finally:
        procs.close()
    assert code == 0 and "restarting the Zenoh router (1/1)" in out, out[-4000:]
    run_dir = tmp_path / "rec" / run
    assert_same_results(fits_and_residuals(clean), fits_and_residuals(run_dir), rtol=1e-9)
    kinds = [j["kind"] for j in _journal(run_dir)]
    assert kinds[0] == "start" and kinds[-1] == "end" and "router-died" in kinds and "router-restarted" in kinds, kinds
    res = subprocess.run(ttl_command("inspect", str(run_dir)), capture_output=True, text=True, timeout=300)
    assert f"the Zenoh router (pid {router.pid}) died (killed by SIGKILL)" in res.stdout, res.stdout[-3000:]
    assert not [p for p in psutil.process_iter(["cmdline"]) if run in " ".join(p.info["cmdline"] or ())]


def test_launcher_killed_then_resumed_completes_the_run(clean, tmp_path):
    """SIGKILL of ``ttl run`` once every stage handled two segments: everything it started
    stops (nothing orphaned); the same command with ``--resume`` goes on from the first
    segment some stage lacked (``board.json``) and completes the run, every recorded copy of
    every fit and residual equal to the clean run's to 1e-9; ``ttl inspect`` lists the
    killed launcher and the resume."""
    import subprocess

    port = free_port()
    procs = Procs(tmp_path)
    run = "kill-launcher"
    args = run_args(run, tmp_path / "rec", "--listen", f"tcp/127.0.0.1:{port}", "--pace", "450")
    try:
        proc = procs.ttl(*args)
        with Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as bus:
            board = watch_board(bus, run)
            # every stage past segment 1 (the monitor comes last): the resume starts at 2 or later
            wait_for(
                lambda: min(handled_count(board, s) for s in STAGES) >= 2 or proc.poll() is not None,
                600,
                "every stage at segment 2",
            )
        everything = psutil.Process(proc.pid).children(recursive=True)
        first_pid = proc.pid
        proc.kill()
        proc.wait(30)
        gone, alive = psutil.wait_procs(everything, timeout=60)
        assert not alive, [p.cmdline() for p in alive]
        again = procs.ttl(*args, "--resume", name="ttl-resumed")
        code = finish(again, 900)
        out = output(again)
    finally:
        procs.close()
    assert code == 0 and "--resume: going on from segment" in out, out[-4000:]
    run_dir = tmp_path / "rec" / run
    resumed = [j for j in _journal(run_dir) if j["kind"] == "resume"]
    assert len(resumed) == 1 and resumed[0]["first"] >= 2, resumed
    reference = fits_and_residuals(clean)
    for stage, topic in (("fitter", "fit"), ("subtractor", "residual")):
        copies: dict = {}
        for path in sorted(run_dir.glob(f"{stage}*.mcap")):
            for s in read_recording(path).segments(topic):
                copies.setdefault(s.header.index, []).append(s.arrays)
        assert sorted(copies) == sorted(reference[topic]), topic
        for i, arrays in copies.items():
            for a in arrays:
                for name, arr in reference[topic][i].items():
                    np.testing.assert_allclose(
                        a[name], arr, rtol=1e-9, atol=0, equal_nan=True, err_msg=f"{topic} {i} {name}"
                    )
    res = subprocess.run(ttl_command("inspect", str(run_dir)), capture_output=True, text=True, timeout=300)
    assert f"ttl run (pid {first_pid}) ended without its end record (killed)" in res.stdout, res.stdout[-3000:]
    assert "launcher: resume: resumed: segments 0.." in res.stdout, res.stdout[-3000:]
    assert not [p for p in psutil.process_iter(["cmdline"]) if run in " ".join(p.info["cmdline"] or ())]


def test_restarted_fitter_keeps_the_model_changed_by_control(tmp_path):
    """``ttl control fitter model`` mid-run, then SIGKILL of the fitter: the restarted fitter
    fits with the model in force (from its earlier recording), not the configured one."""
    import subprocess

    port = free_port()
    procs = Procs(tmp_path)
    run = "kill-model"
    effects = ["linear-ttl", "drift"]
    try:
        proc = procs.ttl(
            *run_args(run, tmp_path / "rec", "--listen", f"tcp/127.0.0.1:{port}", "--restart", "1", "--pace", "450")
        )
        with Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as bus:
            board = watch_board(bus, run)
            wait_for(lambda: handled_count(board, "fitter") >= 2 or proc.poll() is not None, 600, "fitter at segment 2")
            sent = subprocess.run(
                ttl_command(
                    "control",
                    "fitter",
                    "model",
                    json.dumps({"effects": effects}),
                    "--run",
                    run,
                    "--connect",
                    f"tcp/127.0.0.1:{port}",
                ),
                capture_output=True,
                text=True,
                timeout=90,
            )
            # accepted, or queued by a fitter inside its diagnosis (handled after the segment)
            assert sent.returncode in (0, 3), (sent.stdout, sent.stderr)
            # the segment the change applies from (its 'model' event), then one fit beyond it
            run_dir = tmp_path / "rec" / run

            def model_event():
                found = [e for e in read_recording(run_dir / "fitter.mcap").json("events") if e["kind"] == "model"]
                return found[0]["details"]["from_index"] if found else None

            wait_for(lambda: model_event() is not None or proc.poll() is not None, 120, "the model event")
            start = model_event()
            assert start is not None and start < SEGMENTS - 1, (start, output(proc)[-3000:])
            wait_for(
                lambda: handled_count(board, "fitter") >= start + 1 or proc.poll() is not None,
                600,
                f"fitter past segment {start}",
            )
            stage_processes(proc)["fitter"].send_signal(signal.SIGKILL)
            code = finish(proc, 900)
        out = output(proc)
    finally:
        procs.close()
    assert code == 0 and "restarting fitter" in out, out[-4000:]
    before, after = read_recording(run_dir / "fitter.1.mcap"), read_recording(run_dir / "fitter.mcap")
    changed = [e for e in before.json("events") if e["kind"] == "model"]
    assert len(changed) == 1 and changed[0]["details"]["effects"] == effects, changed
    old = {f.header.index: f.header.meta for f in before.segments("fit")}
    new = {f.header.index: f.header.meta for f in after.segments("fit")}
    assert [old[i]["model"] for i in sorted(old) if i >= start] and new, (sorted(old), sorted(new), start)
    assert all(old[i]["model"] == (effects if i >= start else ["linear-ttl"]) for i in old), old
    assert all(m["model"] == effects for m in new.values()), {i: m["model"] for i, m in new.items()}
    restored = [e for e in after.json("events") if e["kind"] == "model-restored"]
    assert restored and restored[0]["details"]["effects"] == effects, restored
    # the change is reported once, by the process that made it (a fit from `start` on is in its file)
    assert not restored[0]["details"]["change_due"]
    assert not [i for i, m in new.items() if "model_change" in m], new
    assert len([i for i, m in old.items() if "model_change" in m]) <= 1, old


def test_launcher_killed_stages_stop_with_a_clear_error(clean, tmp_path):
    """SIGKILL of the launcher mid-run: every stage and the router stop by themselves
    (nothing orphaned), each stage's recording closed with the reason, ``ttl inspect`` says
    so, and what was produced before equals the clean run's to 1e-9."""
    port = free_port()
    procs = Procs(tmp_path)
    try:
        proc = procs.ttl(*run_args("orphans", tmp_path / "rec", "--listen", f"tcp/127.0.0.1:{port}", "--pace", "450"))
        with Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as bus:
            board = watch_board(bus, "orphans")
            wait_for(lambda: handled_count(board, "fitter") >= 1 or proc.poll() is not None, 600, "the first fit")
        children = stage_processes(proc)
        assert set(children) == set(STAGES), children
        everything = psutil.Process(proc.pid).children(recursive=True)  # the router too
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        gone, alive = psutil.wait_procs(everything, timeout=90)
        assert not alive, f"processes left running after the launcher died: {[p.cmdline() for p in alive]}"
    finally:
        for p in psutil.process_iter(["cmdline"]):
            if "orphans" in " ".join(p.info["cmdline"] or ()) and p.pid != os.getpid():
                p.kill()
        procs.close()
    run_dir = tmp_path / "rec" / "orphans"
    for stage in STAGES:
        rec = read_recording(run_dir / f"{stage}.mcap")
        assert rec.complete, (stage, rec.problem)  # closed by the stage itself
        stop = [e for e in rec.json("events") if e["kind"] == "stop"]
        assert stop and stop[-1]["details"]["orphaned"] and "launcher" in stop[-1]["message"], (stage, stop)
        assert [e for e in rec.json("errors") if e["kind"] == "orphaned"], stage
    res = __import__("subprocess").run(
        ttl_command("inspect", str(run_dir)), capture_output=True, text=True, timeout=300
    )
    assert "orphaned" in res.stdout and "launcher" in res.stdout, res.stdout[-3000:]
    # what the run produced before it stopped is the clean run's
    partial, reference = fits_and_residuals(run_dir), fits_and_residuals(clean)
    assert partial["fit"], "no fit recorded before the launcher died"
    for topic in ("fit", "residual"):
        assert set(partial[topic]) <= set(reference[topic]), topic
    assert_same_results({t: {i: reference[t][i] for i in partial[t]} for t in ("fit", "residual")}, partial, rtol=1e-9)


# ---------------------------------------------------------------------------- gaps


def test_nan_gap_ends_the_run_with_the_gap_reported(tmp_path):
    """Ten minutes of NaN in eta: the run ends by itself (exit 0), the gap is reported, and
    the fit after the gap is within 1 sigma of the clean run's over the same data."""
    import subprocess

    import h5py

    clean_file = tmp_path / "clean.h5"
    res = subprocess.run(
        ttl_command("simulate", *SIM.split(), "--out", str(clean_file)), capture_output=True, text=True, timeout=600
    )
    assert res.returncode == 0, res.stderr
    gap_file = tmp_path / "gap.h5"
    gap_file.write_bytes(clean_file.read_bytes())
    with h5py.File(gap_file, "r+") as f:
        fs = 4.0
        a = int(2.5 * 3600 * fs)
        f["eta"][:, a : a + int(600 * fs)] = np.nan  # 10 min in the middle of hour 2
    procs = Procs(tmp_path)
    try:
        runs = {}
        for name, path in (("clean", clean_file), ("gap", gap_file)):
            proc = procs.start(
                ttl_command(
                    "run",
                    "--telemetry",
                    str(path),
                    "--segment",
                    "1h",
                    "--run-id",
                    name,
                    "--recordings",
                    str(tmp_path / "rec"),
                    "--timeout",
                    "900",
                    "--insecure",
                ),
                name,
            )
            runs[name] = (finish(proc, 900), output(proc))
    finally:
        procs.close()
    for name, (code, out) in runs.items():
        assert code == 0, (name, out[-3000:])
    run_dir = tmp_path / "rec" / "gap"
    events = read_recording(run_dir / "replayer.mcap").json("events")
    gaps = [e for e in events if e["kind"] == "gap"]
    assert [(e["index"], e["details"]["stretches"]) for e in gaps] == [(2, [[7200, 9600]])], gaps
    fits = {n: read_recording(tmp_path / "rec" / n / "fitter.mcap").segments("fit") for n in runs}
    assert [f.header.index for f in fits["gap"]] == [f.header.index for f in fits["clean"]]
    last_gap, last_clean = fits["gap"][-1].arrays, fits["clean"][-1].arrays
    diff = np.abs(last_gap["coefficients"] - last_clean["coefficients"]) / last_clean["sigma"]
    assert np.all(diff < 1.0), diff
    assert not np.allclose(last_gap["coefficients"], last_clean["coefficients"])  # the gap was seen
    res = subprocess.run(ttl_command("inspect", str(run_dir)), capture_output=True, text=True, timeout=300)
    assert "gap" in res.stdout and "segment 2" in res.stdout, res.stdout[-3000:]


@pytest.mark.parametrize("stage", ["tdi_builder", "fitter", "monitor"])
def test_a_stage_failing_every_segment_ends_the_run(stage, tmp_path):
    """A stage whose ``handle`` raises on every input segment (injected by
    tests/faults/sitecustomize.py) does not hold the run until its timeout: each segment that
    failed there is given up once no good copy follows (streamer/runtime/catch_up.py), the run ends
    by itself with exit status 1, and every segment is reported failed by that stage.

    Before, nothing was missing (the segments had come) and nothing was handled: the replayer
    waited at its window, an ordered stage's queue never started, and ``ttl run`` ran into its
    ``--timeout``."""
    env = dict(
        os.environ,
        TTL_TEST_FAIL_HANDLE=stage,
        PYTHONPATH=os.pathsep.join([str(Path(__file__).parent / "faults"), os.environ.get("PYTHONPATH", "")]),
    )
    segments = 3
    procs = Procs(tmp_path)
    try:
        start = time.monotonic()
        proc = procs.start(
            ttl_command(
                *run_args("fails", tmp_path / "rec", "--timeout", "400", sim=f"--duration {segments}h --seed 2")
            ),
            "run",
            env=env,
        )
        code = finish(proc, 450)
        wall = time.monotonic() - start
        out = output(proc)
    finally:
        procs.close()
    assert code == 1, out[-3000:]
    assert "timed out" not in out and wall < 240, (wall, out[-3000:])  # the timeout is 400 s
    rec = read_recording(tmp_path / "rec" / "fails" / f"{stage}.mcap")
    failed = {e["index"] for e in rec.json("errors") if e["kind"] == "failed" and "injected failure" in e["message"]}
    assert failed == set(range(segments)), rec.json("errors")[:5]
    lost = {w["index"] for w in rec.json("warnings") if w["kind"] == "input-lost"}
    assert set(range(segments)) <= lost, rec.json("warnings")[:5]

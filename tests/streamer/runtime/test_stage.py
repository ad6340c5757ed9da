"""The stage base, run in a child process against a driver (this process) over Zenoh."""

import json
import queue
import signal
import time

import numpy as np
import psutil
import pytest
import zenoh
from mcap.reader import make_reader
from streamer_testutil import output_of, wait_for
from ttl_testutil import local_stage_config, wait_alive

from streamer.bus.codec import encode
from streamer.bus.keys import errors_key, topic_pattern
from streamer.bus.session import Bus, SessionSettings, free_port
from streamer.recording.recorder import read_recording

#: Seconds to wait for a stage's error reports: a bound for a hang, not a speed (10 s was
#: passed by a stage under load 8 with the ops marker and a fresh clone's make test beside).
REPORTS_WITHIN = 30.0
RUN = "stage-test"


def good(index, n=4000, scale=1.0, **meta):
    data = scale * np.random.default_rng(index).standard_normal((2, n))
    payload, attachment = encode(
        data,
        {
            "run": RUN,
            "index": index,
            "t0": 3600.0 * index,
            "fs": 4.0,
            "channels": ["a", "b"],
            "producer": "driver",
            "meta": meta,
        },
    )
    return data, payload, attachment


class Driver:
    """This process's side: publishes telemetry, collects tdi outputs and errors."""

    def __init__(self):
        self.port = free_port()
        self.bus = Bus.open(SessionSettings(listen=(f"tcp/127.0.0.1:{self.port}",)))
        self.outputs: queue.Queue = queue.Queue()
        self.errors: list = []
        self.alive: list = []
        self.bus.segment_subscriber(
            topic_pattern(RUN, "tdi"),
            lambda s: self.outputs.put((str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes())),
            history=0,
        )
        self.bus.subscriber(
            f"ttl/{RUN}/errors/*", lambda s: self.errors.append((str(s.key_expr), json.loads(s.payload.to_bytes())))
        )
        self.bus.watch_alive(RUN, lambda stage, alive: self.alive.append((stage, alive)))
        self.telemetry = self.bus.segment_publisher(RUN, "telemetry", cache=8)

    def start_stage(self, children, tmp_path, **fields):
        config = local_stage_config(RUN, self.port, tmp_path / "recordings", gap_grace=0.5, **fields)
        proc = children.start("stage", config=config.to_dict())
        wait_alive(self.bus, RUN, "doubler", proc, 30)
        assert proc.poll() is None, output_of(proc)
        return proc, tmp_path / "recordings" / RUN / "doubler.mcap"

    def put(self, key: str, payload: bytes, **options) -> None:
        """Publish one message as the test's sender, waiting for room in the queue: Zenoh's
        default for a put drops the message when the queue is full (a loaded CI machine),
        and a copy the test sends must arrive for what it checks to happen."""
        self.bus.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK, **options)

    def output(self, timeout=10):
        from streamer.bus.codec import decode

        key, payload, attachment = self.outputs.get(timeout=timeout)
        return decode(payload, attachment, key=key)

    def close(self):
        self.bus.close()


@pytest.fixture
def driver():
    d = Driver()
    yield d
    d.close()


def test_stage_validates_deduplicates_reports_and_stops_cleanly(driver, children, tmp_path):
    proc, mcap_path = driver.start_stage(children, tmp_path)
    _check_loopback_only(proc)
    data5 = _feed_good_bad_and_failing(driver)
    kinds = _check_error_reports(driver)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0, output_of(proc)
    wait_for(lambda: ("doubler", False) in driver.alive, 10, "the stage's token to go")
    assert ("doubler", True) in driver.alive
    _check_stage_recording(mcap_path, kinds, data5)


def _check_loopback_only(proc) -> None:
    """Only loopback listening sockets in the default configuration, no multicast scouting socket."""
    listening = [c for c in psutil.Process(proc.pid).net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]
    assert listening and all(c.laddr.ip == "127.0.0.1" for c in listening), listening
    udp = [c for c in psutil.Process(proc.pid).net_connections(kind="udp")]
    assert all(c.laddr.ip == "127.0.0.1" for c in udp), udp  # no multicast scouting socket


def _feed_good_bad_and_failing(driver):
    """Segments 0 and 1 (a duplicate of 0, five bad copies of 1 and one on another key), 3
    (2 missing), 4 (its handler raises) and 5, each good output checked; returns segment 5's
    data."""
    data0, p0, a0 = good(0)
    driver.telemetry.put(0, p0, a0)
    header, arrays = driver.output()
    assert header.index == 0 and header.producer == "doubler" and header.key == f"ttl/{RUN}/tdi"  # the stream key
    np.testing.assert_array_equal(arrays["data"], 2 * data0)

    driver.telemetry.put(0, p0, a0)  # duplicate: ignored
    data1, p1, a1 = good(1)
    wrong = encode(np.ones((3, 10)), {"run": RUN, "index": 1, "t0": 0, "fs": 4, "channels": ["a", "b", "c"]})
    nan = np.ones((2, 10))
    nan[1, 3] = np.nan
    nan = encode(nan, {"run": RUN, "index": 1, "t0": 0, "fs": 4, "channels": ["a", "b"]}, allow_nonfinite=True)
    driver.telemetry.put(1, p1, b'{"schema": "ttl-segment", oops')  # bad header
    driver.telemetry.put(1, *wrong)  # wrong shape
    driver.telemetry.put(1, *nan)  # NaN
    driver.telemetry.put(1, p1[:-1000], a1)  # truncated payload
    driver.put(f"ttl/{RUN}/telemetry/1", p1, attachment=a1)  # not the stream key
    driver.telemetry.put(1, p1, a1)  # the good one
    header, arrays = driver.output()
    assert header.index == 1
    np.testing.assert_array_equal(arrays["data"], 2 * data1)
    _, p3, a3 = good(3)
    driver.telemetry.put(3, p3, a3)  # gap: 2 missing (reported after 0.5 s)
    _, p4, a4 = good(4, fail=True)
    driver.telemetry.put(4, p4, a4)  # handler raises
    data5, p5, a5 = good(5)
    driver.telemetry.put(5, p5, a5)  # and the stage goes on
    assert driver.output()[0].index == 3
    header, arrays = driver.output()
    assert header.index == 5
    np.testing.assert_array_equal(arrays["data"], 2 * data5)
    with pytest.raises(queue.Empty):
        driver.output(timeout=0.5)  # nothing for 0 again, 2 or 4
    return data5


def _check_error_reports(driver) -> list:
    """The seven error reports, in order but for the copy on the wrong key; returns their
    (kind, index, field) without it."""
    wait_for(lambda: len(driver.errors) >= 7, REPORTS_WITHIN, "seven error reports")
    time.sleep(0.3)
    kinds = [(e["kind"], e["index"], e["field"]) for _, e in driver.errors]
    # the copy on ttl/<run>/telemetry/1 (two publishers: its order among the others is Zenoh's)
    stray = [e for _, e in driver.errors if e["field"] == "key"]
    assert len(stray) == 1 and stray[0]["key"] == f"ttl/{RUN}/telemetry/1" and stray[0]["index"] is None, stray
    kinds = [k for k in kinds if k[2] != "key"]
    assert kinds == [
        ("rejected", None, "header"),
        ("rejected", 1, "arrays[data].shape"),
        ("rejected", 1, "arrays[data]"),
        ("rejected", 1, "payload"),
        ("failed", 4, None),
        ("gap", 3, None),
    ], kinds
    # an unreadable header: the index is unknown (the stream key carries none)
    assert [k for k, _ in driver.errors][:1] == [errors_key(RUN, None)]
    assert "RuntimeError: asked to fail on segment 4" in driver.errors[-2][1]["message"]
    assert "not received within 0.5 s" in driver.errors[-1][1]["message"]
    return kinds


def _check_stage_recording(mcap_path, kinds: list, data5) -> None:
    """The stage's MCAP recording: metadata, inputs and outputs, errors, events, summaries,
    and JSON schemas on its JSON channels (mcap's own reader)."""
    rec = read_recording(mcap_path)
    assert rec.complete and rec.problem is None
    assert rec.metadata["ttl"]["stage"] == "doubler"
    assert [s.header.index for s in rec.segments("telemetry")] == [0, 1, 3, 4, 5]
    assert [s.header.index for s in rec.segments("tdi")] == [0, 1, 3, 5]
    np.testing.assert_array_equal(rec.segments("tdi")[-1].arrays["data"], 2 * data5)
    assert [(e["kind"], e["field"]) for e in rec.json("errors") if e["field"] != "key"] == [(k, f) for k, _, f in kinds]
    events = [(e["kind"], e["index"]) for e in rec.json("events")]
    assert events[0] == ("start", None) and ("duplicate", 0) in events and events[-1] == ("stop", None)
    assert [s["index"] for s in rec.json("tdi/summary")] == [0, 1, 3, 5]

    with open(mcap_path, "rb") as f:  # mcap's own reader: JSON channels with JSON schemas
        for schema, channel, _ in make_reader(f).iter_messages():
            if channel.message_encoding == "json":
                assert schema is not None and schema.encoding == "jsonschema", channel.topic


def test_conflicting_copies_within_the_hold_are_both_kept_out(driver, children, tmp_path):
    """Two different copies of a segment within the hold: neither is used, the conflict is
    recorded; a different copy after the first was used is refused and says so."""
    proc, mcap_path = driver.start_stage(children, tmp_path, hold=1.5)
    data0, p0, a0 = good(0)
    _, q0, b0 = good(0, scale=1.001)  # same index, t0, fs, producer: different content
    driver.telemetry.put(0, p0, a0)
    driver.telemetry.put(0, q0, b0)
    driver.telemetry.put(0, p0, a0)  # and the first again: refused as well
    data1, p1, a1 = good(1)
    driver.telemetry.put(1, p1, a1)
    header, arrays = driver.output(timeout=10)
    assert header.index == 1, header  # nothing for 0
    np.testing.assert_array_equal(arrays["data"], 2 * data1)
    _, q1, b1 = good(1, scale=1.001)
    driver.telemetry.put(1, q1, b1)  # after the hold: too late to withdraw segment 1
    wait_for(
        lambda: len([e for _, e in driver.errors if e["kind"] == "conflict"]) >= 3, REPORTS_WITHIN, "three conflicts"
    )
    with pytest.raises(queue.Empty):
        driver.output(timeout=0.5)
    driver.put(f"ttl/{RUN}/control/doubler/stop", b"")
    assert proc.wait(20) == 0, output_of(proc)
    conflicts = [e for e in read_recording(mcap_path).json("errors") if e["kind"] == "conflict"]
    assert [(e["index"], e["field"], e["details"].get("first_copy")) for e in conflicts] == [
        (0, "payload", "withdrawn"),
        (0, "index", None),
        (1, "payload", "used"),
    ], conflicts
    assert "first copy is withdrawn" in conflicts[0]["message"] and "had been used" in conflicts[2]["message"]
    assert [s.header.index for s in read_recording(mcap_path).segments("tdi")] == [1]


def test_a_damaged_copy_is_fetched_again_from_the_publishers_cache(driver, children, tmp_path):
    """A copy whose payload does not match its header's checksum (as Zenoh delivered once
    after a 12-s stall, docs/operations.md) is refused, and the intact copy is fetched from
    the publisher's cache and used; with no intact copy cached, a warning says so."""
    data0, p0, a0 = good(0)
    driver.telemetry.put(0, p0, a0)  # cached before the stage starts: it asks no history
    proc, mcap_path = driver.start_stage(children, tmp_path, history=0)
    damaged = bytearray(p0)
    damaged[len(damaged) // 2 : len(damaged) // 2 + 64] = bytes(64)  # same size, other content
    driver.put(f"ttl/{RUN}/telemetry", bytes(damaged), attachment=a0)  # not cached
    header, arrays = driver.output()
    assert header.index == 0
    np.testing.assert_array_equal(arrays["data"], 2 * data0)

    _, p1, a1 = good(1)  # never published intact: nothing to fetch
    driver.put(f"ttl/{RUN}/telemetry", p1[:-8] + bytes(8), attachment=a1)
    wait_for(lambda: len(driver.errors) >= 2, 30, "two error reports")
    with pytest.raises(queue.Empty):
        driver.output(timeout=0.5)
    driver.put(f"ttl/{RUN}/control/doubler/stop", b"")
    assert proc.wait(40) == 0, output_of(proc)
    rec = read_recording(mcap_path)
    assert [(e["kind"], e["index"], e["field"], e["details"]["refetch"]) for e in rec.json("errors")] == [
        ("rejected", 0, "checksum", 1),
        ("rejected", 1, "checksum", 1),
    ]
    assert [e["index"] for e in rec.json("events") if e["kind"] == "refetched"] == [0]
    assert [s.header.index for s in rec.segments("tdi")] == [0]
    empty = [w for w in rec.json("warnings") if w["kind"] == "refetch-empty"]
    assert [w["index"] for w in empty] == [1] and "no publisher cache holds an intact copy" in empty[0]["message"]


def test_killed_stage_leaves_a_salvageable_recording(driver, children, tmp_path):
    proc, mcap_path = driver.start_stage(children, tmp_path)
    data, payload, attachment = good(0)
    driver.telemetry.put(0, payload, attachment)
    assert driver.output()[0].index == 0
    time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait(10) == -signal.SIGKILL
    rec = read_recording(mcap_path)
    assert not rec.complete and "without footer" in rec.problem and rec.records > 5
    np.testing.assert_array_equal(rec.segments("telemetry")[0].arrays["data"], data)
    np.testing.assert_array_equal(rec.segments("tdi")[0].arrays["data"], 2 * data)
    assert rec.json("events")[0]["kind"] == "start"
    # the killed session's liveliness token lingers until Zenoh notices the dead link; a
    # restart must not mistake the old token for the new process's
    wait_for(lambda: "doubler" not in driver.bus.alive_stages(RUN, timeout=0.5), 30, "the killed stage's token to go")

    # a restarted stage keeps the killed one's file and catches up from the publisher's cache
    proc, mcap_path = driver.start_stage(children, tmp_path)
    assert (mcap_path.parent / "doubler.1.mcap").exists()
    header, _ = driver.output()
    assert header.index == 0  # re-processed from history: the new process has no memory of it
    driver.put(f"ttl/{RUN}/control/doubler/stop", b"")
    assert proc.wait(20) == 0, output_of(proc)
    assert [s.header.index for s in read_recording(mcap_path).segments("telemetry")] == [0]


def test_control_messages_change_a_stage_or_are_rejected_and_recorded(driver, children, tmp_path):
    proc, mcap_path = driver.start_stage(children, tmp_path)
    control = f"ttl/{RUN}/control/doubler"
    driver.put(f"{control}/factor", b'{"factor": 3}')
    driver.put(f"{control}/factor", b'{"factor": "x"}')  # bad value: rejected
    driver.put(f"{control}/factor", b"{oops")  # not JSON: rejected
    # 1 kB nested 500 deep: the recorder's walk of it killed every stage (RecursionError)
    driver.put(f"{control}/factor", b'{"factor": ' + b"[" * 500 + b"]" * 500 + b"}")
    driver.put(f"{control}/explode", b"")  # unknown command: rejected
    wait_for(lambda: len(driver.errors) >= 4, 60, "four rejections")  # 10 s ran out under make test at load 11
    data, payload, attachment = good(0)
    driver.telemetry.put(0, payload, attachment)
    header, arrays = driver.output()
    np.testing.assert_array_equal(arrays["data"], 3 * data)  # the accepted factor holds
    rejected = [e for _, e in driver.errors]
    assert [(e["kind"], e["field"], e["key"]) for e in rejected] == [
        ("rejected", "payload", f"{control}/factor")
    ] * 3 + [("rejected", "payload", f"{control}/explode")]
    assert "factor: expected a number" in rejected[0]["message"] and "no command 'explode'" in rejected[3]["message"]
    assert "field 'payload': JSON nested 501 levels deep (at most 32)" in rejected[2]["message"]
    driver.put(f"{control}/stop", b"")
    assert proc.wait(20) == 0, output_of(proc)
    rec = read_recording(mcap_path)
    assert [(c["command"], c["accepted"]) for c in rec.json("control")] == [
        ("factor", True),
        ("factor", False),
        ("factor", False),
        ("factor", False),
        ("explode", False),
    ]
    assert rec.json("control")[0]["payload"] == {"factor": 3}


def test_no_message_content_stops_the_stage(driver, children, tmp_path):
    """A header nested 100000 deep (under the 1 MiB limit: RecursionError in Python's JSON
    parser), huge numbers, long strings, and a message whose checks raise something other
    than a CodecError: each one a recorded rejection naming the field, and the stage goes on."""
    proc, mcap_path = driver.start_stage(children, tmp_path)
    data0, p0, a0 = good(0)
    text = a0.decode()
    deep = text.replace('"meta":{}', '"meta":{"x":' + "[" * 100_000 + "]" * 100_000 + "}")
    assert len(deep) < (1 << 20) and deep != text
    driver.telemetry.put(0, p0, deep.encode())
    driver.telemetry.put(0, p0, text.replace('"meta":{}', '"meta":{"x":1e999999}').encode())
    driver.telemetry.put(0, p0, text.replace('"index":0', '"index":' + "9" * 5000).encode())
    driver.telemetry.put(0, p0, text.replace('"meta":{}', '"meta":{"s":"' + "a" * 500_000 + '"}').encode())
    _, p99, a99 = good(99)
    driver.telemetry.put(99, p99, a99)  # Doubler.expect raises LookupError
    driver.telemetry.put(0, p0, a0)  # and the stage goes on
    header, arrays = driver.output()
    assert header.index == 0
    np.testing.assert_array_equal(arrays["data"], 2 * data0)
    wait_for(lambda: len(driver.errors) >= 5, REPORTS_WITHIN, "five error reports")
    got = [(e["kind"], e["field"]) for _, e in driver.errors]
    assert got == [
        ("rejected", "header"),
        ("rejected", "meta.x"),
        ("rejected", "index"),
        ("rejected", "meta.s"),
        ("rejected", "message"),
    ], got
    assert "nested 100002 levels deep" in driver.errors[0][1]["message"]
    assert "LookupError" in driver.errors[4][1]["message"]
    assert proc.poll() is None
    driver.put(f"ttl/{RUN}/control/doubler/stop", b"")
    assert proc.wait(20) == 0, output_of(proc)
    rec = read_recording(mcap_path)
    assert [(e["kind"], e["field"]) for e in rec.json("errors")] == got
    assert rec.json("events")[-1]["kind"] == "stop"


@pytest.fixture
def small_disk(tmp_path):
    """A 3 MB tmpfs (a real file system that fills up); skipped where mounting is not allowed."""
    import subprocess

    disk = tmp_path / "disk"
    disk.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(disk)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_full_disk_stops_the_stage_and_says_so(driver, children, small_disk):
    """Recording onto a disk that fills up: the stage frees its reserve, leaves a stop note,
    reports ``disk-full`` on the bus, closes its recording and exits 4; ``ttl inspect`` names
    the cause ("disk full"), not "process killed?"."""
    from streamer.tools.inspect import format_report, inspect_run

    config = local_stage_config(RUN, driver.port, small_disk / "recordings", hold=0.0)
    proc = children.start("stage", config=config.to_dict())
    wait_alive(driver.bus, RUN, "doubler", proc, 30)
    for i in range(60):  # 128 kB recorded per segment (input and output): 2 MB free
        if proc.poll() is not None:
            break
        driver.telemetry.put(i, *good(i)[1:])
        time.sleep(0.05)
    assert proc.wait(30) == 4, output_of(proc)
    wait_for(lambda: [e for _, e in driver.errors if e["kind"] == "disk-full"], REPORTS_WITHIN, "the disk-full report")
    full = [e for _, e in driver.errors if e["kind"] == "disk-full"][0]
    assert "disk full: No space left on device" in full["message"], full
    run_dir = small_disk / "recordings" / RUN
    note = json.loads((run_dir / "doubler.mcap.stop.json").read_text())
    assert note["reason"] == "disk-full" and note["errno"] == 28, note
    assert not (run_dir / "doubler.mcap.reserve").exists()
    report = inspect_run(run_dir)
    kinds = [(i["kind"], i["message"]) for i in report["interruptions"]]
    assert [k for k, _ in kinds] == ["disk-full"], kinds
    assert "disk full" in kinds[0][1] and "killed" not in format_report(report), kinds
    rec = read_recording(run_dir / "doubler.mcap")
    assert rec.segments("tdi"), "nothing recorded before the disk filled up"
    print(f"recorded {len(rec.segments('tdi'))} segments; file complete: {rec.complete}; {kinds[0][1]}")

"""Control commands answered to their sender (``ttl control``), queued by a busy stage and
handled by its successor when it is killed before handling them (streamer.runtime.controls).

The stage is the test stage of tests/streamer/procs.py in a child process, the driver this
process (tests/streamer/runtime/test_stage.py); the commands are sent by the ``ttl control``
command line, as an operator sends them."""

import signal
import subprocess

import numpy as np
import pytest
from streamer_testutil import output_of, wait_for
from test_stage import RUN, Driver, good
from ttl_testutil import ttl_command

from streamer.recording.recorder import read_recording
from streamer.runtime.controls import due_controls

#: Seconds ``ttl control`` waits for a verdict in these tests (a Python start and a session
#: cost 1-3 s on a loaded machine: not part of the wait).
WAIT = 3.0


@pytest.fixture
def driver():
    d = Driver()
    yield d
    d.close()


def send(driver: Driver, command: str, payload: str, wait: float = WAIT) -> subprocess.CompletedProcess:
    return subprocess.run(
        ttl_command(
            "control", "doubler", command, payload, "--run", RUN,
            "--connect", f"tcp/127.0.0.1:{driver.port}", "--wait", str(wait),
        ),
        capture_output=True,
        text=True,
        timeout=120,
    )  # fmt: skip


def segment(driver: Driver, index: int, **meta) -> np.ndarray:
    data, payload, attachment = good(index, **meta)
    driver.telemetry.put(index, payload, attachment)
    return data


def test_the_verdict_goes_back_to_the_sender(driver, children, tmp_path):
    proc, mcap_path = driver.start_stage(children, tmp_path)
    ok = send(driver, "factor", '{"factor": 3}')
    assert ok.returncode == 0 and "doubler accepted factor" in ok.stdout, (ok.stdout, ok.stderr)
    bad = send(driver, "factor", '{"factor": "x"}')
    assert bad.returncode == 2 and "doubler rejected factor: factor: expected a number" in bad.stderr, bad
    deep = send(driver, "factor", '{"factor": ' + "[" * 500 + "]" * 500 + "}")
    assert deep.returncode == 2 and "nested 501 levels deep" in deep.stderr, deep
    data = segment(driver, 0)
    np.testing.assert_array_equal(driver.output()[1]["data"], 3 * data)  # the accepted factor holds
    records = read_recording(mcap_path).json("control")
    assert [(c["command"], c["state"], c["accepted"]) for c in records] == [
        ("factor", "accepted", True),
        ("factor", "rejected", False),
        ("factor", "rejected", False),
    ]
    # each record names the sender's id, which ttl control printed
    assert records[0]["id"] in ok.stdout and len({c["id"] for c in records}) == 3
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0, output_of(proc)


def test_a_busy_stage_queues_a_command_and_handles_it_after_the_segment(driver, children, tmp_path):
    proc, mcap_path = driver.start_stage(children, tmp_path)
    # busy long enough to outlast the recording's poll and the sender's start-up under load
    # (10 s was not: a fresh clone's make test at load 7 found the segment done, the command
    # accepted at once)
    segment(driver, 0, busy=25.0)
    wait_for(lambda: read_recording(mcap_path).segments("telemetry"), 30, "segment 0 taken in")
    res = send(driver, "factor", '{"factor": 3}', wait=1.0)
    # queued at once (the stage's checkpoint), no verdict within the wait: exit status 3
    assert res.returncode == 3 and "doubler queued factor (busy with segment 0)" in res.stdout, res
    assert "has not handled it within 1 s: it will" in res.stderr, res.stderr
    assert driver.output(timeout=60)[0].index == 0  # segment 0 with the factor in force before
    data = segment(driver, 1)
    np.testing.assert_array_equal(driver.output()[1]["data"], 3 * data)
    records = read_recording(mcap_path).json("control")
    assert [(c["state"], c["id"]) for c in records] == [("queued", records[0]["id"]), ("accepted", records[0]["id"])]
    assert records[0]["payload"] == {"factor": 3} and due_controls(records) == []
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0, output_of(proc)


def test_a_command_queued_by_a_stage_killed_before_handling_it_is_handled_by_its_successor(driver, children, tmp_path):
    proc, mcap_path = driver.start_stage(children, tmp_path)
    data0 = segment(driver, 0, busy=25.0)
    wait_for(lambda: read_recording(mcap_path).segments("telemetry"), 30, "segment 0 taken in")
    res = send(driver, "factor", '{"factor": 5}', wait=1.0)
    assert res.returncode == 3, res
    proc.send_signal(signal.SIGKILL)
    assert proc.wait(10) == -signal.SIGKILL
    (queued,) = due_controls(read_recording(mcap_path).json("control"))
    assert (queued.command, queued.payload) == ("factor", b'{"factor": 5}')
    wait_for(lambda: "doubler" not in driver.bus.alive_stages(RUN, timeout=0.5), 30, "the killed stage's token to go")
    proc, mcap_path = driver.start_stage(children, tmp_path)
    # the successor handles it before anything else: segment 0, again from the publisher's
    # cache (busy again), and 1 with the queued factor
    header, arrays = driver.output(timeout=90)
    assert header.index == 0, output_of(proc)
    np.testing.assert_array_equal(arrays["data"], 5 * data0)
    data = segment(driver, 1)
    np.testing.assert_array_equal(driver.output(timeout=30)[1]["data"], 5 * data)
    records = read_recording(mcap_path).json("control")
    assert [(c["state"], c["id"]) for c in records] == [("accepted", queued.id)]  # once, with its id
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0, output_of(proc)

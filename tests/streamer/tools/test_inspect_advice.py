"""Unit tests of :mod:`streamer.tools.inspect_advice`: the command ``ttl inspect`` advises, live
or offline (a run directory on disk and a real listening socket; no bus)."""

import json
import os
import shlex
import socket
import time

import pytest

from streamer.tools.inspect_advice import advise, process_alive_since, refit_command, run_state


@pytest.fixture
def router():
    """A TCP socket listening on 127.0.0.1: what a live router answers like."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(4)
        yield f"tls/127.0.0.1:{server.getsockname()[1]}"


def journal(run_dir, *records):
    run_dir.mkdir(exist_ok=True)
    (run_dir / "launcher.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records) + "not json\n")


def start(router, credentials=None, pid=None, **kw):
    rec = {"kind": "start", "router": router, "launcher_pid": pid or os.getpid(), "time": time.time(), **kw}
    if credentials is not None:
        rec["credentials"] = str(credentials)
    return rec


def test_an_ended_run_is_not_live(tmp_path, router):
    journal(tmp_path / "r1", start(router), {"kind": "end", "status": 0})
    state = run_state(tmp_path / "r1")
    assert state["live"] is False and state["control"] is False
    assert state["why"] == "ttl run ended (exit status 0)" and state["router"] == router
    # a later start without an end: the run was resumed
    journal(tmp_path / "r1", start(router), {"kind": "end", "status": 0}, start(router))
    assert run_state(tmp_path / "r1")["live"] is True


def test_a_live_run_with_its_credentials_here_takes_ttl_control(tmp_path, router):
    creds = tmp_path / "creds"
    creds.mkdir()
    journal(tmp_path / "r1", start(router, creds))
    state = run_state(tmp_path / "r1")
    assert (state["live"], state["control"]) == (True, False)  # no control.pem yet
    assert "credentials are not here" in state["why"]
    (creds / "control.pem").write_text("")
    state = run_state(tmp_path / "r1")
    assert (state["live"], state["control"]) == (True, True)
    assert f"is running; its router answers at {router}" in state["why"]


def test_a_gone_launcher_or_a_silent_router_is_not_live(tmp_path, router):
    journal(tmp_path / "r1", start(router, pid=2**22 + 12345))
    assert "is gone" in run_state(tmp_path / "r1")["why"]
    with socket.socket() as s:  # a port that nothing listens on
        s.bind(("127.0.0.1", 0))
        closed = f"tls/127.0.0.1:{s.getsockname()[1]}"
    journal(tmp_path / "r2", start(closed))
    state = run_state(tmp_path / "r2")
    assert state["live"] is False and f"no router answers at {closed}" in state["why"]
    # no journal: the address of the recorded command
    (tmp_path / "r3").mkdir()
    state = run_state(tmp_path / "r3", f"ttl control --run r3 --connect {router} fitter model '{{}}'")
    assert state["live"] is True and state["why"].startswith("no launcher journal")


def test_process_alive_since():
    assert process_alive_since(os.getpid(), time.time())
    assert not process_alive_since(os.getpid(), time.time() - 3600 * 24 * 365 * 30)  # started after that
    assert not process_alive_since("nope", None)


def test_refit_command():
    assert shlex.split(refit_command("rec/r1", ["linear-ttl", "drift"], ["linear-ttl"], [24, 47])) == [
        "ttl",
        "refit",
        "rec/r1",
        "--effects",
        "linear-ttl,drift",
        "--segments",
        "24:47",
    ]
    assert "--baseline linear-ttl,step" in refit_command("rec/r1", ["linear-ttl"], ["linear-ttl", "step"], None)


def test_advise_gives_each_diagnosis_its_command(tmp_path, router):
    model = {
        "diagnoses": [
            {
                "model": ["linear-ttl", "glitch:t0=5"],
                "effects": ["linear-ttl", "glitch:t0=5", "drift"],
                "segments": [0, 23],
                "command": f"ttl control --run r1 --connect {router} fitter model '{{}}'",
                "removal": [{"spec": "glitch:t0=5"}],
            }
        ]
    }
    journal(tmp_path / "r1", start(router), {"kind": "end", "status": 1})
    state = advise(model, tmp_path / "r1", "r1")
    assert state["live"] is False and "checked" in state
    d = model["diagnoses"][0]
    assert shlex.split(d["advice"])[:5] == [
        "ttl",
        "refit",
        str(tmp_path / "r1"),
        "--effects",
        "linear-ttl,glitch:t0=5,drift",
    ]
    assert "--effects linear-ttl " in d["removal"][0]["advice"] + " "
    # live now: ttl control with the live address
    journal(tmp_path / "r1", start(router))
    advise(model, tmp_path / "r1", "r1")
    words = shlex.split(model["diagnoses"][0]["advice"])
    assert words[:6] == ["ttl", "control", "--run", "r1", "--connect", router]
    assert json.loads(words[-1]) == {"effects": ["linear-ttl", "glitch:t0=5", "drift"]}
    assert advise({"diagnoses": []}, tmp_path / "r1", "r1") == {}


def test_advise_offline_when_live_without_the_credentials(tmp_path, router):
    model = {"diagnoses": [{"model": ["linear-ttl"], "effects": ["linear-ttl", "drift"], "segments": [0, 23]}]}
    journal(tmp_path / "r1", start(router, tmp_path / "no-credentials"))
    state = advise(model, tmp_path / "r1", "r1")
    assert (state["live"], state["control"]) == (True, False)
    assert shlex.split(model["diagnoses"][0]["advice"])[:2] == ["ttl", "refit"]

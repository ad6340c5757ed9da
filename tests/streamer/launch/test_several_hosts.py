"""Three hosts for real: network namespaces, one Zenoh router each, mutual TLS, a link cut.

Hosts (network namespaces, created and removed by the test)::

    A 198.18.1.1 ---- 198.18.1.2 B 198.18.2.2 ---- 198.18.2.3 C
    ttl run (router,                ttl router          ttl router
    replayer, monitor)              tdi_builder         fitter, subtractor

Each router listens on its own addresses (TLS only) and on 127.0.0.1 of its host; the
stages are clients of their host's router; B's router connects to A's, C's to B's.  Once
the fitter has fitted two segments, the A-B link goes down for :data:`CUT_SECONDS` and
comes back; the run must complete with every segment handled by every stage, and the fits
equal a one-host run's bit for bit.  Skipped (with the reason) where network namespaces
cannot be created (not root, no ``ip``, no CAP_NET_ADMIN).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from ttl_testutil import MONITOR, Procs, finish, output, run_args, ttl_command, wait_for

from streamer.bus import security
from streamer.recording.recorder import read_recording

pytestmark = pytest.mark.ops

SIM = "--duration 8h --orbit unequal --seed 1"
SEGMENTS = 8
CUT_SECONDS = 12.0
PORT = 7447
TAG = f"t{os.getpid() % 100000}"
NS = {h: f"{TAG}{h}" for h in "ABC"}
#: veth pairs: (end in the first host, its address), (end in the second host, its address)
LINKS = {
    "AB": (("A", f"{TAG}ab", "198.18.1.1"), ("B", f"{TAG}ba", "198.18.1.2")),
    "BC": (("B", f"{TAG}bc", "198.18.2.2"), ("C", f"{TAG}cb", "198.18.2.3")),
}


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=30)


def in_ns(host: str, *cmd: str) -> list[str]:
    return ["ip", "netns", "exec", NS[host], *cmd]


def remove_network() -> None:
    """Delete the namespaces (their veth ends go with them) and any veth end left outside."""
    for name in NS.values():
        ip("netns", "del", name, check=False)
    for (_, a, _), (_, b, _) in LINKS.values():
        for dev in (a, b):
            ip("link", "del", dev, check=False)


@pytest.fixture
def network():
    """Three namespaces joined by two veth pairs; removed afterwards, even on failure."""
    if shutil.which("ip") is None:
        pytest.skip("no 'ip' command (iproute2): cannot create network namespaces")
    probe = ip("netns", "add", NS["A"], check=False)
    if probe.returncode != 0:
        pytest.skip(f"cannot create network namespaces here ({probe.stderr.strip()}; needs root or CAP_NET_ADMIN)")
    try:
        for h in "BC":
            ip("netns", "add", NS[h])
        for h in "ABC":
            ip("-n", NS[h], "link", "set", "lo", "up")
        for (h1, d1, a1), (h2, d2, a2) in LINKS.values():
            ip("link", "add", d1, "type", "veth", "peer", "name", d2)
            for h, d, a in ((h1, d1, a1), (h2, d2, a2)):
                ip("link", "set", d, "netns", NS[h])
                ip("-n", NS[h], "addr", "add", f"{a}/24", "dev", d)
                ip("-n", NS[h], "link", "set", d, "up")
        yield
    finally:
        remove_network()
        left = ip("netns", "list").stdout
        assert not any(name in left for name in NS.values()), left


def endpoint(address: str) -> str:
    return f"tls/{address}:{PORT}"


LOCAL = endpoint("127.0.0.1")


def fits(run_dir: Path) -> dict:
    rec = read_recording(run_dir / "fitter.mcap")
    return {m.header.index: {k: np.asarray(v) for k, v in m.arrays.items()} for m in rec.segments("fit")}


def stage_config(path: Path, run: str, stage: str, rec: Path, creds: Path) -> Path:
    """The configuration ttl run would give the stage (same cache), connecting to its host's router."""
    path.write_text(
        json.dumps(
            {
                "run": run,
                "stage": stage,
                "recordings": str(rec),
                "cache": 8,
                "record_inputs": stage == "tdi_builder",
                "zenoh": {"mode": "client", "connect": [LOCAL], "credentials": str(creds), "identity": stage},
            }
        )
    )
    return path


def done(out: str, stage: str) -> int:
    counts = re.findall(rf"{stage} (\d+)/{SEGMENTS}", out)
    return int(counts[-1]) if counts else 0


def test_three_hosts_with_a_cut_link_equal_one_host(network, tmp_path):
    procs = Procs(tmp_path)
    rec = tmp_path / "rec"
    skip = [] if MONITOR else ["--skip", "monitor"]
    try:
        # the reference: every stage on one host (the root namespace, loopback)
        one = procs.start(
            ttl_command(*run_args("one", rec, *skip, sim=SIM, timeout=500)),
            "one",
        )
        assert finish(one, 600) == 0, output(one)[-3000:]

        creds = security.ensure_credentials(
            tmp_path / "creds", hosts=[a for pair in LINKS.values() for _, _, a in pair]
        )
        # hosts B and C: routers (to the previous host) and their stages, up before the run starts
        _start_routers(procs, creds)
        remote = {"tdi_builder": "B", "fitter": "C", "subtractor": "C"}
        stages = {}
        for stage, host in remote.items():
            cfg = stage_config(tmp_path / f"{stage}.json", "three", stage, rec, creds)
            stages[stage] = procs.start(in_ns(host, *ttl_command("stage", stage, "--config", str(cfg))), stage)
        run = procs.start(
            in_ns(
                "A",
                *ttl_command(
                    *run_args("three", rec, "--credentials", str(creds), sim=SIM, timeout=500),
                    "--listen",
                    LOCAL,
                    "--listen",
                    endpoint("198.18.1.1"),
                    "--external",
                    ",".join(remote),
                    *skip,
                ),
            ),
            "three",
        )
        wait_for(lambda: done(output(run), "fitter") >= 2 or run.poll() is not None, 400, "two fits on host C")
        assert run.poll() is None, output(run)[-3000:]
        (_, a_dev, _), _ = LINKS["AB"]
        ip("-n", NS["A"], "link", "set", a_dev, "down")  # host A loses host B (and C behind it)
        time.sleep(CUT_SECONDS)
        cut_at = done(output(run), "fitter")
        still_running = run.poll() is None
        ip("-n", NS["A"], "link", "set", a_dev, "up")
        code = finish(run, 600)
        out = output(run)
        assert code == 0 and f"done: {SEGMENTS} segments" in out, out[-3000:]
        assert still_running and cut_at < SEGMENTS, f"the run ended before the link came back ({cut_at} fits)"
        for stage, proc in stages.items():  # the stop reached the remote stages too
            assert finish(proc, 60) == 0, (stage, output(proc)[-2000:])

        # every segment arrived everywhere, and the results are the one-host run's
        _check_same_as_one_host(rec / "one", rec / "three")
    finally:
        procs.close()


def _start_routers(procs: Procs, creds) -> None:
    """The routers of hosts B (to A) and C (to B), listening on their links and loopback."""
    for host, listen, connect in (
        ("B", ("198.18.1.2", "198.18.2.2"), "198.18.1.1"),
        ("C", ("198.18.2.3",), "198.18.2.2"),
    ):
        listens = [a for address in (LOCAL, *map(endpoint, listen)) for a in ("--listen", address)]
        router = ttl_command("router", "--credentials", str(creds), *listens, "--connect", endpoint(connect))
        procs.start(in_ns(host, *router), f"router-{host}")


def _check_same_as_one_host(one_dir, three_dir) -> None:
    """Every segment arrived at every remote stage, the fits and residuals are the one-host
    run's bit for bit, and the routers refused nothing of the run's own stages."""
    for stage, topic in {"tdi_builder": "tdi", "fitter": "fit", "subtractor": "residual"}.items():
        got = sorted(m.header.index for m in read_recording(three_dir / f"{stage}.mcap").segments(topic))
        assert got == list(range(SEGMENTS)), (stage, got)
    a, b = fits(one_dir), fits(three_dir)
    assert sorted(a) == sorted(b) == list(range(SEGMENTS))
    for i in a:
        for k in a[i]:
            np.testing.assert_array_equal(a[i][k], b[i][k], err_msg=f"fit {i} {k}")
    ra = read_recording(one_dir / "subtractor.mcap").segments("residual")
    rb = read_recording(three_dir / "subtractor.mcap").segments("residual")
    for x, y in zip(ra, rb):
        for k in x.arrays:
            np.testing.assert_array_equal(np.asarray(x.arrays[k]), np.asarray(y.arrays[k]))
    # the routers refused nothing of the run's own stages
    refused = (three_dir / "security.jsonl").read_text()
    assert refused == "", refused[:2000]

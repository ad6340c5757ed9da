"""Authentication and access control (streamer.bus.security): real routers, real TLS.

* credentials: a CA and one certificate per role, keys 0600, made once, the router
  certificate reissued when a host is added;
* a ``ttl router --credentials`` process: a stage's certificate publishes its own topic;
  another stage's certificate publishing telemetry, fits, progress or stop, a peer with no
  certificate, one with another CA's certificate and a plain TCP peer are all refused,
  nothing of theirs reaches a subscriber, and the router's log records each refusal;
* (``ops``) the same intruders against a live ``ttl run``: the run completes, every
  refusal is in ``security.jsonl``, and the fits equal a clean run's bit for bit.
"""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID
from ttl_testutil import MONITOR, Procs, finish, output, run_args, ttl_command, wait_for

from streamer.bus import security
from streamer.bus.codec import CodecError, parse_header
from streamer.bus.session import Bus, SessionSettings, free_port
from streamer.recording.recorder import read_recording

INTRUDER = Path(__file__).parents[1] / "intruder.py"


def common_name(path: Path) -> str:
    cert = x509.load_pem_x509_certificate(path.read_bytes())
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value


def test_credentials_are_made_once_with_private_keys(tmp_path):
    d = security.ensure_credentials(tmp_path / "creds")
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    for role in security.ROLES:
        assert common_name(d / f"{role}.pem") == role
        assert stat.S_IMODE((d / f"{role}.key").stat().st_mode) == 0o600, role
    assert stat.S_IMODE((d / "ca.key").stat().st_mode) == 0o600
    assert security._cert_hosts(x509.load_pem_x509_certificate((d / "router.pem").read_bytes())) == {
        "127.0.0.1",
        "localhost",
    }
    assert security._cert_hosts(x509.load_pem_x509_certificate((d / "fitter.pem").read_bytes())) == set()
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    security.ensure_credentials(d)
    assert {p.name: p.read_bytes() for p in d.iterdir()} == before  # nothing reissued
    security.ensure_credentials(d, hosts=("198.18.0.1",))  # a router host added: only its certificate changes
    after = {p.name: p.read_bytes() for p in d.iterdir()}
    assert [n for n in before if before[n] != after[n]] == ["router.key", "router.pem"] or sorted(
        n for n in before if before[n] != after[n]
    ) == ["router.key", "router.pem"]
    assert "198.18.0.1" in security._cert_hosts(x509.load_pem_x509_certificate(after["router.pem"]))
    # a stage host holds no CA key: it cannot issue certificates, and says which file is missing
    (d / "ca.key").unlink()
    (d / "monitor.pem").unlink()
    with pytest.raises(security.CredentialsError, match="ca.key"):
        security.ensure_credentials(d)
    os.chmod(d / "fitter.key", 0o644)
    with pytest.raises(security.CredentialsError, match="fitter.key.*readable by others"):
        security.Identity(d, "fitter").check()


def foreign_certificate(tmp_path: Path) -> str:
    """A ``fitter`` certificate of another CA (prefix of its .pem/.key)."""
    other = security.ensure_credentials(tmp_path / "other-ca", roles=("fitter",))
    return str(other / "fitter")


def stranger_certificate(tmp_path: Path) -> str:
    """A ``fitter`` certificate of a CA of another name (prefix of its .pem/.key; its CA in
    ``ca.pem`` beside it)."""
    original = security._name
    security._name = lambda cn: original(f"stranger {cn}")
    try:
        other = security.ensure_credentials(tmp_path / "stranger-ca", roles=("fitter",))
    finally:
        security._name = original
    return str(other / "fitter")


def intruders(procs: Procs, tmp_path: Path, creds: Path, endpoint: str, run: str, duration: float) -> dict:
    """Start the six intruders; returns name -> (process, report path).  The last two trust
    another CA than the run's, so they refuse the router's certificate themselves (the
    router logs the alert they send: DecryptError for a CA of the same name, UnknownCA)."""
    base = {"run": run, "endpoint": endpoint, "duration": duration, "ca": str(creds / "ca.pem")}
    foreign, stranger = foreign_certificate(tmp_path), stranger_certificate(tmp_path)
    kinds = {
        "other-stage": {"credentials": str(creds), "identity": "subtractor"},
        "no-certificate": {},
        "foreign-ca": {"foreign": foreign},
        "plain-tcp": {"plain": True},
        "trusts-foreign-ca": {"foreign": foreign, "ca": str(Path(foreign).with_name("ca.pem"))},
        "trusts-stranger-ca": {"foreign": stranger, "ca": str(Path(stranger).with_name("ca.pem"))},
    }
    out = {}
    for name, extra in kinds.items():
        report = tmp_path / f"{name}.json"
        proc = procs.start([sys.executable, str(INTRUDER), json.dumps({**base, **extra, "out": str(report)})], name)
        out[name] = (proc, report)
    return out


def check_intruders(started: dict) -> dict:
    reports = {}
    for name, (proc, report) in started.items():
        assert finish(proc, 120) == 0, output(proc)
        reports[name] = json.loads(report.read_text())
    # only the holder of a certificate of the run's CA gets in (and is then bound by the ACL)
    assert reports["other-stage"]["connected"] and reports["other-stage"]["puts"] > 0
    assert reports["other-stage"]["answers"] == 0  # its commands to the fitter never reached it
    for name in ("no-certificate", "foreign-ca", "plain-tcp", "trusts-foreign-ca", "trusts-stranger-ca"):
        assert not reports[name]["connected"], (name, reports[name])
    return reports


def check_refusals(refused: list[dict], run: str) -> None:
    forbidden = {(r["subject"], r["key"]) for r in refused if r["kind"] == "forbidden"}
    for key in (
        f"ttl/{run}/telemetry",
        f"ttl/{run}/fit",
        f"ttl/{run}/control/progress/replayer",
        f"ttl/{run}/control/stop",
        f"ttl/{run}/control/fitter/model",  # asked as ttl control asks: a command all the same
    ):
        assert ("subtractor", key) in forbidden, (key, sorted(forbidden)[:20])
    assert {s for s, _ in forbidden} == {"subtractor"}, forbidden  # no genuine message refused
    unauth = [r["message"] for r in refused if r["kind"] == "unauthenticated"]
    assert any("invalid peer certificate" in m for m in unauth), unauth  # the foreign CA
    assert any("corrupt message" in m for m in unauth), unauth  # plain TCP on the TLS port
    assert any("no certificate" in m.lower() or "certificaterequired" in m.lower().replace(" ", "") for m in unauth), (
        unauth
    )  # a TLS peer without certificate
    assert any("fatal alert: DecryptError" in m for m in unauth), unauth  # a peer trusting a same-named CA
    assert any("fatal alert: UnknownCA" in m for m in unauth), unauth  # a peer trusting another CA


def test_router_refuses_and_records_intruders(tmp_path):
    creds = security.ensure_credentials(tmp_path / "creds")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    procs = Procs(tmp_path)
    try:
        router = procs.ttl("router", "--credentials", str(creds), "--listen", endpoint, name="router")
        wait_for(lambda: "listening on" in output(router) or router.poll() is not None, 60, "the router")
        assert router.poll() is None, output(router)
        got: queue.Queue = queue.Queue()
        with (
            Bus.open(
                SessionSettings(mode="client", connect=(endpoint,), credentials=creds, identity="monitor")
            ) as reader,
            Bus.open(
                SessionSettings(mode="client", connect=(endpoint,), credentials=creds, identity="fitter")
            ) as fitter,
        ):
            reader.subscriber("ttl/r1/**", lambda s: got.put((str(s.key_expr), s.payload.to_bytes())))
            time.sleep(0.5)
            started = intruders(procs, tmp_path, creds, endpoint, "r1", duration=3.0)
            fitter.session.put("ttl/r1/fit", b"genuine")  # a stage publishes its own topic
            check_intruders(started)
            time.sleep(0.5)
            received = []
            while not got.empty():
                received.append(got.get())
        assert received == [("ttl/r1/fit", b"genuine")], received[:5]
        router.send_signal(signal.SIGTERM)
        assert finish(router, 20) == 0, output(router)
        log = output(router)
        check_refusals(security.refusals(log.splitlines()), "r1")
        assert " is authorized to " not in log  # allowed messages are not logged one by one
        # and a Zenoh router listening on the TLS endpoint only, on loopback
    finally:
        procs.close()


# ---------------------------------------------------------------------------- a live run under attack

SIM = "--duration 6h --orbit unequal --seed 1"
SEGMENTS = 6
NO_MONITOR = [] if MONITOR else ["--skip", "monitor"]


def run_cmd(run: str, rec: Path, *extra) -> list[str]:
    return ttl_command(*run_args(run, rec, *NO_MONITOR, *extra, sim=SIM, timeout=400))


def fits(run_dir: Path) -> dict[int, dict]:
    rec = read_recording(run_dir / "fitter.mcap")
    return {m.header.index: {k: np.asarray(v) for k, v in m.arrays.items()} for m in rec.segments("fit")}


@pytest.mark.ops
def test_intruders_against_a_live_run_change_nothing(tmp_path):
    procs = Procs(tmp_path)
    try:
        clean = procs.start(run_cmd("clean", tmp_path / "rec"), "clean")
        assert finish(clean, 500) == 0, output(clean)[-3000:]
        attacked = procs.start(run_cmd("attacked", tmp_path / "rec"), "attacked")
        wait_for(
            lambda: re.search(r"router on (tls/\S+?)[ ;]", output(attacked)) or attacked.poll() is not None,
            120,
            "the run's router",
        )
        endpoint = re.search(r"router on (tls/\S+?)[ ;]", output(attacked)).group(1)
        creds = tmp_path / "rec" / "attacked" / "credentials"
        started = intruders(procs, tmp_path, creds, endpoint, "attacked", duration=20.0)
        check_intruders(started)
        code = finish(attacked, 500)
        out = output(attacked)
        assert code == 0 and f"done: {SEGMENTS} segments" in out, out[-3000:]
        assert "refusal(s) by the router" in out and "refused: subtractor may not Put" in out, out[-3000:]
        refused = [
            json.loads(line) for line in (tmp_path / "rec" / "attacked" / "security.jsonl").read_text().splitlines()
        ]
        check_refusals(refused, "attacked")
        # the clean run refused nothing, and the attacked run's results are the clean run's
        assert (tmp_path / "rec" / "clean" / "security.jsonl").read_text() == ""
        a, b = fits(tmp_path / "rec" / "clean"), fits(tmp_path / "rec" / "attacked")
        assert sorted(a) == sorted(b) == list(range(SEGMENTS))
        for i in a:
            assert a[i].keys() == b[i].keys()
            for k in a[i]:
                np.testing.assert_array_equal(a[i][k], b[i][k], err_msg=f"fit {i} {k}")
        for stage in ("tdi_builder", "fitter", "subtractor"):
            assert read_recording(tmp_path / "rec" / "attacked" / f"{stage}.mcap").json("errors") == [], stage
        # the keys stayed private, and nothing but the router listens, on loopback only
        for key in creds.glob("*.key"):
            assert stat.S_IMODE(key.stat().st_mode) == 0o600, key
    finally:
        procs.close()


def test_credentials_make_every_link_mutual_tls_and_routers_enforce_the_acl(tmp_path):
    from streamer_testutil import ROOT

    from streamer.bus.session import SessionConfigError, _get, make_config

    creds = security.ensure_credentials(tmp_path / "creds")
    stage = make_config(
        SessionSettings(mode="client", connect=("tls/127.0.0.1:7447",), credentials=creds, identity="fitter")
    )
    tls = _get(stage, "transport/link/tls")
    assert tls["enable_mtls"] and tls["connect_certificate"].endswith("fitter.pem") and tls["verify_name_on_connect"]
    assert _get(stage, "transport/link/protocols") == ["tls"] and _get(stage, "listen/endpoints") == []
    assert not (_get(stage, "access_control") or {}).get("enabled")  # a client enforces nothing
    # the example router of a deployment: TLS endpoints, and the pipeline's ACL added
    router = make_config(
        SessionSettings(config_file=ROOT / "streamer/configs/router.json5", credentials=creds, identity="router")
    )
    assert all(e.startswith("tls/") for e in _get(router, "listen/endpoints") + _get(router, "connect/endpoints"))
    assert _get(router, "transport/link/tls/listen_certificate") == str((creds / "router.pem").resolve())
    acl = _get(router, "access_control")
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert {s["cert_common_names"][0] for s in acl["subjects"]} == set(security.ROLES)
    # a peer with credentials listens on TLS, on loopback only; plain endpoints are refused
    peer = make_config(SessionSettings(credentials=creds, identity="router"))
    assert [e.split(":")[0] for e in _get(peer, "listen/endpoints")] == ["tls/127.0.0.1"]
    with pytest.raises(SessionConfigError, match="tcp/127.0.0.1:7447.*tls/127.0.0.1:7447"):
        make_config(
            SessionSettings(mode="client", connect=("tcp/127.0.0.1:7447",), credentials=creds, identity="fitter")
        )
    with pytest.raises(SessionConfigError, match="identity"):
        make_config(SessionSettings(mode="client", credentials=creds))
    with pytest.raises(SessionConfigError, match="nobody.pem: missing"):
        make_config(SessionSettings(mode="client", credentials=creds, identity="nobody"))


def test_router_needs_credentials_or_insecure(tmp_path):
    r = subprocess.run(ttl_command("router", "--listen", "tcp/127.0.0.1:1"), capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "--credentials" in r.stderr and "--insecure" in r.stderr, r.stderr
    r = subprocess.run(
        ttl_command(
            "run",
            "--simulate",
            "--duration 1h",
            "--run-id",
            "x",
            "--listen",
            "tcp/127.0.0.1:7447",
            "--recordings",
            str(tmp_path),
        ),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode != 0 and "tls/127.0.0.1:7447" in r.stderr and "--insecure" in r.stderr, r.stderr


def test_refusals_are_read_from_zenoh_log_lines():
    # the formats of zenoh 1.10 (access_control at trace level, zenoh_link_tls at debug/warn)
    zid = "4760c7ae5a5a15441e795c87c7f0e941"
    subject = f"Interface(lo)+CertCommonName(monitor)+Transport(Tls)+{zid}"
    head = "2026-11-23T21:38:19.46{}Z TRACE  rx-0 ThreadId(09) zenoh::net::routing::interceptor::access_control: "
    lines = [
        head.format(1) + "ACL (ingress): caching permissions for `ttl/r1/fit/0` ...",
        head.format(2) + f"{zid} on {subject} is unauthorized to Put (ingress) on ttl/r1/fit/0",  # precomputed
        head.format(3) + f"{zid} on {subject} is unauthorized to Put (ingress) on ttl/r1/telemetry/3",
        head.format(4) + f"Using cached result: {zid} is unauthorized to Put (ingress) on ttl/r1/fit/0",
        head.format(5) + f"{zid} on {subject} is authorized to Put (egress) on ttl/r1/fit/0",
        "2026-11-23T21:39:34.12Z  WARN acc-0 ThreadId(05) zenoh_link_tls::unicast: peer sent no certificates. "
        "Hint: increase the system open file limit.",
        # a peer refusing the router's certificate (it trusts another CA), as zenoh 1.10 logs it
        "\x1b[2m2026-11-26T03:44:32.188356Z\x1b[0m \x1b[33m WARN\x1b[0m acc-0 ThreadId(05) \x1b[2mzenoh_link_tls::unicast"
        "\x1b[0m\x1b[2m:\x1b[0m received fatal alert: DecryptError. Hint: increase the system open file limit.",
        "2026-11-26T03:44:33.19Z  WARN acc-0 ThreadId(05) zenoh_link_tls::unicast: received fatal alert: UnknownCA. "
        "Hint: increase the system open file limit.",
    ]
    got = security.refusals(lines)
    assert [(r["kind"], r.get("subject"), r.get("key")) for r in got] == [
        ("forbidden", "monitor", "ttl/r1/telemetry/3"),
        ("forbidden", "monitor", "ttl/r1/fit/0"),
        ("unauthenticated", None, None),
        ("unauthenticated", None, None),
        ("unauthenticated", None, None),
    ]
    assert [r["message"] for r in got[2:]] == [
        "peer sent no certificates",
        "received fatal alert: DecryptError",
        "received fatal alert: UnknownCA",
    ]
    assert got[3]["time"] == "2026-11-26T03:44:32.188356Z"


@pytest.mark.ops
def test_insecure_run_is_plain_tcp_and_says_so(tmp_path):
    r = subprocess.run(
        ttl_command(
            "run",
            "--simulate",
            "--duration 1h",
            "--segment",
            "30min",
            "--run-id",
            "ins",
            "--recordings",
            str(tmp_path),
            "--insecure",
            "--skip",
            "monitor",
            "--timeout",
            "120",
        ),
        capture_output=True,
        text=True,
        timeout=200,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "--insecure: no TLS, no access control" in r.stderr and "router on tcp/127.0.0.1:" in r.stderr
    assert not (tmp_path / "ins" / "credentials").exists() and not (tmp_path / "ins" / "security.jsonl").exists()


# ---------------------------------------------------------------------------- hostile content from every identity

#: Consumers of each topic (who must record every hostile message on it).
CONSUMERS = {
    "telemetry": ("tdi_builder", "monitor"),
    "tdi": ("fitter", "subtractor", "monitor"),
    "fit": ("subtractor", "monitor"),
    "residual": ("monitor",),
}
JSON_VALUES = [None, True, False, 0, -1, 2**63, 1.5, -1e308, "", "x", "<f8", [], [1], [[]], ["a"], {}, {"a": 1}]


def _with_text(attachment: bytes, old: str, new: str) -> bytes:
    text = attachment.decode()
    assert old in text, old
    return text.replace(old, new, 1).encode()


def hostile_variants(payload: bytes, attachment: bytes):
    """(kind, payload, attachment) of hostile messages built from a genuine one: parsing
    bombs, every JSON type in every header and array field, and a conflicting copy."""
    import zlib

    header = json.loads(attachment)
    small = payload if len(payload) <= 65536 else b""  # the every-type cases need no big payload
    meta = '"meta":' + json.dumps(header["meta"], separators=(",", ":"))
    compact = json.dumps(header, separators=(",", ":")).encode()
    yield "deep", b"", _with_text(compact, meta, '"meta":{"x":' + "[" * 100_000 + "]" * 100_000 + "}")
    yield "deep-33", b"", _with_text(compact, meta, '"meta":{"x":' + "[" * 32 + "]" * 32 + "}")
    yield "huge-exponent", small, _with_text(compact, meta, '"meta":{"x":1e999999}')
    yield "huge-exponent-t0", small, _with_text(compact, f'"t0":{json.dumps(header["t0"])}', '"t0":-1e400')
    yield "huge-int", small, _with_text(compact, f'"index":{header["index"]}', '"index":' + "9" * 5000)
    yield "long-string", b"", _with_text(compact, meta, '"meta":{"s":"' + "a" * 900_000 + '"}')
    yield (
        "long-name",
        small,
        _with_text(compact, f'"producer":"{header["producer"]}"', '"producer":"' + "p" * 5000 + '"'),
    )
    for name in header:
        for value in JSON_VALUES:
            yield "every-type", small, json.dumps({**header, name: value}).encode()
    for name in header["arrays"][0]:
        for value in JSON_VALUES:
            arrays = [dict(header["arrays"][0], **{name: value})] + header["arrays"][1:]
            yield "every-type", small, json.dumps({**header, "arrays": arrays}).encode()
    # a different copy of a segment every stage has used: a conflict, the first copy kept
    altered = bytearray(payload)
    altered[-1] ^= 0x01
    yield (
        "conflict-after-use",
        bytes(altered),
        json.dumps({**header, "checksum": f"crc32:{zlib.crc32(bytes(altered)) & 0xFFFFFFFF:08x}"}).encode(),
    )


@pytest.mark.ops
def test_hostile_content_from_each_identity_changes_nothing(tmp_path):
    """With each stage's own certificate (the access control lets it publish its topic, its
    errors and its progress), hostile content: headers nested 100000 deep, huge exponents and
    integers, long strings, every JSON type in every field, a conflicting copy of a segment
    already used; error and progress messages nested 100000 deep; and from the launcher's
    certificate, control messages of the same kind.  No stage crashes or stalls, every
    message is recorded by every stage it reached, the fits and residuals are the clean
    run's bit for bit, and ``ttl run`` exits 1 for the conflicting copies."""
    procs = Procs(tmp_path)
    rec = tmp_path / "rec"
    port = free_port()
    sent: dict[str, int] = {}
    try:
        clean = procs.start(run_cmd("clean", rec), "clean")
        assert finish(clean, 500) == 0, output(clean)[-3000:]
        # paced (a segment every 12 s): the attack meets the run in progress
        attacked = procs.start(run_cmd("hostile", rec, "--listen", f"tls/127.0.0.1:{port}", "--pace", "300"), "hostile")
        endpoint = f"tls/127.0.0.1:{port}"
        wait_for(lambda: "router on" in output(attacked) or attacked.poll() is not None, 120, "the run's router")
        code = _attack(attacked, endpoint, rec / "hostile" / "credentials", sent)
        out = output(attacked)
    finally:
        procs.close()
    print(json.dumps(sent))
    assert "died" not in out, out[-4000:]
    assert code == 1 and "conflicting copies of" in out and "gave up" not in out and "did not handle" not in out, out[
        -4000:
    ]
    run_dir = rec / "hostile"
    for topic, consumers in CONSUMERS.items():
        for stage in consumers:
            _check_hostile_recorded(run_dir / f"{stage}.mcap", stage, topic, sent[topic])
    # the verdicts (a fitter inside a diagnosis records a command "queued" first)
    control = [c for c in read_recording(run_dir / "fitter.mcap").json("control") if c["state"] != "queued"]
    assert [c["accepted"] for c in control] == [False, False, False], control
    _check_same_as_clean(rec / "clean", run_dir)


def _attack(attacked, endpoint: str, creds, sent: dict) -> int:
    """Once segment 1 of every topic is published and the monitor is past it, the hostile
    content sent with each stage's certificate and the launcher's (``sent``: counts by topic
    and by topic/kind); returns the exit code of the attacked run."""
    from streamer.bus.keys import control_key

    genuine: dict[str, dict] = {t: {} for t in CONSUMERS}

    def keep(topic, sample) -> None:
        """The first copy of each segment (this reader also sees the hostile ones sent
        below, which the codec refuses: they are not kept)."""
        try:
            index = parse_header(sample.attachment, str(sample.key_expr)).index
        except CodecError:
            return
        genuine[topic].setdefault(index, (sample.payload.to_bytes(), sample.attachment.to_bytes()))

    with Bus.open(SessionSettings(mode="client", connect=(endpoint,), credentials=creds, identity="monitor")) as reader:
        for topic in CONSUMERS:
            reader.subscriber(f"ttl/hostile/{topic}", lambda s, t=topic: keep(t, s))
        # segment 1 of every topic published, and (progress) used by every consumer
        wait_for(
            lambda: all(1 in g for g in genuine.values()) or attacked.poll() is not None,
            600,
            "segment 1 of every topic",
        )
        wait_for(
            lambda: "monitor 2/" in output(attacked) or attacked.poll() is not None,
            600,
            "the monitor past segment 1",
        )
        assert attacked.poll() is None, output(attacked)[-3000:]
        for stage, topic in (
            ("replayer", "telemetry"),
            ("tdi_builder", "tdi"),
            ("fitter", "fit"),
            ("subtractor", "residual"),
        ):
            _send_hostile(endpoint, creds, stage, topic, genuine[topic][1], sent)
        with Bus.open(
            SessionSettings(mode="client", connect=(endpoint,), credentials=creds, identity="launcher")
        ) as bus:
            for payload in (
                b'{"effects":' + b"[" * 100_000 + b"]" * 100_000 + b"}",
                b'{"effects": [1e999999]}',
                b'{"effects": ["' + b"a" * 900_000 + b'"]}',
            ):
                bus.session.put(control_key("hostile", "fitter", "model"), payload)
        return finish(attacked, 600)


def _send_hostile(endpoint: str, creds, stage: str, topic: str, first: tuple, sent: dict) -> None:
    """With ``stage``'s certificate, the hostile variants of segment 1 of ``topic`` (``first``:
    its payload and attachment) and error and progress messages nested 100000 deep."""
    from streamer.bus.keys import errors_key, progress_key

    with Bus.open(SessionSettings(mode="client", connect=(endpoint,), credentials=creds, identity=stage)) as bus:
        put = bus.session.put
        for kind, payload, attachment in hostile_variants(*first):
            put(
                f"ttl/hostile/{topic}",
                payload,
                attachment=attachment,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            sent[topic] = sent.get(topic, 0) + 1
            sent[f"{topic}/{kind}"] = sent.get(f"{topic}/{kind}", 0) + 1
            time.sleep(0.002)
        bomb = b'{"stage":' + b"[" * 100_000 + b"]" * 100_000 + b"}"
        put(errors_key("hostile", 1), bomb)
        put(progress_key("hostile", stage), bomb)


def _check_hostile_recorded(path, stage: str, topic: str, n_sent: int) -> None:
    """A consumer's recording holds every hostile message on ``topic`` it reached (``n_sent``
    sent) as a rejection, a conflict or a duplicate, no failure, the conflicting copies with
    the first used, and the deep nesting named."""
    r = read_recording(path)
    assert r.complete and r.problem is None, stage
    errors = r.json("errors")
    on_topic = [
        e
        for e in errors
        if (e.get("key") or "").split("/")[2:3] == [topic] and e["kind"] in ("rejected", "forged", "conflict")
    ]
    dups = [e for e in r.json("events") if e["kind"] == "duplicate" and f"/{topic}/" in e["message"]]
    assert len(on_topic) + len(dups) >= n_sent, (stage, topic, len(on_topic), len(dups), n_sent)
    assert not [e for e in errors if e["kind"] == "failed"], (
        stage,
        [e for e in errors if e["kind"] == "failed"][:3],
    )
    conflicts = [e for e in on_topic if e["kind"] == "conflict" and e["field"] == "payload"]
    assert conflicts and all(e["details"]["first_copy"] == "used" for e in conflicts), (stage, conflicts[:3])
    deep = [e for e in on_topic if "levels deep" in e["message"]]
    assert deep, (stage, topic)


def _check_same_as_clean(clean_dir, run_dir) -> None:
    """The attacked run's fits and residuals are the clean run's bit for bit."""
    a, b = fits(clean_dir), fits(run_dir)
    assert sorted(a) == sorted(b) == list(range(SEGMENTS))
    for i in a:
        for k in a[i]:
            np.testing.assert_array_equal(a[i][k], b[i][k], err_msg=f"fit {i} {k}")
    residual = {}
    for name, path in (("clean", clean_dir), ("hostile", run_dir)):
        residual[name] = {
            s.header.index: s.arrays for s in read_recording(path / "subtractor.mcap").segments("residual")
        }
    assert sorted(residual["clean"]) == sorted(residual["hostile"]) == list(range(SEGMENTS))
    for i, arrays in residual["clean"].items():
        for k, v in arrays.items():
            np.testing.assert_array_equal(v, residual["hostile"][i][k], err_msg=f"residual {i} {k}")

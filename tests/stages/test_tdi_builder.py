"""The tdi_builder stage as a real process, fed crafted telemetry messages over Zenoh."""

import json
import queue
import signal
import time

import numpy as np
import pytest
from mcap.reader import make_reader
from ttl_testutil import indices, output, wait_alive, wait_for

from stages.tdi_builder import rebuilt_copy
from streamer.bus.codec import Expect, decode, encode
from streamer.bus.keys import topic_pattern
from streamer.bus.session import Bus, SessionSettings, free_port
from streamer.recording.recorded_inputs import recorded_copies, wire_copy
from streamer.recording.recorder import Recorder, read_recording
from streamer.recording.recording_reader import RecordingError
from ttlcore.conventions import COEFFICIENT_NAMES, LINKS
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.data import TDIStream

RUN = "tdi-stage"
FS = 4.0
N = 2400  # 10 min segments


def telemetry(index: int) -> Telemetry:
    """Crafted telemetry (the stage does not care about physics): noise and ~8.3 s delays."""
    rng = np.random.default_rng(100 + index)
    ltt = 8.3 + 0.01 * np.arange(6)[:, None] + np.zeros((6, N))
    return Telemetry(
        t0=index * N / FS,
        fs=FS,
        eta=1e-14 * rng.standard_normal((6, N)),
        dws_phi=1e-9 * rng.standard_normal((6, N)),
        dws_eta=1e-9 * rng.standard_normal((6, N)),
        ltt=ltt,
    )


def message(index: int, tm: Telemetry | None = None, **changes):
    tm = tm or telemetry(index)
    arrays = {"eta": tm.eta, "dws_phi": tm.dws_phi, "dws_eta": tm.dws_eta, "ltt": tm.ltt}
    arrays.update(changes.pop("arrays", {}))
    fields = {
        "run": RUN,
        "index": index,
        "t0": tm.t0,
        "fs": tm.fs,
        "channels": list(LINKS),
        "producer": "test",
        "meta": {"segments_total": 4, "segment_duration": N / FS, "source": "crafted", "truth": None},
    }
    fields.update(changes)
    return encode(arrays, fields, allow_nonfinite=True)


def test_tdi_builder_ignores_duplicates_reports_malformed_and_goes_on(procs, tmp_path):
    port = free_port()
    outputs, errors = queue.Queue(), []
    with Bus.open(SessionSettings(listen=(f"tcp/127.0.0.1:{port}",))) as bus:
        bus.segment_subscriber(
            topic_pattern(RUN, "tdi"),
            lambda s: outputs.put((str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes())),
            history=0,
        )
        bus.subscriber(f"ttl/{RUN}/errors/*", lambda s: errors.append(json.loads(s.payload.to_bytes())))
        pub = bus.segment_publisher(RUN, "telemetry", cache=8)
        stage = _start_tdi_builder(procs, bus, port, tmp_path)

        def got(timeout=20):
            key, payload, attachment = outputs.get(timeout=timeout)
            return decode(payload, attachment, Expect(allow_nonfinite=True), key=key)

        got_all = _feed_good_bad_and_duplicates(pub, got)
        with pytest.raises(queue.Empty):
            got(timeout=1.0)  # nothing twice
        _check_streaming_tdi(got_all)

        wait_for(lambda: len([e for e in errors if e["kind"] in ("rejected", "forged")]) >= 7, 10, "seven rejections")
        rejected = [(e["index"], e["field"]) for e in errors if e["kind"] in ("rejected", "forged")]
        # an unreadable header: the index is unknown (the stream key ttl/<run>/telemetry carries none)
        assert rejected == [
            (None, "header"),
            (1, "arrays[eta].shape"),
            (1, "arrays[eta]"),
            (1, "payload"),
            (1, "arrays[ltt].shape"),
            (1, "fs"),
            (1, "producer"),
        ], rejected
        assert not [e for e in errors if e["kind"] == "failed"]
        assert all(e["stage"] == "tdi_builder" for e in errors)

        stage.send_signal(signal.SIGTERM)
        assert stage.wait(30) == 0, output(stage)

    _check_tdi_builder_recording(tmp_path / "rec" / RUN / "tdi_builder.mcap", rejected)
    _check_rebuilt_copies(tmp_path / "rec" / RUN, got_all)


def _start_tdi_builder(procs, bus, port: int, tmp_path):
    """The tdi_builder started on the router at ``port``, once its liveliness token is seen."""
    stage = procs.stage(
        "tdi_builder",
        "--run",
        RUN,
        "--connect",
        f"tcp/127.0.0.1:{port}",
        "--recordings",
        tmp_path / "rec",
        "--settle",
        "0.3",
    )
    wait_alive(bus, RUN, "tdi_builder", stage, 60)
    assert stage.poll() is None, output(stage)
    time.sleep(0.5)  # subscribers declared after the token
    return stage


def _feed_good_bad_and_duplicates(pub, got) -> list:
    """Segments 0 to 3 published with a duplicate, seven malformed versions of segment 1
    and 3 before 2; returns the four outputs ``(header, arrays)`` received, in order."""
    pub.put(0, *message(0))
    h0, a0 = got()
    pub.put(0, *message(0))  # duplicate: ignored
    p1, att1 = message(1)
    pub.put(1, p1, b'{"schema": "ttl-segment", broken')  # unreadable header
    bad = telemetry(1)
    pub.put(1, *message(1, arrays={"eta": bad.eta[:5]}, channel_axis={"eta": None}))  # wrong shape
    nan = np.full_like(telemetry(1).eta, np.nan)
    pub.put(1, *message(1, arrays={"eta": nan}))  # no finite eta: no data
    pub.put(1, p1[:-8], att1)  # truncated payload
    pub.put(1, *message(1, arrays={"ltt": bad.ltt[:, :-4]}))  # inconsistent lengths
    pub.put(1, *message(1, fs=2.0))  # another sampling rate
    pub.put(1, *message(1, producer="intruder"))  # another producer
    pub.put(1, p1, att1)  # the good one
    h1, a1 = got()
    pub.put(3, *message(3))  # out of order: waits for 2
    pub.put(2, *message(2))
    h2, a2 = got()
    h3, a3 = got()
    return [(h0, a0), (h1, a1), (h2, a2), (h3, a3)]


def _check_streaming_tdi(outputs: list) -> None:
    """The outputs are the streaming TDI of the four segments (tail carried between them)."""
    (h0, a0), (h1, a1), (h2, a2), (h3, a3) = outputs
    assert [h.index for h in (h0, h1, h2, h3)] == [0, 1, 2, 3]
    ref = TDIStream()
    for h, a, i in ((h0, a0, 0), (h1, a1, 1), (h2, a2, 2), (h3, a3, 3)):
        td = ref.push(telemetry(i))
        assert h.channels == ("X2", "Y2", "Z2") and h.producer == "tdi_builder"
        assert h.t0 == i * N / FS and h.fs == FS
        assert h.meta["names"] == list(COEFFICIENT_NAMES) and len(h.meta["ltt_mean"]) == 6
        assert h.meta["segments_total"] == 4 and h.meta["continuous"] == (i > 0)
        assert a["data"].shape == (3, N) and a["regressors"].shape == (3, 24, N)
        np.testing.assert_array_equal(a["data"], td.data)
        np.testing.assert_array_equal(a["regressors"], td.regressors)
    assert np.isnan(a0["data"][:, 0]).all() and np.isfinite(a1["data"]).all()


def _check_tdi_builder_recording(path, rejected: list) -> None:
    """The stage's MCAP recording: the outputs, each accepted input once, the rejections, the
    events, and JSON schemas on its JSON channels."""
    rec = read_recording(path)
    assert rec.complete and rec.problem is None
    assert indices(rec, "tdi") == [0, 1, 2, 3]
    # accepted inputs are recorded: each segment once
    assert sorted(indices(rec, "telemetry")) == [0, 1, 2, 3]
    assert [(e["index"], e["field"]) for e in rec.json("errors") if e["kind"] in ("rejected", "forged")] == rejected
    events = [(e["kind"], e["index"]) for e in rec.json("events")]
    assert ("duplicate", 0) in events and ("complete", 3) in events and events[-1] == ("stop", None)
    with open(rec.path, "rb") as f:  # JSON channels carry JSON schemas
        for schema, channel, _ in make_reader(f).iter_messages():
            if channel.message_encoding == "json":
                assert schema is not None and schema.encoding == "jsonschema", channel.topic


def _check_rebuilt_copies(run_dir, published: list) -> None:
    """The tdi segments recorded without their regressors and telemetry are rebuilt from the
    replayer's recorded telemetry into the published copies, byte for byte (their checksum
    is the published one); a rebuild from other telemetry, or without it, is refused."""
    replayer = Recorder(run_dir / "replayer.mcap", metadata={"run": RUN, "stage": "replayer", "class": "Replayer"})
    for i in range(4):
        payload, attachment = message(i)
        replayer.write_segment("telemetry", json.loads(attachment), payload)
    replayer.close()
    recorded = recorded_copies(run_dir, "tdi_builder", "tdi", range(4))
    assert sorted(recorded) == [0, 1, 2, 3]
    for (h, a), i in zip(published, range(4), strict=True):
        seg = recorded[i]
        assert set(seg.arrays) == {"data"}  # the recording keeps the data only
        payload, attachment = wire_copy(seg, rebuilt_copy, run_dir)
        header, arrays = decode(payload, attachment, Expect(allow_nonfinite=True), key=f"ttl/{RUN}/tdi/{i}")
        assert header.checksum == h.checksum and header.meta == h.meta and header.arrays == h.arrays
        for name in a:
            np.testing.assert_array_equal(arrays[name], a[name])
    # segment 2's TDI reaches back into segment 1: other telemetry there gives another payload
    bad = run_dir / "other"
    bad.mkdir()
    other = Recorder(bad / "replayer.mcap", metadata={"run": RUN, "stage": "replayer", "class": "Replayer"})
    for i in (1, 2):
        tm = telemetry(i)
        if i == 1:
            tm.eta[2, -10] *= 1.5
        payload, attachment = message(i, tm)
        other.write_segment("telemetry", json.loads(attachment), payload)
    other.close()
    with pytest.raises(RecordingError, match=r"tdi segment 2: rebuilt .*\(segments 1\.\.2\).* not the published"):
        rebuilt_copy(bad, recorded[2])
    with pytest.raises(RecordingError, match="tdi segment 3: its telemetry is not in the replayer's recordings"):
        rebuilt_copy(bad, recorded[3])

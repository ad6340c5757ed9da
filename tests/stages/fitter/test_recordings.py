"""Unit tests of :mod:`stages.fitter.recordings`: what a restarted fitter reads from the run's
recordings (real MCAP files written by the recorder; no bus in it)."""

import json
import logging

import numpy as np
from ttl_testutil import noise_telemetry

from stages.fitter.recordings import pushed_again, recorded_models, recorded_telemetry
from streamer.bus.codec import encode
from streamer.recording.recorder import Recorder
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.data import TDIStream

RUN = "r1"
FS = 2.0
N = 1200  # 600 s segments

log = logging.getLogger("test_recordings")


def recorder(path, stage: str) -> Recorder:
    return Recorder(path, metadata={"run": RUN, "stage": stage, "class": "X", "config": "{}"})


def fitter_file(path, fits, summaries, models) -> None:
    rec = recorder(path, "fitter")
    for i in fits:
        payload, attachment = encode(
            {"coefficients": np.zeros(24)}, {"run": RUN, "index": i, "t0": 600.0 * i, "fs": FS, "meta": {}}
        )
        rec.write_segment("fit", json.loads(attachment), payload)
    for i in summaries:
        rec.write_json("fit/summary", {"run": RUN, "index": i})
    for effects in models:
        rec.write_json("events", {"kind": "model", "effects": effects})
    rec.write_json("events", {"kind": "start"})
    rec.close()


def telemetry(index: int, t0: float) -> Telemetry:
    return noise_telemetry(t0, N / FS, FS, index)


def replayer_file(path, segments: dict[int, Telemetry]) -> None:
    rec = recorder(path, "replayer")
    for i, tm in segments.items():
        arrays = {k: getattr(tm, k) for k in ("eta", "dws_phi", "dws_eta", "ltt")}
        payload, attachment = encode(arrays, {"run": RUN, "index": i, "t0": tm.t0, "fs": FS, "meta": {}})
        rec.write_segment("telemetry", json.loads(attachment), payload)
    rec.close()


def test_the_models_and_fits_of_the_earlier_processes(tmp_path, caplog):
    fitter_file(tmp_path / "fitter.10.mcap", fits=[6, 7], summaries=[6], models=[["linear-ttl", "step"]])
    fitter_file(tmp_path / "fitter.2.mcap", fits=[3, 4, 5], summaries=[3, 4, 9], models=[["linear-ttl", "drift"]])
    fitter_file(tmp_path / "fitter.mcap", fits=[8], summaries=[8], models=[["x"]])  # the live process's own
    (tmp_path / "fitter.3.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 40)  # damaged
    with caplog.at_level(logging.WARNING, logger="test_recordings"):
        models, segments, summaries = recorded_models(tmp_path, "fitter", log)
    # oldest process first (2 before 10), the damaged file said and skipped
    assert [m["effects"] for m in models] == [["linear-ttl", "drift"], ["linear-ttl", "step"]]
    assert segments == {3, 4, 5, 6, 7, 9} and summaries == {3, 4, 6, 9}  # a summary alone counts too
    assert any("fitter.3.mcap" in r.getMessage() for r in caplog.records)


def test_the_replayers_telemetry_pushed_again(tmp_path):
    segments = {i: telemetry(i, 600.0 * i) for i in range(3)}
    segments[3] = telemetry(3, 600.0 * 3 + 3600.0)  # an hour later: a discontinuity in time
    replayer_file(tmp_path / "replayer.mcap", segments)
    earlier = telemetry(99, 600.0)
    replayer_file(tmp_path / "replayer.1.mcap", {1: earlier})  # an earlier process's copy of 1
    read = recorded_telemetry(tmp_path, 4, log)
    assert sorted(read) == [0, 1, 2, 3]
    assert recorded_telemetry(tmp_path, 2, log).keys() == {0, 1}
    np.testing.assert_array_equal(read[1].arrays["eta"], earlier.eta)  # the first copy found (name order)
    segments[1] = earlier
    again = list(pushed_again(read, 1, 4))
    assert [h.index for h, _ in again] == [1, 2, 3]
    # one TDI stream from segment 1, a new one after the discontinuity
    stream = TDIStream()
    expected = [stream.push(segments[1]), stream.push(segments[2]), TDIStream().push(segments[3])]
    for (_, (td, tm)), want, i in zip(again, expected, [1, 2, 3]):
        np.testing.assert_array_equal(tm.eta, segments[i].eta)
        np.testing.assert_array_equal(td.data, want.data)

"""Segments read back from their producers' recordings (streamer.recording.recorded_inputs); when a
stage reads them: tests/stages/monitor/test_catch_up.py."""

from __future__ import annotations

import json

import numpy as np

from streamer.bus.codec import decode, encode
from streamer.recording.recorded_inputs import recorded_copies, recording_files, wire_copy
from streamer.recording.recorder import Recorder, read_recording

RUN = "r1"


def _write(path, topic: str, indices, close: bool = True, scale: float = 1.0) -> None:
    rec = Recorder(path, metadata={"run": RUN, "stage": path.stem.split(".")[0], "class": "X", "config": "{}"})
    for i in indices:
        payload, attachment = encode(
            {"coefficients": np.full(24, scale * i), "sigma": np.ones(24)},
            {"run": RUN, "index": i, "t0": 600.0 * i, "fs": 4.0, "producer": "fitter", "meta": {}},
        )
        rec.write_segment(topic, json.loads(attachment), payload)
        rec.write_json("events", {"kind": "x", "index": i})
    if close:
        rec.close()
    else:
        rec.flush()  # a live process's file: no footer yet


def test_the_wanted_segments_of_a_topic_are_read_back_from_every_process_file(tmp_path):
    _write(tmp_path / "fitter.1.mcap", "fit", range(6), close=True, scale=1.0)  # an earlier process
    _write(tmp_path / "fitter.mcap", "fit", range(4, 12), close=False, scale=1.0)  # the live one, unclosed
    _write(tmp_path / "fitter_other.mcap", "fit", range(20), scale=-1.0)  # not the fitter's
    _write(tmp_path / "subtractor.mcap", "fit", range(20), scale=-1.0)  # another stage's copy
    assert [p.name for p in recording_files(tmp_path, "fitter")] == ["fitter.1.mcap", "fitter.mcap"]
    got = recorded_copies(tmp_path, "fitter", "fit", {2, 5, 9, 30})
    assert sorted(got) == [2, 5, 9]  # 30 is in no file
    for i, seg in got.items():
        assert seg.header.index == i and np.all(seg.arrays["coefficients"] == i)
    # only what is asked for is decoded: no JSON topic, no other segment
    rec = read_recording(tmp_path / "fitter.1.mcap", keep=lambda t, h: t == "fit" and h["index"] == 3)
    assert [m.header.index for m in rec.messages] == [3]


def test_a_recorded_segment_is_published_again_byte_for_byte(tmp_path):
    """What a stage takes from a recording goes through the checks of a copy from the bus:
    its payload rebuilt from the arrays matches the recorded header's size and checksum."""
    _write(tmp_path / "fitter.mcap", "fit", range(3))
    seg = recorded_copies(tmp_path, "fitter", "fit", {2})[2]
    payload, attachment = wire_copy(seg)
    header, arrays = decode(payload, attachment, key=f"ttl/{RUN}/fit/2")
    assert header.index == 2 and header.checksum == seg.header.checksum
    assert np.array_equal(arrays["coefficients"], np.full(24, 2.0))

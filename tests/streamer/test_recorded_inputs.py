"""Segments read back from their producers' recordings (streamer.recorded_inputs), and the
monitor's bookkeeping of which it needs (stages.monitor_settling.Settling.evicted)."""

from __future__ import annotations

import json

import numpy as np

from stages.monitor_settling import Settling
from streamer.codec import encode
from streamer.progress import Progress
from streamer.recorded_inputs import recorded_copies, recording_files
from streamer.recorder import Recorder, read_recording

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


def test_the_monitor_asks_once_for_what_left_the_caches_and_it_still_needs():
    s = Settling(("telemetry", "tdi", "fit", "residual"))
    s.drawn["tdi"] |= {0, 1, 2, 3, 4, 7, 11, 12}
    s.drawn["fit"] |= {0, 11}
    board = {
        "tdi_builder": Progress("tdi_builder", done=set(range(14))),
        "fitter": Progress("fitter", done=set(range(14)), extra={"fits": set(range(14))}),
        "subtractor": Progress("subtractor", done=set(range(6))),  # behind: all in its cache
    }
    own = Progress("monitor", done={0, 1})  # the earlier process drew 0 and 1
    gone = s.evicted(board, handled=set(), cache=8, own=own)
    # 14 published, the caches hold 6..13: of 0..5, TDI 5 was never drawn here; fits 2..4
    # for the TDI drawn (0 and 1 were handled by the earlier process; 5's TDI comes first;
    # 7's fit is still in the cache); the subtractor's cache still holds all it published
    assert gone == {"tdi": {5}, "fit": {2, 3, 4}}
    assert s.evicted(board, handled=set(), cache=8, own=own) == {}  # asked once

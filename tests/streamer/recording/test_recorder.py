"""MCAP recording: round trip, JSON schemas, and salvaging unfinished files."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from streamer.bus.codec import encode, parse_header
from streamer.recording.recorder import Recorder, RecordingError, read_recording

FIELDS = {"run": "r", "t0": 0.0, "fs": 4.0, "channels": ["X2", "Y2", "Z2"], "producer": "test"}


def segment(index, n=1000):
    rng = np.random.default_rng(index)
    arrays = {"data": rng.standard_normal((3, n)), "regressors": rng.standard_normal((3, 24, n))}
    payload, attachment = encode(arrays, {**FIELDS, "index": index})
    return arrays, parse_header(attachment), payload


def write_sample(path, close=True):
    rec = Recorder(path, metadata={"run": "r", "stage": "test"})
    rec.write_json("events", {"run": "r", "stage": "test", "kind": "start", "time": 1.0})
    written = []
    for i in range(3):
        arrays, header, payload = segment(i)
        rec.write_segment("tdi", header, payload)
        rec.write_json(
            "fit/summary",
            {
                "run": "r",
                "index": i,
                "names": ["a", "b"],
                "coefficients": np.array([1.0, np.nan]),
                "chi2": np.float64(2.5),
            },
            schema="ttl.Fit",
        )
        written.append(arrays)
    rec.write_json(
        "errors",
        {"run": "r", "stage": "test", "kind": "rejected", "index": 4, "field": "fs", "message": "bad", "time": 2.0},
    )
    if close:
        rec.close()
    return rec, written


def test_round_trip(tmp_path):
    path = tmp_path / "test.mcap"
    _, written = write_sample(path)
    rec = read_recording(path)
    assert rec.complete and rec.problem is None
    assert rec.metadata["ttl"] == {"run": "r", "stage": "test"}
    assert rec.topics() == ["errors", "events", "fit/summary", "tdi"]
    segments = rec.segments("tdi")
    assert [s.header.index for s in segments] == [0, 1, 2]
    for seg, arrays in zip(segments, written):
        for name in arrays:
            np.testing.assert_array_equal(seg.arrays[name], arrays[name])
    fits = rec.json("fit/summary")
    assert fits[0]["coefficients"] == [1.0, None] and fits[0]["chi2"] == 2.5  # NaN written as null
    assert rec.json("errors")[0]["field"] == "fs"


def test_json_channels_carry_json_schemas(tmp_path):
    path = tmp_path / "test.mcap"
    write_sample(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        seen = {}
        for schema, channel, _message in reader.iter_messages():
            seen[channel.topic] = (schema, channel)
    for topic in ("events", "errors", "tdi/header", "fit/summary"):
        schema, channel = seen[topic]
        assert channel.message_encoding == "json"
        assert schema.encoding == "jsonschema", topic
        body = json.loads(schema.data)
        assert body["type"] == "object" and body["title"] == schema.name
    assert seen["tdi/header"][0].name == "ttl.SegmentHeader"
    assert seen["fit/summary"][0].name == "ttl.Fit"
    schema, channel = seen["tdi/payload"]
    assert schema is None and channel.message_encoding == "application/octet-stream"
    assert channel.metadata["header_topic"] == "tdi/header"
    assert summary.statistics.message_count == 1 + 3 * 3 + 1


def test_unclosed_file_is_salvaged(tmp_path):
    path = tmp_path / "killed.mcap"
    rec, written = write_sample(path, close=False)  # flushed, never finished: as if killed
    got = read_recording(path)
    assert not got.complete and "without footer" in got.problem
    assert [s.header.index for s in got.segments("tdi")] == [0, 1, 2]
    assert len(got.json("errors")) == 1
    rec.close()


def _segment_chunks(path):
    """Start offsets of the chunks holding a segment payload (the big ones)."""
    with open(path, "rb") as f:
        return [
            c.chunk_start_offset for c in make_reader(f).get_summary().chunk_indexes if c.uncompressed_size > 100_000
        ]


def test_truncated_file_stops_at_the_truncated_chunk(tmp_path):
    path = tmp_path / "full.mcap"
    write_sample(path)
    data = path.read_bytes()
    full = read_recording(path)
    # a chunk per segment: cut inside the chunk of the last segment
    starts = _segment_chunks(path)
    assert len(starts) == 3
    last = starts[-1]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: last + 1000])
    got = read_recording(cut)
    assert not got.complete and "truncated record" in got.problem
    assert got.records < full.records
    assert [s.header.index for s in got.segments("tdi")] == [0, 1]
    # cut inside a record header
    cut.write_bytes(data[: last + 5])
    assert read_recording(cut).segments("tdi")[-1].header.index == 1


def test_chunked_compressed_mission_time(tmp_path):
    """Chunks are zstd-compressed, each segment closes its chunk, log_time is mission time."""
    path = tmp_path / "t.mcap"
    rec = Recorder(path)
    for i in range(3):
        arrays, header, payload = segment(i)
        header = header.to_dict() | {"t0": 3600.0 * i}
        rec.write_segment("tdi", header, payload)
        rec.write_json("fit/summary", {"index": i})
    rec.close()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
    assert len(summary.chunk_indexes) >= 3
    got = read_recording(path)
    times = [(m.topic, m.log_time) for m in got.messages]
    assert times == [
        ("tdi", 0),
        ("fit/summary", 0),
        ("tdi", 3600 * 10**9),
        ("fit/summary", 3600 * 10**9),
        ("tdi", 7200 * 10**9),
        ("fit/summary", 7200 * 10**9),
    ]
    assert all(abs(m.publish_time / 1e9 - time.time()) < 60 for m in got.messages)  # wall clock kept


def test_lz4_and_bad_compression(tmp_path):
    rec = Recorder(tmp_path / "l.mcap", compression="lz4")
    arrays, header, payload = segment(0)
    rec.write_segment("tdi", header, payload)
    rec.close()
    np.testing.assert_array_equal(read_recording(tmp_path / "l.mcap").segments("tdi")[0].arrays["data"], arrays["data"])
    with pytest.raises(ValueError, match="compression"):
        Recorder(tmp_path / "b.mcap", compression="gzip")


WRITER = """
import sys, time
import numpy as np
from streamer.bus.codec import encode, parse_header
from streamer.recording.recorder import Recorder
rec = Recorder(sys.argv[1], max_chunk_age=3600)
rng = np.random.default_rng(0)
i = 0
while True:
    arrays = {"data": rng.standard_normal((3, 2000)), "regressors": rng.standard_normal((3, 24, 2000))}
    payload, att = encode(arrays, {"run": "r", "t0": 500.0 * i, "fs": 4.0, "channels": ["X2", "Y2", "Z2"],
                                   "producer": "w", "index": i})
    rec.write_segment("tdi", parse_header(att), payload)
    rec.write_json("fit/summary", {"index": i})
    print(i, flush=True)
    i += 1
    time.sleep(0.02)
"""


def test_sigkill_loses_at_most_the_open_chunk(tmp_path):
    """A real recording process killed with SIGKILL mid-run: every segment it reported written
    is read back by the salvage reader; what is lost is the chunk it was filling (here the
    fit summary written after the last closed segment chunk)."""
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(path)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=Path(__file__).resolve().parents[3],
    )
    try:
        written = -1
        deadline = time.monotonic() + 60
        while written < 20 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            written = int(line.split()[0])
        assert written >= 20, "the writer did not get going"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    got = read_recording(path)
    assert not got.complete and got.problem
    indices = [s.header.index for s in got.segments("tdi")]
    assert indices == list(range(len(indices))) and indices[-1] >= written  # nothing reported written is lost
    summaries = [m["index"] for m in got.json("fit/summary")]
    # the fit summary of segment k sits in the chunk closed by segment k + 1: at most the last is lost
    assert summaries == list(range(len(summaries))) and len(summaries) >= len(indices) - 1
    assert all(m.kind in ("segment", "json") for m in got.messages)


def test_not_mcap(tmp_path):
    path = tmp_path / "x.mcap"
    path.write_bytes(b"hello world, not mcap")
    with pytest.raises(RecordingError, match="x.mcap"):
        read_recording(path)
    with pytest.raises(RecordingError, match="missing.mcap"):
        read_recording(tmp_path / "missing.mcap")


def write_many(path, n=12):
    """A closed recording of ``n`` segments (a chunk each) with a fit summary each."""
    rec = Recorder(path, metadata={"run": "r", "stage": "test"})
    for i in range(n):
        _, header, payload = segment(i, n=300)
        rec.write_segment("tdi", header, payload)
        rec.write_json("fit/summary", {"run": "r", "index": i}, schema="ttl.Fit")
    rec.close()


def test_flipped_bytes_inside_one_chunk_lose_that_chunk_only(tmp_path):
    path = tmp_path / "damaged.mcap"
    write_many(path)
    starts = _segment_chunks(path)
    data = bytearray(path.read_bytes())
    for k in range(50):  # inside the compressed body of the 5th segment's chunk
        data[starts[4] + 200 + 7 * k] ^= 0xFF
    path.write_bytes(bytes(data))
    got = read_recording(path)  # no ZstdError, no exception at all
    indices = [s.header.index for s in got.segments("tdi")]
    assert indices == [0, 1, 2, 3, 5, 6, 7, 8, 9, 10, 11], indices
    assert got.complete and len(got.skipped) == 1 and got.skipped[0]["start"] == starts[4]
    assert "1 corrupt stretch(es) skipped" in got.problem


def test_2000_flipped_bytes_are_salvaged_not_raised(tmp_path):
    """A closed file with 2000 flipped bytes (the issue's case): read past every damaged
    stretch, damaged record lengths included, keeping every chunk that passes its CRC."""
    path = tmp_path / "damaged.mcap"
    write_many(path, n=40)
    clean = read_recording(path)
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(3)
    for pos in rng.choice(np.arange(8, len(data) - 8), size=2000, replace=False):
        data[pos] ^= 1 << int(rng.integers(8))
    path.write_bytes(bytes(data))
    got = read_recording(path)  # before: ZstdError or CRCValidationError out of mcap's reader
    # about 50 flips per chunk: every chunk is lost (each fails its CRC), the footer is read
    assert got.complete and got.records > 0 and len(got.skipped) >= 30, (got.records, got.skipped[:2])
    assert "corrupt stretch" in got.problem
    good = {s.header.index: s.arrays for s in clean.segments("tdi")}
    for s in got.segments("tdi"):  # what is kept is intact
        np.testing.assert_array_equal(s.arrays["data"], good[s.header.index]["data"])


def test_a_damaged_record_length_is_skipped_by_resynchronising(tmp_path):
    path = tmp_path / "damaged.mcap"
    write_many(path)
    starts = _segment_chunks(path)
    data = bytearray(path.read_bytes())
    data[starts[3] + 8] = 0x7F  # the top byte of the chunk's length: far beyond the file
    path.write_bytes(bytes(data))
    got = read_recording(path)
    assert [s.header.index for s in got.segments("tdi")] == [0, 1, 2, 4, 5, 6, 7, 8, 9, 10, 11]
    assert "damaged record length" in got.skipped[0]["why"] and got.skipped[0]["start"] == starts[3]

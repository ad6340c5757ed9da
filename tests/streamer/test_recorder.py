"""MCAP recording: round trip, JSON schemas, and salvaging unfinished files."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from streamer.codec import encode, parse_header
from streamer.recorder import Recorder, RecordingError, read_recording

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
        rec.write_json("fit/summary", {"run": "r", "index": i, "names": ["a", "b"],
                                       "coefficients": np.array([1.0, np.nan]), "chi2": np.float64(2.5)},
                       schema="ttl.Fit")
        written.append(arrays)
    rec.write_json("errors", {"run": "r", "stage": "test", "kind": "rejected", "index": 4,
                              "field": "fs", "message": "bad", "time": 2.0})
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
        for schema, channel, message in reader.iter_messages():
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


def test_truncated_file_stops_at_the_truncated_record(tmp_path):
    path = tmp_path / "full.mcap"
    write_sample(path)
    data = path.read_bytes()
    full = read_recording(path)
    # cut inside the payload of the last segment (the biggest record)
    cut = tmp_path / "cut.mcap"
    last_payload = data.rfind(segment(2)[2][:64])
    cut.write_bytes(data[: last_payload + 1000])
    got = read_recording(cut)
    assert not got.complete and "truncated record" in got.problem
    assert got.records < full.records
    assert [s.header.index for s in got.segments("tdi")] == [0, 1]
    assert [m.kind for m in got.messages if m.topic == "tdi"] == ["segment", "segment", "incomplete"]
    # cut inside a record header
    cut.write_bytes(data[: last_payload - 20])
    assert read_recording(cut).segments("tdi")[-1].header.index == 1


def test_not_mcap(tmp_path):
    path = tmp_path / "x.mcap"
    path.write_bytes(b"hello world, not mcap")
    with pytest.raises(RecordingError, match="x.mcap"):
        read_recording(path)
    with pytest.raises(RecordingError, match="missing.mcap"):
        read_recording(tmp_path / "missing.mcap")

"""The telemetry and TDI segments' meta as a value (streamer/bus/segment_record.py): the meta the
replayer and the tdi_builder write, read by attribute; a field of the wrong type an error
naming the message and the field."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from streamer.bus.segment_record import MessageError, SegmentMeta, segment_meta, segments_total_of
from ttlcore.conventions import COEFFICIENT_NAMES, LINKS

# telemetry/0 and tdi/0 as main wrote them (ttl run --simulate "--duration 12h --orbit unequal
# --seed 1" --segment 1h, commit 88bef55; the truth's 24 coefficients cut to two)
TRUTH = {"coefficients": {"base": {"12.phi.rx": 0.0023, "12.phi.tx": 0.0023}, "t_ref": 0.0}}
TELEMETRY = {
    "source": "simulation",
    "truth": TRUTH,
    "file": None,
    "dws_asd": 2.0895522388059703e-10,
    "segments_total": 12,
    "segment_duration": 3600.0,
    "gaps": [],
}
TDI = {
    "segments_total": 12,
    "segment_duration": 3600.0,
    "source": "simulation",
    "truth": TRUTH,
    "dws_asd": 2.0895522388059703e-10,
    "gaps": [],
    "names": list(COEFFICIENT_NAMES),
    "ltt_mean": [8.424999999999997, 8.372, 8.322000000000001, 8.322000000000001, 8.372, 8.322000000000001],
    "continuous": False,
    "recorded": {"arrays": ["data"], "published_checksum": "crc32:50e7f8f9", "published_bytes": 11404800},
}


def test_the_replayers_and_the_tdi_builders_meta_read_by_attribute():
    t = SegmentMeta.from_header(json.loads(json.dumps(TELEMETRY)), "telemetry 0")
    assert (t.source, t.truth, t.file, t.segments_total, t.segment_duration) == ("simulation", TRUTH, None, 12, 3600.0)
    assert t.dws_asd == 2.0895522388059703e-10 and t.gaps == () and t.names is None and t.ltt_mean is None
    d = segment_meta(SimpleNamespace(topic="tdi", index=0, meta=TDI))
    assert d.names == tuple(COEFFICIENT_NAMES) and d.ltt_mean == tuple(TDI["ltt_mean"]) and d.continuous is False
    # a truth file, and the light travel times given by link
    by_link = dict(zip(LINKS, TDI["ltt_mean"]))
    f = SegmentMeta.from_header({"truth": "/data/day.truth.h5", "ltt_mean": by_link})
    assert f.truth == "/data/day.truth.h5" and f.ltt_mean == tuple(TDI["ltt_mean"])
    assert SegmentMeta.from_header({}) == SegmentMeta()


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("segments_total", 12.0),
        ("segment_duration", "1h"),
        ("dws_asd", True),
        ("source", 3),
        ("names", "12.phi.rx"),
        ("ltt_mean", "8.3"),
        ("continuous", 0),
        ("truth", 3),
    ],
)
def test_a_field_of_the_wrong_type_is_an_error_naming_it(field, value):
    header = SimpleNamespace(topic="tdi", index=4, meta={**TDI, field: value})
    with pytest.raises(MessageError, match=f"tdi 4: meta field '{field}': expected"):
        segment_meta(header)


def test_segments_total_of_any_message():
    assert segments_total_of(TDI) == 12 and segments_total_of({"fit_index": 3, "segments_total": 7}) == 7
    for meta in ({}, {"segments_total": 0}, {"segments_total": True}, {"segments_total": "12"}, None, [12]):
        assert segments_total_of(meta) is None


def test_the_replayers_meta_of_a_file_reads(tmp_path):
    """The meta the replayer writes for a segment of a telemetry file (its path as source,
    the file's index among the run's files, the truth beside it) reads as a SegmentMeta: the
    producer and the value agree (the index was typed as a str, and every segment of
    ``ttl run --telemetry`` failed in the tdi_builder)."""
    from stages.replayer import FileSource
    from ttlcore.cli.main import main

    path = tmp_path / "day.h5"
    assert main(["simulate", "--duration", "2h", "--seed", "3", "--out", str(path), "--quiet"]) == 0
    source = FileSource([path], 3600.0)
    for i in range(source.segments_total):
        _, meta = source.segment(i)
        m = SegmentMeta.from_header(meta, f"telemetry {i}")
        assert m.file == 0 and m.source == str(path) and m.truth is not None, m

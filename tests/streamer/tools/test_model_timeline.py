"""Unit tests of :mod:`streamer.tools.model_timeline`: the model timeline's bookkeeping (bus-free)."""

from streamer.tools.model_timeline import BY_WINDOW, SpanMerger, change_text, excluded_kind, model_delta


def test_model_delta():
    assert model_delta(None, ["linear-ttl"]) == ([], [], False)
    # a coupling added: a new model epoch
    assert model_delta(["linear-ttl"], ["linear-ttl", "drift"]) == (["drift"], [], True)
    # a transient added or removed alone: no new epoch
    assert model_delta(["linear-ttl"], ["linear-ttl", "glitch:t0=100"]) == (["glitch:t0=100"], [], False)
    assert model_delta(["linear-ttl", "gate:t0=1,t1=2"], ["linear-ttl"]) == ([], ["gate:t0=1,t1=2"], False)
    assert model_delta(["linear-ttl", "drift"], ["drift", "linear-ttl"]) == ([], [], False)


def test_change_text():
    assert change_text(["drift"], [], "adopt auto", diagnosis_index=23, reason="a drift", new_epoch=True) == (
        "+ drift by adopt auto after the diagnosis of segment 23: a drift  [new model epoch]"
    )
    assert change_text([], ["glitch:t0=5"], "window") == f"- glitch:t0=5 by window{BY_WINDOW}"
    assert change_text([], [], "control") == "the same effects by control"


def test_excluded_kind():
    assert excluded_kind({"gap": True, "gate": "g"}) == "gap"
    assert excluded_kind({"gate": "gate:t0=1"}) == "gated"
    assert excluded_kind({"z": 7.0}) == "outlier"


def test_span_merger_merges_consecutive_items_of_one_cause():
    spans = SpanMerger()
    assert spans.add("gap", 1, 0.0, 10.0)[1] is True
    span, new = spans.add("gap", 1, 10.0, 20.0)
    assert not new and (span["count"], span["t_stop"]) == (2, 20.0)
    # another cause, another gate, or apart in time: a new span
    assert spans.add("gated", 2, 20.0, 30.0, gate="g1")[1] is True
    assert spans.add("gated", 2, 30.0, 40.0, gate="g2")[1] is True
    assert spans.add("gated", 3, 100.0, 110.0, gate="g2")[1] is True
    out, new = spans.add("outlier", 4, 110.0, 120.0, z=5.0)
    assert new and out["z_max"] == 5.0 and "gate" not in out
    out, new = spans.add("outlier", 5, 120.0, 130.0, z=8.0)
    assert not new and (out["z_max"], out["from_index"], out["to_index"]) == (8.0, 4, 5)
    assert [s["kind"] for s in spans.spans] == ["gap", "gated", "gated", "gated", "outlier"]
    assert spans.spans[1]["gate"] == "g1"


def test_span_merger_keeps_the_latest():
    spans = SpanMerger(keep=2)
    for i in range(4):
        spans.add("gap", i, 100.0 * i, 100.0 * i + 10)
    assert [s["from_index"] for s in spans.spans] == [2, 3]

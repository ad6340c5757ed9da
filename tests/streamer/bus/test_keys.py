"""Key expressions: build, parse, and errors that name the key."""

import pytest

from streamer.bus.keys import (
    KeyExprError,
    SegmentKey,
    alive_key,
    alive_pattern,
    control_key,
    errors_key,
    parse_alive_key,
    parse_control_key,
    parse_segment_key,
    parse_stream_key,
    segment_key,
    stream_key,
    topic_pattern,
)
from streamer.runtime.plan import RangeSet
from streamer.runtime.progress import Progress


def test_build_and_parse_round_trip():
    assert segment_key("run-1", "tdi", 12) == "ttl/run-1/tdi/12"
    assert parse_segment_key("ttl/run-1/tdi/12") == SegmentKey("run-1", "tdi", 12)
    assert str(SegmentKey("r", "fit", 3)) == "ttl/r/fit/3"
    assert stream_key("r", "residual") == "ttl/r/residual" and parse_stream_key("ttl/r/residual") == "residual"
    assert topic_pattern("r", "residual") == "ttl/r/residual/**"  # the stream key and strays under it
    assert topic_pattern("r", "errors") == "ttl/r/errors/*"
    assert errors_key("r", None) == "ttl/r/errors/unknown"
    assert parse_segment_key("ttl/r/errors/unknown").index is None
    assert alive_key("r", "fitter") == "ttl/r/alive/fitter"
    assert alive_pattern("r") == "ttl/r/alive/*"
    assert parse_alive_key("ttl/r/alive/fitter") == ("r", "fitter")
    assert control_key("r", "fitter", "stop") == "ttl/r/control/fitter/stop"
    assert parse_control_key("ttl/r/control/stop") == ("r", ("stop",))


@pytest.mark.parametrize(
    "key",
    [
        "ttl/r/tdi",
        "ttl/r/tdi/1/2",
        "xyz/r/tdi/1",
        "ttl/r/bogus/1",
        "ttl/r/tdi/-1",
        "ttl/r/tdi/01",
        "ttl/r/tdi/one",
        "ttl/r/telemetry/unknown",
        "ttl/r*/tdi/1",
        "",
    ],
)
def test_parse_errors_name_the_key(key):
    with pytest.raises(KeyExprError) as err:
        parse_segment_key(key)
    assert repr(key) in str(err.value)


@pytest.mark.parametrize(
    "run, topic, index",
    [
        ("a/b", "tdi", 1),
        ("r*", "tdi", 1),
        ("", "tdi", 1),
        ("r", "nope", 1),
        ("r", "tdi", -1),
        ("r", "tdi", None),
        ("r", "tdi", True),
    ],
)
def test_builders_reject_bad_chunks(run, topic, index):
    with pytest.raises(KeyExprError):
        segment_key(run, topic, index)


@pytest.mark.parametrize("key", ["ttl/r/tdi/1", "ttl/r/errors", "ttl/r/bogus", "ttl/r*/tdi", "xyz/r/tdi", "ttl/r"])
def test_stream_key_errors_name_the_key(key):
    with pytest.raises(KeyExprError) as err:
        parse_stream_key(key)
    assert repr(key) in str(err.value)
    with pytest.raises(KeyExprError):
        stream_key("r", "errors")  # error reports are per index


def test_alive_and_control_errors():
    with pytest.raises(KeyExprError, match="ttl/r/tdi/1"):
        parse_alive_key("ttl/r/tdi/1")
    with pytest.raises(KeyExprError, match="ttl/r/alive/x"):
        parse_control_key("ttl/r/alive/x")
    with pytest.raises(KeyExprError):
        control_key("r")


def test_progress_keys_and_the_one_topology():
    from streamer.bus.keys import TOPICS, board_key, parse_progress_key, progress_key, progress_pattern
    from streamer.bus.security import ROLES
    from streamer.bus.topology import OUTPUT_TOPIC, STAGES, UPSTREAM
    from streamer.runtime.plan import PRODUCERS
    from streamer.runtime.progress import Progress, key_stage

    assert progress_key("r", "fitter") == "ttl/r/control/progress/fitter"
    assert board_key("r", "fitter") == "ttl/r/control/board/fitter"
    assert progress_pattern("r") == "ttl/r/control/progress/*"
    assert progress_pattern("r", board=True) == "ttl/r/control/board/*"
    assert parse_progress_key(board_key("r", "monitor")) == ("r", "monitor")
    assert key_stage("ttl/r/control/progress/fitter") == "fitter"
    for bad in ("ttl/r/control/stop", "ttl/r/control/progress", "ttl/r/control/progress/a/b", "ttl/r/fit/1"):
        assert key_stage(bad) is None
        with pytest.raises(KeyExprError):
            parse_progress_key(bad)
    # every list of stages and topics is the topology's
    assert TOPICS == (*(OUTPUT_TOPIC[s] for s in STAGES), "errors")
    assert {PRODUCERS[t]: t for t in PRODUCERS} == OUTPUT_TOPIC
    assert ROLES[: len(STAGES)] == STAGES and set(UPSTREAM) == set(STAGES) - {"replayer"}
    # a progress message read back is the progress it was made from (the launcher's board)
    p = Progress("fitter", done={0, 1, 2, 5}, failed={3, 4}, gaps={4}, segments_total=8, extra={"fits": {1, 2, 5}})
    msg = p.message("r", pid=7, index=5)
    assert msg["done"] == [[0, 2], [5, 5]] and msg["fits_ranges"] == [[1, 2], [5, 5]] and msg["pid"] == 7
    q = Progress("fitter")
    q.update(msg)
    assert (q.done, q.failed, q.gaps, q.segments_total, q.extra, q.pids) == (
        p.done,
        p.failed,
        p.gaps,
        8,
        {"fits": {1, 2, 5}},
        {7},
    )
    assert not q.covers() and q.highest == 5
    q.update({"done": [[6, 7]], "stage": "fitter", "complete": True})
    assert q.covers() and q.complete
    q.update({"done": [[0, 2**40]], "stage": "fitter"}, limit=8)  # clipped, not 2^40 entries
    assert max(q.done) == 7


def test_progress_is_ranges_however_long_the_run():
    """A stage's progress after 100000 segments is one range per set, not one entry per
    segment, and the message it publishes stays one line long."""
    p = Progress("fitter", segments_total=100_000)
    follower = Progress("fitter")
    for i in range(100_000):
        p.done.add(i)
        if i % 7 == 3:
            p.extra.setdefault("fits", RangeSet()).add(i)
        if i % 1000 == 999:
            follower.update(p.message("r", index=i))
    assert p.done.n_ranges == 1 and follower.done.n_ranges == 1 and follower.covers()
    assert p.message("r")["done"] == [[0, 99_999]] and len(follower.extra["fits"]) == len(range(3, 100_000, 7))
    assert isinstance(p.copy().done, RangeSet) and p.copy().done == p.done and p.copy().done is not p.done

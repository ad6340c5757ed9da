"""Key expressions: build, parse, and errors that name the key."""

import pytest

from streamer.keys import (KeyExprError, SegmentKey, alive_key, alive_pattern, control_key,
                           errors_key, parse_alive_key, parse_control_key, parse_segment_key,
                           segment_key, topic_pattern)


def test_build_and_parse_round_trip():
    assert segment_key("run-1", "tdi", 12) == "ttl/run-1/tdi/12"
    assert parse_segment_key("ttl/run-1/tdi/12") == SegmentKey("run-1", "tdi", 12)
    assert str(SegmentKey("r", "fit", 3)) == "ttl/r/fit/3"
    assert topic_pattern("r", "residual") == "ttl/r/residual/*"
    assert errors_key("r", None) == "ttl/r/errors/unknown"
    assert parse_segment_key("ttl/r/errors/unknown").index is None
    assert alive_key("r", "fitter") == "ttl/r/alive/fitter"
    assert alive_pattern("r") == "ttl/r/alive/*"
    assert parse_alive_key("ttl/r/alive/fitter") == ("r", "fitter")
    assert control_key("r", "fitter", "stop") == "ttl/r/control/fitter/stop"
    assert parse_control_key("ttl/r/control/stop") == ("r", ("stop",))


@pytest.mark.parametrize("key", [
    "ttl/r/tdi", "ttl/r/tdi/1/2", "xyz/r/tdi/1", "ttl/r/bogus/1", "ttl/r/tdi/-1",
    "ttl/r/tdi/01", "ttl/r/tdi/one", "ttl/r/telemetry/unknown", "ttl/r*/tdi/1", "",
])
def test_parse_errors_name_the_key(key):
    with pytest.raises(KeyExprError) as err:
        parse_segment_key(key)
    assert repr(key) in str(err.value)


@pytest.mark.parametrize("run, topic, index", [
    ("a/b", "tdi", 1), ("r*", "tdi", 1), ("", "tdi", 1), ("r", "nope", 1), ("r", "tdi", -1),
    ("r", "tdi", None), ("r", "tdi", True),
])
def test_builders_reject_bad_chunks(run, topic, index):
    with pytest.raises(KeyExprError):
        segment_key(run, topic, index)


def test_alive_and_control_errors():
    with pytest.raises(KeyExprError, match="ttl/r/tdi/1"):
        parse_alive_key("ttl/r/tdi/1")
    with pytest.raises(KeyExprError, match="ttl/r/alive/x"):
        parse_control_key("ttl/r/alive/x")
    with pytest.raises(KeyExprError):
        control_key("r")

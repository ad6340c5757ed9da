"""``ttl refit --segments A:B``: the range is checked against the recorded segments."""

from __future__ import annotations

import pytest

from streamer.tools.refit import RefitError, _parse_range, _select

FOUND = {i: (f"header {i}", f"arrays {i}") for i in range(24, 48)}


def test_a_range_inside_the_recordings_selects_it():
    assert _select(FOUND, 30, 32) == [FOUND[30], FOUND[31], FOUND[32]]
    assert len(_select(FOUND, *_parse_range("40:"))) == 8 and len(_select(FOUND, *_parse_range(":25"))) == 2


@pytest.mark.parametrize("text", ["0:1000", "24:48", "10:30", "50:60"])
def test_a_range_beyond_the_recordings_is_refused_not_clipped(text):
    """It used to be clipped silently: ``0:1000`` refitted 24-47 without a word."""
    with pytest.raises(RefitError, match=rf"--segments {text}: the run recorded segments 24-47"):
        _select(FOUND, *_parse_range(text))


def test_a_hole_in_the_range_is_named():
    found = {i: v for i, v in FOUND.items() if i != 30}
    with pytest.raises(RefitError, match=r"segments \[30\] are missing"):
        _select(found, 24, 40)

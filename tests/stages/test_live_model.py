"""The live model's checks (``stages/live_model.py``): a state object with no bus in it."""

from __future__ import annotations

import pytest

from stages.live_model import MAX_COLUMNS, MAX_EFFECTS, LiveModel


def model() -> LiveModel:
    return LiveModel(["linear-ttl"], ())


def test_a_model_is_checked_and_spelled_as_the_effects_spell_it():
    assert model().check(["linear-ttl", "drift"]) == ["linear-ttl", "drift"]


@pytest.mark.parametrize(
    "specs, needle",
    [
        (["linear-ttl", "step:t_step=abc"], "bad duration 'abc'"),
        (["linear-ttl", "witness:source=foo"], "unknown 'foo'"),
        (["drift"], "must include linear-ttl"),
        (["linear-ttl", "no-such-effect"], "unknown effect"),
        ("", "expected a list"),
    ],
)
def test_a_model_that_cannot_be_fitted_is_refused_with_the_option_at_fault(specs, needle):
    with pytest.raises(ValueError, match=needle):
        model().check(specs)


def test_the_size_of_a_model_is_bounded():
    """100,000 effects (900 kB) grew the fitter to 6 GB; they are refused before any is built
    (the count comes first); columns are counted too: ten drifts of 24 and the 24 linear
    ones are 264 > 256."""
    with pytest.raises(ValueError, match=f"100001 effects, at most {MAX_EFFECTS}"):
        model().check(["linear-ttl"] + [f"gate:start={k + 1}s,stop={k + 2}s" for k in range(100_000)])
    assert MAX_COLUMNS < 24 * 11
    with pytest.raises(ValueError, match=f"264 columns, at most {MAX_COLUMNS}"):
        model().check(["linear-ttl"] + ["drift"] * 10)
    assert len(model().check(["linear-ttl"] + ["drift"] * 9)) == 10

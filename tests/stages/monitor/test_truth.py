"""Unit tests of :mod:`stages.monitor.truth`: the truth drawn beside the fits (no bus in it)."""

import numpy as np
import pytest

from stages.monitor.truth import FitTruth
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.errors import ConfigError

#: A simulation's coefficient model as the telemetry meta names it: 1 mm/rad on all 24,
#: drifting by 1 mm/rad per day on the first
DAY = 86400.0
NAMED = {
    "coefficients": {
        "base": dict.fromkeys(COEFFICIENT_NAMES, 1e-3),
        "t_ref": 0.0,
        "drift_per_s": {COEFFICIENT_NAMES[0]: 1e-3 / DAY},
    }
}


def test_fits_drawn_before_the_truth_are_drawn_again_with_it():
    warnings = []
    truth = FitTruth(warnings.append)
    truth.add_fit(3, DAY, 2 * DAY, np.ones(24), np.full(24, 0.1))
    truth.add_fit(1, 0.0, DAY, np.zeros(24), np.full(24, 0.1))
    assert truth.mean(0.0, DAY) is None and list(truth.redraw()) == []
    assert truth.is_new(NAMED) and not truth.is_new(None)
    truth.load(NAMED, block=3600.0)
    truth.source = NAMED
    assert not truth.is_new(NAMED)
    drawn = list(truth.redraw())
    assert [(index, centre) for index, centre, *_ in drawn] == [(1, 0.5 * DAY), (3, 1.5 * DAY)]
    _, _, coefficients, sigma, mean = drawn[1]
    np.testing.assert_array_equal(coefficients, np.ones(24))
    np.testing.assert_array_equal(sigma, np.full(24, 0.1))
    # the drifting coefficient averaged over its window: 1 mm/rad + 1.5 days of drift
    assert mean[0] == pytest.approx(2.5e-3, rel=1e-9)
    assert mean[1] == pytest.approx(1e-3, rel=1e-9)
    assert warnings == []


def test_an_unusable_truth_is_an_error_at_load():
    with pytest.raises(ConfigError, match="base"):
        FitTruth(print).load({"coefficients": {"t_ref": 0.0}}, block=3600.0)


class _Failing:
    path = "truth.h5"

    def mean(self, t_start, t_stop):
        raise OSError("block 3 unreadable")


def test_a_truth_that_fails_is_dropped_with_a_warning():
    warnings = []
    truth = FitTruth(warnings.append)
    truth.add_fit(0, 0.0, DAY, np.zeros(24), np.zeros(24))
    truth.add_fit(1, DAY, 2 * DAY, np.zeros(24), np.zeros(24))
    truth.truth = _Failing()  # a truth file read block by block, broken under the monitor's feet
    assert list(truth.redraw()) == []
    assert truth.truth is None
    assert warnings == ["truth file truth.h5: block 3 unreadable; no more truth drawn"]
    assert truth.mean(0.0, DAY) is None

"""Unit tests of :mod:`streamer.tools.inspect_text`: the words of ``ttl inspect`` from its report's
parts (dicts as :func:`streamer.tools.inspect.inspect_run` builds them; no recordings, no bus)."""

from streamer.tools.inspect_text import (
    explained_in_words,
    fmt_ranges,
    refusal_text,
    timeline_text,
    topics_text,
    truth_test_lines,
)

DAY = 86400.0


def test_ranges_topics_and_refusals():
    assert fmt_ranges([]) == "-" and fmt_ranges([[0, 0], [2, 5]]) == "0,2-5"
    table = {
        "fit": {"distinct": 5, "indices": [[0, 5]], "missing": [[3, 3]], "duplicates": [1, 2, 4]},
        "tdi": {"distinct": 6, "indices": [[0, 5]], "missing": [], "duplicates": []},
    }
    assert topics_text(table) == "fit 5 [0-5] missing 3 dup 1-2,4; tdi 6 [0-5]"
    assert topics_text({}) == "-"
    forbidden = {"kind": "forbidden", "subject": "monitor", "action": "put", "key": "ttl/r1/fit", "time": "12:00"}
    assert refusal_text(forbidden) == "monitor may not put on ttl/r1/fit at 12:00"
    assert refusal_text({"kind": "tls", "message": "bad certificate"}) == "bad certificate"


def test_explained_in_words():
    assert explained_in_words({"explained_fraction": 0.874}) == "explains 87 % of the excess"
    glitches = {"explained_fraction": 0.0, "actions": [{"kind": "glitch", "explained_fraction": 0.9}, {"kind": "gate"}]}
    assert explained_in_words(glitches) == "models 2 transient(s), 90 % or more of each one's excess"
    mixed = {"explained_fraction": 0.5, "actions": [{"kind": "glitch"}, {"kind": "add"}]}
    assert explained_in_words(mixed) == "explains 50 % of the excess"


def test_the_timeline_in_words():
    timeline = {
        "models": [
            {
                "from_index": 0,
                "to_index": 23,
                "effects": ["linear-ttl"],
                "fits": 24,
                "by": "configured",
                "new_epoch": False,
                "added": [],
                "removed": [],
            },
            {
                "from_index": 24,
                "to_index": None,
                "effects": ["linear-ttl", "drift"],
                "fits": 1,
                "by": "adopt auto",
                "new_epoch": True,
                "added": ["drift"],
                "removed": [],
                "diagnosis_index": 23,
                "reason": "a drift",
                "recommendation": {"spec": "drift", "explained_fraction": 0.6, "log_bayes_factor": 12.345},
            },
        ],
        "gaps": [{"from_index": 30, "to_index": 31, "t_start": 1.25 * DAY, "t_stop": 1.3333 * DAY}],
        "excluded": [
            {
                "kind": "outlier",
                "from_index": 40,
                "to_index": 41,
                "count": 2,
                "z_max": 9.4,
                "t_start": 1.5 * DAY,
                "t_stop": 1.6 * DAY,
            },
            {
                "kind": "gated",
                "from_index": 50,
                "to_index": 50,
                "count": 1,
                "gate": [2 * DAY, 2.01 * DAY],
                "t_start": 2 * DAY,
                "t_stop": 2.04 * DAY,
            },
        ],
    }
    assert timeline_text(timeline) == [
        "  Timeline: the model from segment to segment (new couplings from segment(s) 24: the monitor's trends "
        "start a new series there)",
        "  segments 0-23    linear-ttl  (24 fits)",
        "      as configured",
        "  segments 24-     linear-ttl,drift  (1 fit)",
        "      + drift by adopt auto after the diagnosis of segment 23: a drift  [new model epoch]",
        "      recommended drift, explains 60 % of the excess, log Bayes factor 12.3",
        "  Gaps (no TDI segment: NaN pushed, window kept): segments 30-31 (1.250-1.333 d)",
        "  Left out of the fit: fits 40-41, 2 FFT segment(s) (1.500-1.600 d): outliers, up to 9 sigma above the window",
        "  Left out of the fit: fit 50, 1 FFT segment(s) (2.000-2.040 d): gated by the gate 2.000-2.010 d",
    ]
    assert timeline_text({}) == []


def test_the_truth_test_line():
    assert truth_test_lines(None) == []
    line = {
        "max_abs_error": 6.05e-5,
        "pull_rms": 1.44,
        "pull_rms_range": [0.64, 1.41],
        "chi2": 52.7,
        "n": 24,
        "p_value": 0.000638,
        "verdict": "too small",
    }
    assert truth_test_lines(line) == [
        "  last fit against the truth: max |error| 0.0605 mm/rad, pull RMS 1.44 (0.64-1.41 for honest sigmas "
        "with this fit's correlations), errors' chi2 52.7 for 24 (p 0.000638): sigmas too small"
    ]

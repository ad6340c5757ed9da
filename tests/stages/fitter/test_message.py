"""Unit tests of :mod:`stages.fitter.message`: the fit message's meta, its summary, its notices
(no bus in it)."""

import numpy as np
import pytest

from stages.fitter.message import fit_meta, fit_summary, notices, rolling_estimate
from streamer.bus.fit_record import SCHEMA, FitMessage
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.estimate.fit import FitResult

P = len(COEFFICIENT_NAMES)


def result(**kw) -> FitResult:
    fields = dict(
        names=tuple(COEFFICIENT_NAMES),
        coefficients=np.full(P, 1e-3),
        covariance=np.eye(P) * 1e-10,
        chi2=230.0,
        dof=200.0,
        band=(0.01, 0.1),
        method="gls",
        iterations=3,
        t_start=0.0,
        t_stop=86400.0,
        n_segments=24,
    )
    return FitResult(**(fields | kw))


def meta_of(res) -> FitMessage:
    return fit_meta(res, window_duration=86400.0, fft_segment=3600.0, segments_total=72, model=["linear-ttl"])


def test_fit_meta_is_a_checked_value_that_crosses_the_wire():
    meta = meta_of(result())
    header = meta.to_header()
    assert header["schema"] == SCHEMA
    assert header["chi2_dof"] == pytest.approx(1.15) and header["segments"] == 24
    assert header["model"] == ["linear-ttl"] and header["band"] == [0.01, 0.1]
    assert FitMessage.from_header(header, "fit 5") == meta


def test_fit_summary_and_rolling_estimate():
    res = result()
    arrays = {"coefficients": res.coefficients, "sigma": res.sigma, "covariance": res.covariance}
    summary = fit_summary("r1", 5, res, meta_of(res), arrays)
    assert (summary["run"], summary["index"], summary["segments"]) == ("r1", 5, 24)
    assert summary["t_end"] == 86400.0 and summary["chi2_dof"] == pytest.approx(1.15)
    assert summary["names"] == list(COEFFICIENT_NAMES) and summary["model"] == ["linear-ttl"]
    assert summary["fit"]["coefficients"][COEFFICIENT_NAMES[0]] == 1e-3
    assert rolling_estimate(arrays) == {"coefficients": [1e-3] * P, "sigma": [1e-5] * P}


def test_a_quiet_fit_says_nothing():
    res = result()
    said, meta = notices(5, res, meta_of(res))
    assert said == [] and meta.excluded is None


@pytest.mark.parametrize(
    "excluded, level, kind, words",
    [
        ({"t_start": 0.0, "t_stop": 3600.0, "gap": True}, "event", "segment-gap", "less than half valid samples"),
        ({"t_start": 0.0, "t_stop": 3600.0, "gate": [100.0, 200.0]}, "event", "segment-gated", "gate [100.0, 200.0]"),
        (
            {"t_start": 7200.0, "t_stop": 10800.0, "chi2_dof": 9.5, "z": 12.0, "reference": 1.02},
            "warning",
            "segment-excluded",
            "[7200, 10800] s is left out of the rolling fit: chi2/dof 9.500 at its own best fit, 12 sigma",
        ),
    ],
)
def test_an_fft_segment_left_out(excluded, level, kind, words):
    res = result(extra={"excluded": excluded})
    said, meta = notices(5, res, meta_of(res))
    assert [(lv, k) for lv, k, _, _ in said] == [(level, kind)]
    assert said[0][2].startswith("fit 5: ") and words in said[0][2]
    assert said[0][3] == excluded and meta.excluded == excluded


def test_a_fit_that_did_not_converge_is_a_warning():
    res = result(converged=False, iterations=50, extra={"last_change_sigma": 0.25})
    said, _ = notices(7, res, meta_of(res))
    ((level, kind, message, details),) = said
    assert (level, kind) == ("warning", "not-converged")
    assert "did not converge in 50 iterations" in message and "0.25 sigma" in message
    assert details == {"iterations": 50, "last_change_sigma": 0.25}


def test_a_model_that_fails_against_the_noise_model_is_a_warning():
    res = result()
    adequacy = {"chi2_dof": 3.2, "fails": True, "summary": ["0.01-0.03 Hz: chi2/dof 5.1"], "bands": []}
    meta = meta_of(res).with_fields({"adequacy": adequacy})
    said, _ = notices(9, res, meta)
    assert [(lv, k) for lv, k, _, _ in said] == [("warning", "model-inadequate")]
    assert said[0][2] == (
        "fit 9: the model linear-ttl fails against the instrument noise model "
        "(chi2/dof 3.200; 0.01-0.03 Hz: chi2/dof 5.1)"
    )
    said, _ = notices(9, res, meta_of(res).with_fields({"adequacy": adequacy | {"fails": False}}))
    assert said == []

"""Unit tests of :mod:`stages.monitor.noise`: the monitor's noise view (real segment headers from
the codec, a real Rerun recording in memory; no bus in it)."""

import numpy as np
import pytest
import rerun as rr

from stages.monitor.noise import NoiseCurves, trim
from streamer.bus.codec import decode, encode
from ttlcore.conventions import ARM_LENGTH, C

FS = 4.0
N = 3600 * 4
BAND = (1e-3, 0.1)


def header(index: int, ltt_mean=None):
    meta = {} if ltt_mean is None else {"ltt_mean": list(ltt_mean)}
    payload, attachment = encode(
        np.zeros((3, 8)), {"run": "r1", "index": index, "t0": 3600.0 * index, "fs": FS, "meta": meta}
    )
    return decode(payload, attachment)[0]


def test_trim_keeps_the_highest_keys():
    d = {i: i for i in range(12)}
    trim(d, keep=3)
    assert sorted(d) == [9, 10, 11]


@pytest.mark.filterwarnings("error::RuntimeWarning")  # a gap's all-NaN arms: silently not kept
def test_the_arms_of_a_segment():
    curves = NoiseCurves(BAND)
    nominal = np.full(6, ARM_LENGTH / C)
    np.testing.assert_array_equal(curves.ltt_of(header(0)), nominal)
    ltt = np.full((6, 100), 8.3) + np.arange(6)[:, None] * 0.01
    curves.telemetry(1, ltt)
    curves.telemetry(2, np.full((6, 100), np.nan))  # nothing usable: not kept
    curves.telemetry(3, ltt + 0.5)
    np.testing.assert_allclose(curves.ltt_of(header(1)), ltt[:, 0])
    np.testing.assert_allclose(curves.ltt_of(header(5)), ltt[:, 0] + 0.5)  # the latest known
    given = np.full(6, 8.25)
    np.testing.assert_array_equal(curves.ltt_of(header(1, given)), given)  # the meta first


def test_tdi_and_residual_curves_and_the_ratio_to_the_expected():
    stream = rr.RecordingStream("test_noise")
    memory = stream.memory_recording()
    curves = NoiseCurves(BAND)
    rng = np.random.default_rng(1)
    data = 1e-21 * rng.standard_normal((3, N))
    curves.tdi(stream, header(0), data)
    assert list(curves._ref) == [0]
    first = curves._ref[0]
    residual = {"residual": data, "ttl_model": np.zeros((3, N))}
    f, asd, ratio = curves.residual(stream, header(0), residual)
    assert curves._ref[0] is first  # the references of a segment computed once
    assert np.isfinite(ratio) and ratio > 0 and f.shape == asd.shape
    _, _, doubled = curves.residual(stream, header(0), {**residual, "residual": 2 * data})
    assert doubled == pytest.approx(2 * ratio, rel=1e-9)
    # an effect the subtractor took away is drawn; one with no matching meta is not
    parts = {**residual, "effect_model": 1e-22 * rng.standard_normal((1, 3, N))}
    curves.residual(stream, header(0), parts, effects=["drift"])
    curves.residual(stream, header(0), parts, effects=["drift", "step"])
    assert len(memory.drain_as_bytes()) > 0

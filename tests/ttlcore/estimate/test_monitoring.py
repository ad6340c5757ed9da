"""What the monitor computes, without the bus: the truth over a fit window, the longest
finite stretch, the channel ASD against the requirement's bins."""

import numpy as np
import pytest

from ttlcore.estimate.monitoring import FileTruth, ModelTruth, channel_asd, reference_curves, window_truth
from ttlcore.estimate.spectra import longest_run
from ttlcore.io.truth import CORE_DATASETS, TruthWriter, read_truth
from ttlcore.sim.coefficients import make_coefficients

FS = 0.1  # truth samples per second


def _truth_file(path, size, t0=100.0):
    t = t0 + np.arange(size) / FS
    coefficients = np.sin(np.arange(24)[:, None] + t / 500.0) * 1e-3
    w = TruthWriter(path, t0=t0, fs=FS, size=size, config={})
    for name, (rows, _) in CORE_DATASETS.items():
        w.append(name, coefficients if name == "coefficients" else np.zeros((len(rows), size)))
    return w.close(), coefficients


@pytest.mark.parametrize("span", [(100.0, 200.0), (150.0, 1710.0), (430.0, 2100.0), (100.0, 2100.0)])
def test_file_truth_averages_like_a_plain_mean_across_blocks(tmp_path, span):
    path, coefficients = _truth_file(tmp_path / "d.truth.h5", 200)
    truth = FileTruth(path, block=300.0)  # 30 samples a block: spans start, end and run across blocks
    a, b = (int(round((s - 100.0) * FS)) for s in span)
    expected = coefficients[:, a:b].mean(axis=1)
    np.testing.assert_allclose(truth.mean(*span), expected, rtol=1e-12)
    np.testing.assert_allclose(truth.mean(*span), expected, rtol=1e-12)  # again, from the cached blocks
    assert truth.mean(5000.0, 6000.0) is None  # after the file: nothing
    assert read_truth(path).coefficients.shape == (24, 200)


def test_window_truth_picks_the_model_or_the_file(tmp_path):
    model = make_coefficients("paper").with_drift({"12.phi.rx": 1e-3})
    picked = window_truth({"coefficients": model.describe()})
    assert isinstance(picked, ModelTruth)
    np.testing.assert_allclose(picked.mean(0.0, 3600.0), model.mean(0.0, 3600.0))
    path, _ = _truth_file(tmp_path / "d.truth.h5", 50)
    assert isinstance(window_truth(str(path)), FileTruth)
    with pytest.raises(Exception, match="no-such"):
        window_truth(str(tmp_path / "no-such.truth.h5"))


def test_longest_run():
    ok = np.array([1, 1, 0, 1, 1, 1, 0, 1], dtype=bool)
    assert longest_run(ok) == slice(3, 6)
    assert longest_run(np.ones(4, bool)) == slice(0, 4)
    assert longest_run(np.zeros(4, bool)) == slice(0, 0)


def test_channel_asd_uses_the_longest_finite_stretch_and_refuses_too_few_samples():
    rng = np.random.default_rng(0)
    fs = 4.0
    x = rng.normal(0.0, 1e-20, 20000)
    f, asd, f_welch = channel_asd(x, fs)
    gapped = x.copy()
    gapped[:100] = np.nan  # the longest finite stretch is what is left after the gap
    fg, asdg, _ = channel_asd(gapped, fs)
    assert np.all(asd > 0) and np.all(np.diff(f) > 0) and f_welch[0] > 0
    assert np.median(asdg / np.interp(fg, f, asd)) == pytest.approx(1.0, rel=0.1)
    ref = reference_curves(f_welch, np.full(6, 8.34))
    assert set(ref) == {"expected", "requirement"} and all(np.all(a > 0) for _, a in ref.values())
    short = np.full(1000, np.nan)
    short[10:60] = 1.0
    with pytest.raises(ValueError, match="too few finite samples"):
        channel_asd(short, fs)


def test_file_truth_reads_each_block_once_under_a_sliding_window(tmp_path, monkeypatch):
    """A window sliding by whole blocks with edges inside blocks (as the rolling fit's valid
    span lies): every block of the file is read once, the edges come from memory."""
    import ttlcore.estimate.monitoring as monitoring

    path, coefficients = _truth_file(tmp_path / "d.truth.h5", 200)
    reads = []
    monkeypatch.setattr(monitoring, "read_truth", lambda p, a, b: reads.append((a, b)) or read_truth(p, a, b))
    truth = FileTruth(path, block=300.0)  # 30 samples a block
    for start in range(0, 150, 30):
        a, b = start + 7, start + 53  # edges 7 samples into a block and 23 into the next
        np.testing.assert_allclose(
            truth.mean(100.0 + a / FS, 100.0 + b / FS), coefficients[:, a:b].mean(axis=1), rtol=1e-12
        )
    blocks = reads[1:]  # the first read is the head (t0, fs)
    assert blocks == [(k * 30, (k + 1) * 30) for k in range(6)], blocks

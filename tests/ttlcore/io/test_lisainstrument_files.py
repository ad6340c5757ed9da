"""Reading lisainstrument 2.x measurement files, against pytdi and lisainstrument itself.

One one-hour lisainstrument file (Keplerian arms, so the delays and Doppler factors vary;
TTL with lisainstrument's default coefficients and angular jitter on; clock, modulation and
ranging noise off) is simulated once for the module (about 7 s on 2 cores).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from lisainstrument_sim import simulate_lisainstrument

from ttlcore.conventions import COEFFICIENT_NAMES, LINKS, MOSAS, C, link_index
from ttlcore.errors import TelemetryError
from ttlcore.io.lisainstrument import (
    BEATNOTE_DATASETS,
    DWS_ETA_DATASET,
    DWS_PHI_DATASET,
    ETA_TERMS,
    MPR_DATASET,
    is_lisainstrument,
    lisainstrument_truth,
    read_lisainstrument,
)
from ttlcore.io.reader import file_kind, read_telemetry
from ttlcore.io.telemetry import Telemetry, write_telemetry
from ttlcore.tdi.interpolation import delay

ORDER = 31
DELAY_ORDER = 5


@pytest.fixture(scope="module")
def li_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("lisainstrument") / "measurements.h5"
    simulate_lisainstrument(path, duration=3600, orbits="keplerian", ttl=True, jitter=True, seed=3)
    return path


@pytest.fixture(scope="module")
def tm(li_file):
    return read_lisainstrument(li_file, order=ORDER, delay_order=DELAY_ORDER)


@pytest.fixture(scope="module")
def metadata(li_file):
    with h5py.File(li_file, "r") as f:
        return json.loads(f.attrs["metadata_json"])


def _lowpass_rel_rms(x, ref, fs, fmax=1.0, edge=64):
    """Relative RMS of ``x - ref`` over frequencies below ``fmax``.

    Both are cut by ``edge`` samples at each end and Hann-windowed before the FFT; the
    ratio is sqrt(sum |FFT(x - ref)|^2 / sum |FFT(ref)|^2) over the bins below ``fmax``.
    """
    x = np.asarray(x)[edge:-edge]
    ref = np.asarray(ref)[edge:-edge]
    w = np.hanning(ref.size)
    f = np.fft.rfftfreq(ref.size, 1 / fs)
    keep = f < fmax
    d = np.fft.rfft((x - ref) * w)[keep]
    r = np.fft.rfft(ref * w)[keep]
    return float(np.sqrt(np.sum(np.abs(d) ** 2) / np.sum(np.abs(r) ** 2)))


def _copy(src: Path, tmp_path: Path, name: str = "copy.h5") -> Path:
    dst = tmp_path / name
    shutil.copyfile(src, dst)
    return dst


# ---------------------------------------------------------------------------
# Detection
# ---------------------------------------------------------------------------


def test_detects_lisainstrument_files_and_only_them(li_file, tm, tmp_path):
    with h5py.File(li_file, "r") as f:
        assert is_lisainstrument(f)
    assert file_kind(li_file) == "lisainstrument"
    ours = write_telemetry(tmp_path / "ours.h5", tm.slice(0, 100))
    with h5py.File(ours, "r") as f:
        assert not is_lisainstrument(f)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.attrs["version"] = "1.0"
        f["x"] = np.zeros(3)
    with h5py.File(other, "r") as f:
        assert not is_lisainstrument(f)


# ---------------------------------------------------------------------------
# eta against pytdi
# ---------------------------------------------------------------------------


def test_eta_terms_are_pytdis_eta_set():
    # Our table of the reduction is pytdi's ETA_SET (= ETA_ij_XI @ XI_SET, simplified);
    # the eta variables hold single delays only, so no nested delay has to be built.
    from pytdi.intervar import ETA_SET

    for link in LINKS:
        ref = {}
        for measurement, polynomial in ETA_SET[f"eta_{link}"].simplified().components.items():
            for factor, operators in polynomial:
                assert len(operators) <= 1, "eta variables have single delays only"
                if operators:
                    assert operators == [f"D_{link}"]
                ref[(measurement, bool(operators))] = ref.get((measurement, bool(operators)), 0.0) + factor
        local, remote = ETA_TERMS[link]
        ours = {(m, False): c for m, c in local} | {(m, True): c for m, c in remote}
        assert ours == {k: v for k, v in ref.items() if v != 0}


@pytest.mark.parametrize("order", [ORDER, 11])
def test_eta_agrees_with_pytdi_compute_etas(li_file, tm, order):
    """Our eta equal pytdi's ``compute_etas`` on the same file.

    pytdi (``Data.from_instrument(path)``, fluctuations in Hz, MPRs as delays, numerical
    delay derivatives) is fed Hz, so its eta are in Hz: we compare ``eta * central_freq``.
    pytdi zero-pads before the first sample, so its first ``dropped_leading_samples`` are
    wrong where ours are dropped; we align on the first sample we keep.

    Tolerance: the brief's 1e-8 relative RMS below 1 Hz.  Both sides evaluate the same
    Lagrange polynomials (ttlcore.tdi.interpolation agrees with pytdi.dsp to ~1e-15) and the same
    Doppler factors, so the actual difference is float64 rounding (~1e-16); we also require
    1e-12 over the full band, which any error in a coefficient, a delay or a Doppler factor
    (~3e-9 here) would exceed.  eta_31 and eta_21 carry no laser noise with N1-12 locking,
    so they test the secondary-noise level, not only the laser noise.
    """
    from pytdi import Data
    from pytdi.intervar import compute_etas

    ours = tm if order == ORDER else read_lisainstrument(li_file, order=order)
    data = Data.from_instrument(str(li_file))
    etas = compute_etas(data, order=order, delay_order=DELAY_ORDER)
    nu0 = ours.config["central_freq"]
    k = ours.config["dropped_leading_samples"]
    for row, link in enumerate(LINKS):
        ref = np.asarray(etas[f"eta_{link}"])[k : k + ours.size]
        assert ref.shape == (ours.size,)
        mine = ours.eta[row] * nu0
        assert _lowpass_rel_rms(mine, ref, ours.fs, fmax=1.0) < 1e-8, link
        full = np.sqrt(np.mean((mine - ref) ** 2) / np.mean(ref**2))
        assert full < 1e-12, (link, full)


def test_delays_vary_so_doppler_terms_are_exercised(tm):
    rates = np.array([np.mean(np.gradient(d, 1 / tm.fs)) for d in tm.ltt])
    assert np.max(np.abs(rates)) > 1e-9


def test_leading_samples_dropped_exactly_where_delayed_terms_are_undefined(li_file, tm, metadata):
    # sample k of D_ij x needs x[k + floor(-d_ij fs) - (order - 1)/2] >= 0
    with h5py.File(li_file, "r") as f:
        mprs = np.stack([f[f"{MPR_DATASET}/{m}"][()] for m in LINKS])
    k = np.arange(mprs.shape[1])
    first_valid = [int(np.argmax(k + np.floor(-d * tm.fs) - (ORDER - 1) // 2 >= 0)) for d in mprs]
    assert tm.config["dropped_leading_samples"] == max(first_valid) == 49  # 8.33 s at 4 Hz, order 31
    assert tm.config["dropped_trailing_samples"] == 0
    assert tm.size == metadata["size"] - 49
    assert tm.t0 == pytest.approx(metadata["t0"] + 49 / metadata["fs"], abs=1e-9)
    assert np.all(np.isfinite(tm.eta))


# ---------------------------------------------------------------------------
# DWS, delays, sampling, configuration
# ---------------------------------------------------------------------------


def test_dws_ltt_and_sampling_are_the_files(li_file, tm, metadata):
    k = tm.config["dropped_leading_samples"]
    sl = slice(k, k + tm.size)
    with h5py.File(li_file, "r") as f:
        for row, mosa in enumerate(MOSAS):
            assert np.array_equal(tm.dws_phi[row], f[f"{DWS_PHI_DATASET}/{mosa}"][sl])
            assert np.array_equal(tm.dws_eta[row], f[f"{DWS_ETA_DATASET}/{mosa}"][sl])
            assert np.array_equal(tm.ltt[row], f[f"{MPR_DATASET}/{mosa}"][sl])
    assert tm.fs == metadata["fs"] == 4.0
    assert np.all((tm.ltt > 8.2) & (tm.ltt < 8.5))
    # DWS readouts are angular velocities: jitter 5 nrad/sqrt(Hz) -> ~1e-8 rad/s RMS
    assert 1e-10 < np.std(tm.dws_phi) < 1e-6


def test_config_records_the_files_metadata(tm, metadata, li_file):
    cfg = tm.config
    json.dumps(cfg)  # JSON-serialisable
    assert cfg["source_format"] == "lisainstrument"
    assert cfg["lisainstrument_version"].startswith("2.")
    assert cfg["central_freq"] == metadata["central_freq"]
    assert cfg["dt"] == metadata["dt"] and cfg["size"] == metadata["size"] and cfg["t0"] == metadata["t0"]
    assert cfg["orbits"].endswith("measurements-orbits.h5")
    noises = cfg["noises"]
    assert not noises["clock"] and not noises["modulation"] and not noises["ranging"]
    assert noises["laser"] and noises["oms"] and noises["testmass"] and noises["backlink"]
    assert noises["angular_jitter"] and noises["dws"] and noises["ttl"]
    assert cfg["ttl_coeffs"] == lisainstrument_truth(li_file)
    assert "aafilter_coeffs" not in cfg["lisainstrument_metadata"]


def test_eta_is_fractional_frequency(tm):
    # laser noise 30 Hz/sqrt(Hz) over ~2 Hz of band -> tens of Hz -> ~1e-13 fractional
    rms = np.sqrt(np.mean(tm.eta[link_index("12")] ** 2))
    assert 1e-15 < rms < 1e-11


def test_read_telemetry_autodetects_and_returns_the_same(li_file, tm):
    other = read_telemetry(li_file)
    assert isinstance(other, Telemetry)
    assert other.t0 == tm.t0 and other.fs == tm.fs and other.source == str(li_file)
    for name in ("eta", "dws_phi", "dws_eta", "ltt"):
        assert np.array_equal(getattr(other, name), getattr(tm, name)), name
    assert other.config == tm.config
    part = read_telemetry(li_file, 10, 110)
    assert part.size == 100 and part.t0 == pytest.approx(tm.t0 + 10 / tm.fs)
    assert np.array_equal(part.eta, tm.eta[:, 10:110])


# ---------------------------------------------------------------------------
# TTL truth and conventions
# ---------------------------------------------------------------------------


def test_truth_is_lisainstruments_default_set(li_file):
    from lisainstrument.instru import instru_defaults as d

    truth = lisainstrument_truth(li_file)
    assert list(truth) == list(COEFFICIENT_NAMES)
    sets = {
        ("phi", "rx"): d.TTL_COEFFS_LOCAL_PHIS,
        ("phi", "tx"): d.TTL_COEFFS_DISTANT_PHIS,
        ("eta", "rx"): d.TTL_COEFFS_LOCAL_ETAS,
        ("eta", "tx"): d.TTL_COEFFS_DISTANT_ETAS,
    }
    for (angle, side), table in sets.items():
        for mosa_id, value in table.items():
            assert truth[f"{mosa_id.value}.{angle}.{side}"] == value
    magnitudes = np.abs(list(truth.values()))
    assert 5e-5 < magnitudes.min() and magnitudes.max() < 2.2e-3  # 0.06 .. 2.1 mm/rad


def test_ttl_sign_and_coefficient_indexing_in_lisainstrument(tmp_path):
    """lisainstrument's TTL is docs/physics.md's ``ttl_ij = -(1/c)[C_rx,ij angdot_ij + D_ij C_tx,ji angdot_ji]``.

    Only jitter and TTL on, six lasers on cavities (so a beam's TTL stays in its own beat
    note), DWS noise off (readouts = true angular velocities).  Coefficient ``12.phi.tx``
    (lisainstrument: distant phi of MOSA 12) must show on link 21, delayed by D_21;
    ``23.eta.rx`` (local eta of MOSA 23) on link 23, undelayed; all other eta stay zero.
    Agreement below 1 Hz is ~5e-7 (lisainstrument delays at 16 Hz before its anti-alias
    filter, we at 4 Hz after); a flipped sign would give 2.
    """
    coeffs = {name: 0.0 for name in COEFFICIENT_NAMES}
    coeffs["12.phi.tx"] = 2e-3
    coeffs["23.eta.rx"] = 1e-3
    path = tmp_path / "ttl-only.h5"
    simulate_lisainstrument(
        path,
        duration=600,
        orbits="static",
        ttl_coeffs=coeffs,
        lock="six",
        laser=False,
        oms=False,
        testmass=False,
        backlink=False,
        reciprocal_backlink=False,
        longitudinal_jitter=False,
        dws_noise=False,
    )
    assert lisainstrument_truth(path) == coeffs
    t = read_lisainstrument(path)
    i12, i21, i23 = link_index("12"), link_index("21"), link_index("23")
    expected_21 = -(1 / C) * 2e-3 * delay(t.dws_phi[i12], t.ltt[i21], t.fs)
    expected_23 = -(1 / C) * 1e-3 * t.dws_eta[i23]
    assert _lowpass_rel_rms(t.eta[i21], expected_21, t.fs, edge=100) < 1e-5
    assert _lowpass_rel_rms(t.eta[i23], expected_23, t.fs, edge=100) < 1e-5
    for link in ("12", "31", "13", "32"):
        assert np.all(t.eta[link_index(link)] == 0), link


# ---------------------------------------------------------------------------
# Errors name the file and the dataset or attribute
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "dataset",
    [f"{BEATNOTE_DATASETS['ref']}/23", f"{BEATNOTE_DATASETS['sci']}/12", f"{MPR_DATASET}/31", f"{DWS_ETA_DATASET}/21"],
)
def test_missing_dataset_is_named(li_file, tmp_path, dataset):
    bad = _copy(li_file, tmp_path)
    with h5py.File(bad, "r+") as f:
        del f[dataset]
    for reader in (read_lisainstrument, read_telemetry):
        with pytest.raises(TelemetryError) as err:
            reader(bad)
        assert err.value.path == str(bad)
        assert err.value.dataset == dataset
        assert str(bad) in str(err.value) and dataset in str(err.value)


@pytest.mark.parametrize(
    "key, value, where",
    [
        ("dt", -0.25, "@metadata_json[dt]"),
        ("dt", 0.0, "@metadata_json[dt]"),
        ("fs", 2.0, "@metadata_json[fs]"),
        ("t0", None, "@metadata_json[t0]"),
        ("central_freq", "big", "@metadata_json[central_freq]"),
    ],
)
def test_bad_sampling_metadata_is_named(li_file, tmp_path, key, value, where):
    bad = _copy(li_file, tmp_path)
    with h5py.File(bad, "r+") as f:
        md = json.loads(f.attrs["metadata_json"])
        md[key] = value
        f.attrs["metadata_json"] = json.dumps(md)
    with pytest.raises(TelemetryError) as err:
        read_telemetry(bad)
    assert err.value.path == str(bad) and err.value.dataset == where


def test_size_mismatch_is_named(li_file, tmp_path, metadata):
    bad = _copy(li_file, tmp_path)
    with h5py.File(bad, "r+") as f:
        md = json.loads(f.attrs["metadata_json"])
        md["size"] += 4
        md["duration"] += 1.0
        f.attrs["metadata_json"] = json.dumps(md)
    with pytest.raises(TelemetryError) as err:
        read_lisainstrument(bad)
    assert err.value.path == str(bad)
    assert err.value.dataset.startswith(BEATNOTE_DATASETS["sci"])
    assert str(metadata["size"] + 4) in str(err.value)


def test_wrong_shape_and_non_finite_data_are_named(li_file, tmp_path):
    bad = _copy(li_file, tmp_path, "shape.h5")
    name = f"{BEATNOTE_DATASETS['tmi']}/32"
    with h5py.File(bad, "r+") as f:
        data = f[name][()]
        del f[name]
        f[name] = np.stack([data, data])
    with pytest.raises(TelemetryError, match="shape") as err:
        read_lisainstrument(bad)
    assert err.value.dataset == name

    # NaN is a gap (tests/ttlcore/io/test_lisainstrument_gaps.py); an infinity is an error
    bad = _copy(li_file, tmp_path, "inf.h5")
    name = f"{MPR_DATASET}/12"
    with h5py.File(bad, "r+") as f:
        f[name][100] = np.inf
    with pytest.raises(TelemetryError, match="infinite.*sample 100") as err:
        read_lisainstrument(bad)
    assert err.value.dataset == name


def test_truncated_file_is_named(li_file, tmp_path):
    bad = tmp_path / "truncated.h5"
    raw = li_file.read_bytes()
    bad.write_bytes(raw[: len(raw) // 2])
    for reader in (read_lisainstrument, read_telemetry):
        with pytest.raises(TelemetryError) as err:
            reader(bad)
        assert err.value.path == str(bad) and str(bad) in str(err.value)


def test_unsupported_version_is_named(li_file, tmp_path):
    bad = _copy(li_file, tmp_path)
    with h5py.File(bad, "r+") as f:
        f.attrs["version_format"] = "1.4"
    with pytest.raises(TelemetryError, match="not supported") as err:
        read_telemetry(bad)
    assert err.value.dataset == "@version_format"


def test_bad_interpolation_order_is_rejected(li_file):
    with pytest.raises(ValueError, match="odd"):
        read_lisainstrument(li_file, order=30)
    with pytest.raises(ValueError, match="odd"):
        read_lisainstrument(li_file, delay_order=4)

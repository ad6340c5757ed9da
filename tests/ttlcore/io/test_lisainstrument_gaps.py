"""Gaps in lisainstrument files: NaN in the datasets is missing data, read as gaps (issue 31).

One 15-minute lisainstrument file (Keplerian arms, so the delays vary) is simulated once for
the module (about 5 s); a copy gets NaN spans the way lisa-gap makes them (a planned-gap mask
of ``lisagap.GapMaskGenerator`` with ``treat_as_nan=True`` multiplies every beat note, MPR and
DWS series), and a few spans in one dataset each: a DWS readout, an MPR, one beat note that
enters two eta variables (undelayed in one, delayed in the other), the sci beat note from the
first sample.  The expected gaps are written out here from the reduction's stencil.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from lisainstrument_sim import simulate_lisainstrument

from ttlcore.conventions import LINKS, MOSAS
from ttlcore.errors import TelemetryError
from ttlcore.io.lisainstrument import (
    BEATNOTE_DATASETS,
    DWS_ETA_DATASET,
    DWS_PHI_DATASET,
    MPR_DATASET,
    read_lisainstrument,
)
from ttlcore.io.reader import read_telemetry

ORDER = 31
DURATION = 900.0
FS = 4.0
HALF = (ORDER - 1) // 2  # 15: the stencil reads 15 samples before and 16 after its base

ALL = [
    f"{group}/{m}"
    for group in (*BEATNOTE_DATASETS.values(), MPR_DATASET, DWS_PHI_DATASET, DWS_ETA_DATASET)
    for m in MOSAS
]
# spans [start, stop) of file samples in one dataset each
ONE_DATASET = {
    f"{DWS_ETA_DATASET}/32": (600, 680),
    f"{MPR_DATASET}/23": (1700, 1760),
    f"{BEATNOTE_DATASETS['tmi']}/12": (2900, 2950),  # tmi_12: eta_12 undelayed, eta_21 delayed by D_21
    f"{BEATNOTE_DATASETS['sci']}/12": (0, 100),  # from the first sample: eta_12 only
}


def lisagap_mask(t: np.ndarray) -> np.ndarray:
    """lisa-gap's planned gaps, two of 30 s in the 15 min (at ~300 and ~600 s), NaN in them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import lisagap
    per_day = 3 * 86400 / DURATION
    defs = {"planned": {"pause": {"rate_per_year": per_day * 365.25, "duration_hr": 30 / 3600}}, "unplanned": {}}
    return np.asarray(lisagap.GapMaskGenerator(t, defs, treat_as_nan=True, planseed=31).generate_mask(), dtype=float)


def stretches(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    base = tmp_path_factory.mktemp("li-gaps")
    clean = base / "clean.h5"
    simulate_lisainstrument(clean, duration=DURATION, fs=FS, orbits="keplerian", seed=31)
    with h5py.File(clean, "r") as f:
        mprs = {m: f[f"{MPR_DATASET}/{m}"][()] for m in MOSAS}  # as they were, for the expectations
    gapped = base / "gapped.h5"
    shutil.copyfile(clean, gapped)
    with h5py.File(gapped, "r+") as f:
        md = json.loads(f.attrs["metadata_json"])
        t = md["t0"] + np.arange(md["size"]) / md["fs"]
        mask = lisagap_mask(t)
        for name in ALL:
            f[name][...] = f[name][()] * mask  # what lisa-gap does to a series
        for name, (a, b) in ONE_DATASET.items():
            f[name][a:b] = np.nan
    common = stretches(np.isnan(mask))
    assert len(common) == 2 and all(b - a == 120 for a, b in common), common
    return {"clean": clean, "gapped": gapped, "common": common, "mprs": mprs}


@pytest.fixture(scope="module")
def both(files):
    return read_lisainstrument(files["clean"], order=ORDER), read_lisainstrument(files["gapped"], order=ORDER)


def expected_missing(files, size: int) -> np.ndarray:
    """(6, size) missing eta samples of the file, from the spans and the stencil of D_ij.

    A delayed beat note's gap [a, b) takes eta_ij over
    [a + ceil(d fs) - (ORDER + 1)/2, b + ceil(d fs) + (ORDER - 1)/2) (d at the gap: the
    delays change by ~1e-5 samples over the file); an MPR's gap takes eta_ij one sample more
    each side (the Doppler factor's centred gradient); an undelayed term, the gap itself.
    """
    out = np.zeros((6, size), dtype=bool)
    links = {link: i for i, link in enumerate(LINKS)}

    def delayed(row, a, b):
        shift = math.ceil(files["mprs"][LINKS[row]][min(b, size - 1)] * FS)
        out[row, max(a + shift - HALF - 1, 0) : b + shift + HALF] = True

    for a, b in files["common"]:  # every dataset: every eta, undelayed and delayed terms
        out[:, a - 1 : b + 1] = True  # the MPRs' reach
        for row in range(6):
            delayed(row, a, b)
    a, b = ONE_DATASET[f"{MPR_DATASET}/23"]
    out[links["23"], a - 1 : b + 1] = True
    a, b = ONE_DATASET[f"{BEATNOTE_DATASETS['tmi']}/12"]
    out[links["12"], a:b] = True
    delayed(links["21"], a, b)
    a, b = ONE_DATASET[f"{BEATNOTE_DATASETS['sci']}/12"]
    out[links["12"], a:b] = True
    return out


def test_gapped_file_reads_with_its_gaps_where_the_stencil_puts_them(files, both):
    clean, tm = both
    k = clean.config["dropped_leading_samples"]
    assert tm.config["dropped_leading_samples"] == k == 49  # a gap from sample 0 does not move t0
    assert tm.t0 == clean.t0 and tm.size == clean.size
    size = k + tm.size
    want = expected_missing(files, size)[:, k:]
    assert np.array_equal(~np.isfinite(tm.eta), want), [
        (LINKS[r], stretches(~np.isfinite(tm.eta[r])), stretches(want[r])) for r in range(6)
    ]
    # the DWS: NaN exactly where the file has none
    for rows, name in ((tm.dws_phi, DWS_PHI_DATASET), (tm.dws_eta, DWS_ETA_DATASET)):
        for r, m in enumerate(MOSAS):
            with h5py.File(files["gapped"], "r") as f:
                assert np.array_equal(np.isnan(rows[r]), np.isnan(f[f"{name}/{m}"][k:])), (name, m)
    # the analytic reach: 8.3 s delays at 4 Hz are ceil(33.x) = 34 samples, plus the half-stencil
    d_max = max(float(np.max(d)) for d in files["mprs"].values())
    reach = math.ceil(d_max * FS) + HALF
    assert reach == 49
    gaps = tm.config["gaps"]
    assert gaps["reach_after_s"] == reach / FS and gaps["reach_before_s"] == 0.0 and gaps["mpr_reach_s"] == 1 / FS
    # each lisa-gap gap: from its first sample (less the MPRs' one) to `reach` after its end
    spans = [(a + k, b + k) for a, b in tm.nan_stretches()]  # in samples of the file
    for a, b in files["common"]:
        assert (a - 1, b + reach) in spans, (a, b, spans)


def test_eta_outside_the_gaps_is_the_clean_files(both):
    clean, tm = both
    ok = ~tm.missing()
    assert 0.7 < ok.mean() < 0.9
    scale = np.max(np.abs(clean.eta))
    assert np.max(np.abs(tm.eta[:, ok] - clean.eta[:, ok])) <= 1e-14 * scale
    # and each eta wherever it alone is finite (the other links' gaps do not reach it)
    both_finite = np.isfinite(tm.eta)
    assert np.max(np.abs(tm.eta[both_finite] - clean.eta[both_finite])) <= 1e-14 * scale
    for name in ("dws_phi", "dws_eta"):
        a, b = getattr(tm, name), getattr(clean, name)
        assert np.array_equal(a[np.isfinite(a)], b[np.isfinite(a)])


def test_mprs_are_interpolated_across_their_gaps(files, both):
    clean, tm = both
    assert np.all(np.isfinite(tm.ltt))
    # smooth delays: a straight line across 30 s misses them by far less than a picosecond
    assert np.max(np.abs(tm.ltt - clean.ltt)) < 1e-12
    k = clean.config["dropped_leading_samples"]
    a, b = ONE_DATASET[f"{MPR_DATASET}/23"]
    row = LINKS.index("23")
    assert not np.array_equal(tm.ltt[row, a - k : b - k], clean.ltt[row, a - k : b - k])  # filled, not kept


def test_gaps_are_recorded_in_the_config(files, both):
    _, tm = both
    gaps = tm.config["gaps"]
    json.dumps(gaps)
    missing = tm.missing()
    assert gaps["samples_missing"] == int(missing.sum()) and gaps["seconds_missing"] == missing.sum() / FS
    assert gaps["spans_s"] == [[tm.t0 + a / FS, tm.t0 + b / FS] for a, b in tm.nan_stretches()]
    assert gaps["spans_left_off"] == 0
    with h5py.File(files["gapped"], "r") as f:
        t0_file = json.loads(f.attrs["metadata_json"])["t0"]
    datasets = gaps["datasets"]
    assert set(datasets) == set(ALL)
    for name, (a, b) in ONE_DATASET.items():
        assert datasets[name]["samples_missing"] == (b - a) + 240
        assert [t0_file + a / FS, t0_file + b / FS] in datasets[name]["spans_s"]
    assert datasets[f"{MPR_DATASET}/12"]["spans_s"] == [
        [t0_file + a / FS, t0_file + b / FS] for a, b in files["common"]
    ]
    assert gaps["mprs_interpolated"] == sorted(f"{MPR_DATASET}/{m}" for m in MOSAS)
    # and the clean file says it has none
    clean = both[0].config["gaps"]
    assert clean["samples_missing"] == 0 and clean["spans_s"] == [] and clean["datasets"] == {}


def test_read_telemetry_reads_the_gaps_too(files, both):
    _, tm = both
    other = read_telemetry(files["gapped"])
    assert np.array_equal(other.eta, tm.eta, equal_nan=True)
    assert other.nan_stretches() == tm.nan_stretches()


@pytest.mark.parametrize("name", [f"{BEATNOTE_DATASETS['ref']}/31", f"{DWS_PHI_DATASET}/13", f"{MPR_DATASET}/21"])
def test_an_infinity_is_refused_naming_the_dataset(files, tmp_path, name):
    bad = tmp_path / "inf.h5"
    shutil.copyfile(files["gapped"], bad)
    with h5py.File(bad, "r+") as f:
        f[name][2000] = -np.inf
    with pytest.raises(TelemetryError, match="infinite values .first at sample 2000") as err:
        read_lisainstrument(bad)
    assert err.value.dataset == name and name in str(err.value)


def test_a_file_without_a_valid_sample_is_refused(files, tmp_path):
    # every series NaN: the delays cannot even be interpolated
    bad = tmp_path / "all-nan.h5"
    shutil.copyfile(files["clean"], bad)
    with h5py.File(bad, "r+") as f:
        for name in ALL:
            f[name][...] = np.nan
    with pytest.raises(TelemetryError, match="no valid sample") as err:
        read_telemetry(bad)
    assert err.value.dataset == f"{MPR_DATASET}/12"
    # the delays there but no beat note: no eta sample
    bad = tmp_path / "no-beatnotes.h5"
    shutil.copyfile(files["clean"], bad)
    with h5py.File(bad, "r+") as f:
        for group in BEATNOTE_DATASETS.values():
            for m in MOSAS:
                f[f"{group}/{m}"][...] = np.nan
    with pytest.raises(TelemetryError, match="no valid sample: every sample") as err:
        read_lisainstrument(bad)
    assert err.value.dataset and err.value.dataset.startswith("debug/")


if __name__ == "__main__":
    sys.exit(pytest.main([str(Path(__file__)), "-q"]))

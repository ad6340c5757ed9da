"""Tests of ``ttl scenarios`` (ttlcore.app.scenarios).

The fast test runs one short merger case (3 h, one variant): the files, the table, the
GW-intact check and the bookkeeping of "with GW minus without". The science test runs the
whole command as the issue asks (all cases, three variants, one day each) and checks the
paper's numbers: max |C_fit - C_true| below 0.1 mm/rad (0.06 without a merger), the GW-
induced shift below 2 sigma unless the GW is loud in the band, the GW left intact by the
subtraction, and the run time (< 45 min on the 2-core machine).
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from ttlcore.app.scenarios import PAPER_CASES, run_scenarios
from ttlcore.errors import TTLError

SHORT_MERGER = ["--cases", "mbhb2", "--variants", "paper", "--duration", "3h", "--seed", "2", "--quiet"]


@pytest.fixture(scope="module")
def short_merger(tmp_path_factory):
    """``ttl scenarios`` of one short merger case, in this process: (output dir, stdout)."""
    import contextlib
    import io

    from ttlcore.cli.main import main

    out = tmp_path_factory.mktemp("scenarios")
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        rc = main(["scenarios", "--out", str(out), *SHORT_MERGER])
    assert rc == 0
    return out, text.getvalue()


def test_short_merger_case(short_merger):
    tmp_path, text = short_merger
    assert "mbhb2" in text
    assert (tmp_path / "summary.json").is_file() and (tmp_path / "summary.md").is_file()
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["variants"]["paper"]["cases"][0]["case"] == "mbhb2"
    assert not list(tmp_path.glob(".*tmp*"))  # atomic writes leave no temporaries
    row = s["variants"]["paper"]["cases"][0]
    for key in ("asd", "gw_intact", "coefficients"):
        assert (tmp_path / "paper" / f"mbhb2_{key}.png").stat().st_size > 10_000
    # the merger is in the middle of the 3 h (t_c scaled with the duration)
    assert row["t_c"] == pytest.approx(11.22e6 + 0.04e6 * 3 / 24)
    # a loud merger (in-band SNR in the thousands) dominates many bins; the subtraction leaves it intact
    assert row["snr_band_x2"] > 1000
    gi = row["gw_intact"]
    assert gi["n_bins"] > 20 and gi["pass"] and gi["max_relative_deviation"] < 0.05
    # coefficient errors are those of the fit against the simulation's truth (3 h: sigma is
    # ~1.4x a day's), within the paper's 0.1 mm/rad for merger days
    assert row["max_abs_error_mm"] < 0.1
    assert row["chi2_dof"] == pytest.approx(1.0, abs=0.2)
    # shift = (with GW) - (without) over sigma, consistent with the per-coefficient table
    z = np.array(list(row["shift_over_sigma"].values()))
    assert row["shift_over_sigma_max"] == pytest.approx(np.max(np.abs(z)), abs=1e-3)
    assert "| mbhb2 |" in (tmp_path / "summary.md").read_text()


def _flat(x, path=""):
    """Nested JSON as {path: value}, floats as pytest.approx(rel=1e-12)."""
    if isinstance(x, dict):
        return {k: v for key, val in x.items() for k, v in _flat(val, f"{path}/{key}").items()}
    if isinstance(x, list):
        return {k: v for i, val in enumerate(x) for k, v in _flat(val, f"{path}[{i}]").items()}
    if isinstance(x, float):
        return {path: pytest.approx(x, rel=1e-12, abs=0, nan_ok=True)}
    return {path: x}


@pytest.mark.science  # a local Dask cluster, 19 s of make test's 10 min
def test_cases_on_a_dask_cluster_equal_the_serial_run(short_merger, tmp_path):
    """The same command on a LocalCluster of two worker processes (one task per variant and
    base simulation): the rows are those of the serial run (same code, same seeds, same
    inputs), numbers to 1e-12 relative: the workers run BLAS single-threaded, which changes
    the last bits of some sums (measured: chi2/dof differs by 1e-15); figures not drawn here."""
    from ttlcore.cli.main import main

    serial = json.loads((short_merger[0] / "summary.json").read_text())
    assert main(["scenarios", "--out", str(tmp_path), *SHORT_MERGER, "--workers", "2", "--no-figures"]) == 0
    dist = json.loads((tmp_path / "summary.json").read_text())
    rows_serial = [{k: v for k, v in r.items() if k != "figures"} for r in serial["variants"]["paper"]["cases"]]
    assert _flat(dist["variants"]["paper"]["cases"]) == _flat(rows_serial)
    assert not list(tmp_path.glob("paper/*.png"))


def test_bad_options_are_named(tmp_path):
    with pytest.raises(TTLError, match="--cases: unknown nope"):
        run_scenarios(tmp_path, cases=["nope"], variants=["paper"])
    with pytest.raises(TTLError, match="--variants: unknown x"):
        run_scenarios(tmp_path, cases=["vb"], variants=["x"])
    f = tmp_path / "file"
    f.write_text("")
    with pytest.raises(TTLError, match="--out"):
        run_scenarios(f, cases=["vb"], variants=["paper"])
    from ttlcore.cli.main import main

    assert main(["scenarios", "--out", str(tmp_path / "o"), "--duration", "soon"]) == 2


@pytest.mark.science
@pytest.mark.timeout(50 * 60)  # the acceptance bound is 45 min; the suite's default 15 min is too short
def test_all_scenarios_reproduce_the_paper(tmp_path):
    start = time.monotonic()
    s = run_scenarios(tmp_path, progress=print)
    elapsed = time.monotonic() - start
    print(f"ttl scenarios (all cases, 3 variants, 1 day each): {elapsed:.0f} s")
    assert elapsed < 45 * 60
    rows = s["variants"]["paper"]["cases"]
    assert [r["case"] for r in rows] == [c.name for c in PAPER_CASES]
    for r in rows:
        limit = 0.1 if r["merger"] else 0.06
        assert r["max_abs_error_mm"] < limit, r["case"]
        if r["gw"]:
            # a shift above 2 sigma is only accepted for a GW loud in the band (SNR > 100)
            assert r["shift_over_sigma_max"] < 2 or r["snr_band_x2"] > 100, r["case"]
            if r["gw_intact"]["n_bins"]:
                assert r["gw_intact"]["pass"], r["case"]
        assert r["fraction_above_requirement"] < 0.05, r["case"]

"""Coefficient sets and time-varying truth models."""

import json

import numpy as np
import pytest

from ttlcore.conventions import COEFFICIENT_NAMES, DAY
from ttlcore.errors import ConfigError
from ttlcore.sim.coefficients import CoefficientModel, lisainstrument_set, make_coefficients, paper_set


def test_names_order_and_count():
    assert len(COEFFICIENT_NAMES) == 24
    assert COEFFICIENT_NAMES[0] == "12.phi.rx" and COEFFICIENT_NAMES[-1] == "21.eta.tx"


def test_paper_set_is_2p3_mm_per_rad():
    assert np.all(paper_set() == 2.3e-3)


def test_lisainstrument_set_matches_lisainstrument_defaults():
    # outside reference: lisainstrument's own default table; 'local' = rx, 'distant' = tx
    from lisainstrument.instru import instru_defaults as d

    ours = dict(zip(COEFFICIENT_NAMES, lisainstrument_set()))
    for mosa_id, value in d.TTL_COEFFS_LOCAL_PHIS.items():
        assert ours[f"{mosa_id.value}.phi.rx"] == value
    for mosa_id, value in d.TTL_COEFFS_DISTANT_ETAS.items():
        assert ours[f"{mosa_id.value}.eta.tx"] == value
    mags = np.abs(lisainstrument_set())
    assert 0.05e-3 < mags.min() and mags.max() < 2.2e-3  # docs/physics.md: 0.06 .. 2.1 mm/rad


def test_drift_step_values():
    m = make_coefficients("paper").with_drift({"12.phi.rx": 0.05e-3}).with_step(DAY, {"13.eta.tx": 0.3e-3})
    t = np.array([0.0, DAY - 1, DAY, 2 * DAY])
    v = m.values(t)
    i, j = COEFFICIENT_NAMES.index("12.phi.rx"), COEFFICIENT_NAMES.index("13.eta.tx")
    assert np.allclose(v[i], 2.3e-3 + 0.05e-3 * t / DAY)
    assert np.allclose(v[j], [2.3e-3, 2.3e-3, 2.6e-3, 2.6e-3])
    back = CoefficientModel.from_description(json.loads(json.dumps(m.describe())))
    assert np.allclose(back.values(t), v, rtol=0, atol=1e-18)


def test_json_file_and_errors(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({n: 1e-3 for n in COEFFICIENT_NAMES}))
    assert np.all(make_coefficients(str(f)).base == 1e-3)
    f.write_text(json.dumps({"12.phi.rx": 1e-3}))
    with pytest.raises(ConfigError, match="missing"):
        make_coefficients(str(f))
    with pytest.raises(ConfigError, match="neither"):
        make_coefficients("nonsense")

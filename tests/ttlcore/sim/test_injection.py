"""Injections: extra signals added to eta, stored alone in the truth file, rebuilt from the config."""

import numpy as np
import pytest

from ttlcore.errors import ConfigError
from ttlcore.io.reader import read_telemetry
from ttlcore.io.truth import read_truth
from ttlcore.sim.injection import injection_from_description
from ttlcore.sim.simulator import NoiseSwitches, SimulationConfig, simulate, simulate_to_file

PLUGIN = """
import numpy as np

class Tone:
    def __init__(self, name, amplitude, frequency):
        self.name, self.amplitude, self.frequency = name, amplitude, frequency

    def describe(self):
        return {"kind": "tone", "module": __file__, "name": self.name,
                "amplitude": self.amplitude, "frequency": self.frequency}

    def link_signal(self, ctx):
        phase = 2 * np.pi * self.frequency * ctx.t
        return self.amplitude * np.sin(phase + np.arange(6)[:, None])

def injection_from_description(d):
    return Tone(d["name"], d["amplitude"], d["frequency"])
"""


@pytest.fixture
def tone(tmp_path):
    path = tmp_path / "tone.py"
    path.write_text(PLUGIN)
    return injection_from_description(
        {"kind": "tone", "module": str(path), "name": "tone", "amplitude": 1e-20, "frequency": 0.01}
    )


def test_injection_is_added_to_eta_and_stored_alone(tone, tmp_path):
    quiet = dict(duration=600.0, orbit="equal", seed=3, noises=NoiseSwitches.parse("none,ttl"))
    base, _ = simulate(SimulationConfig(**quiet))
    cfg = SimulationConfig(**quiet, injections=(tone,))
    tm, truth = simulate(cfg, chunk_size=1000)
    t = tm.t0 + np.arange(tm.size) / tm.fs
    expected = 1e-20 * np.sin(2 * np.pi * 0.01 * t + np.arange(6)[:, None])  # independent formula
    np.testing.assert_allclose(truth["injections/tone"], expected, rtol=0, atol=1e-32)
    np.testing.assert_allclose(tm.eta - base.eta, expected, rtol=0, atol=1e-30)  # nothing else changed

    path, tpath = simulate_to_file(cfg, tmp_path / "day.h5", chunk_size=700)
    on_disk = read_truth(tpath)
    np.testing.assert_array_equal(on_disk.injections["tone"], truth["injections/tone"])
    # the stored configuration rebuilds the injection (plugin file by path)
    again = SimulationConfig.from_dict(read_telemetry(path).config)
    assert again.injections[0].describe() == tone.describe()


def test_bad_injections_are_named(tone):
    with pytest.raises(ConfigError, match="unique"):
        SimulationConfig(duration=10.0, injections=(tone, tone))
    with pytest.raises(ConfigError, match="unknown injection kind 'nope'"):
        injection_from_description({"kind": "nope"})
    with pytest.raises(ConfigError, match="no such Python file"):
        injection_from_description({"kind": "x", "module": "/nonexistent/plugin.py"})

"""The notebook face of ttlcore: ``ttlcore.__all__`` and the sub-packages, each name with one meaning."""

import importlib
import subprocess
import sys
import types
from pathlib import Path

import numpy as np

import ttlcore

SUBPACKAGES = ("io", "sim", "effects", "tdi", "estimate", "diagnose", "gw", "plots", "app", "cli")


def test_every_name_of_the_face_resolves():
    for name in ttlcore.__all__:
        assert getattr(ttlcore, name) is not None, name
    assert set(ttlcore.__all__) <= set(dir(ttlcore))


def test_a_subpackage_name_is_the_subpackage():
    # ``ttlcore.diagnose`` once was the function and the sub-package at once; it is the sub-package,
    # whose face holds the function, and a module under it imports with ``import ... as``
    for name in SUBPACKAGES:
        module = getattr(ttlcore, name)
        assert isinstance(module, types.ModuleType) and module.__name__ == f"ttlcore.{name}"
        assert module is importlib.import_module(f"ttlcore.{name}")
        for public in getattr(module, "__all__", ()):
            assert hasattr(module, public), f"ttlcore.{name}.{public}"
    import ttlcore.diagnose.transients as transients  # noqa: PLC0415 - the form under test

    assert transients is sys.modules["ttlcore.diagnose.transients"]
    assert callable(ttlcore.diagnose.diagnose) and ttlcore.diagnose.diagnose.__module__ == "ttlcore.diagnose.diagnoser"


def _imported(statement: str) -> list[str]:
    code = f"import sys; {statement}; print(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return eval(out)  # noqa: S307 - our own printed list of strings


HEAVY = ("scipy", "h5py", "ttlcore.diagnose", "ttlcore.tdi.data", "ttlcore.io.reader")


def test_the_face_is_imported_on_first_use():
    # ``import ttlcore`` must not pull in the science stack (``ttl --help`` starts in well under a second)
    assert _imported("import ttlcore") == []
    # nor a light module under the io and tdi faces (the stages' atomic writes, the delays)
    assert _imported("import ttlcore.io.atomic, ttlcore.tdi.interpolation") == ["h5py"]
    # a name of a face imports its own module only (the reader: h5py, not the TDI engine)
    assert _imported("from ttlcore.io import read_telemetry") == ["h5py", "ttlcore.io.reader"]


def test_the_readme_notebook_example_runs(tmp_path, monkeypatch):
    # the README's "In a notebook" block, as printed, on a simulated 6-h file named as it says
    readme = (Path(__file__).parents[2] / "README.md").read_text()
    block = readme.split("In a notebook", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    tm, _ = ttlcore.simulate(ttlcore.SimulationConfig(duration=6 * 3600, orbit="keplerian", seed=3))
    ttlcore.write_telemetry(tmp_path / "day.h5", tm)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(block, "README.md", "exec"), namespace)  # noqa: S102 - the documented example
    fit = namespace["fit"]
    assert fit.coefficients.shape == (24,) and np.all(np.isfinite(fit.sigma)) and 0.5 < fit.chi2_dof < 2
    assert namespace["residual"].shape == namespace["td"].data.shape

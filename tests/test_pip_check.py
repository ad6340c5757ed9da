"""``.ci/pip_check.py``: the set-up's ``pip check`` lets through exactly its known line.

The script is run on pip's real output of this venv (the known lisaglitch line, or nothing),
and on made-up outputs of ``pip check`` (a subprocess stand-in: the script's only input is
that text) to see that any other broken requirement fails it.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / ".ci" / "pip_check.py"


def _module():
    spec = importlib.util.spec_from_file_location("pip_check", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_venv_as_set_up_passes():
    r = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert all("(known:" in line for line in r.stdout.splitlines()), r.stdout


@pytest.mark.parametrize(
    "output, rc",
    [
        ("No broken requirements found.\n", 0),
        ("lisaglitch 2.0.0 requires torch, which is not installed.\n", 0),
        (
            "lisaglitch 2.0.0 requires torch, which is not installed.\nmcap 1.2 requires lz4, which is not installed.\n",
            1,
        ),
        ("numpy 2.0 has requirement foo<1, but you have foo 2.\n", 1),
        ("lisa-gap 0.4 requires torchvision, which is not installed.\n", 1),
    ],
)
def test_only_the_known_line_is_let_through(monkeypatch, capsys, output, rc):
    module = _module()
    fake = subprocess.CompletedProcess([], returncode=0 if output.startswith("No") else 1, stdout=output, stderr="")
    monkeypatch.setattr(module.subprocess, "run", lambda *a, **k: fake)
    assert module.main() == rc
    if rc:
        assert "broken requirements beyond the known ones" in capsys.readouterr().err

"""Every command the README prints, pasted as printed.

The README's ``sh`` blocks are read here, not copied: a command changed there is tested as
changed.  A line is a command when it starts with ``ttl``, ``make`` or ``mkdir`` (a ``\\`` joins
the next line); text after ``#`` is a comment, as in a shell.

- Every ``ttl`` command parses with the real parser (in a directory holding stand-ins of the
  files it names, the globs expanded as a shell would), and the effect specs it types
  (``--effects``, ``--inject``) build their effects.  Templates - a command with a
  placeholder the reader fills in (``PORT``, ``DIR``, ``HOST``, ``...``) - are parsed with
  the placeholder filled, and listed in :data:`TEMPLATES`.
- ``-m science``: the walk-through runs for real, every command in the README's order in one
  directory through ``bash -c`` with the venv's ``ttl`` first on the path (globs, quotes and
  all), each must end with status 0.  Not run: templates, the interactive viewer
  (``ttl view``; its conventions are tested in ``tests/test_cli_conventions.py``), the
  paper's whole scenario set (hours; ``tests/ttlcore/gw`` runs its cases) and ``make``.
"""

from __future__ import annotations

import glob
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

#: placeholders of template commands and the values the parse test fills in
PLACEHOLDERS = {"PORT": "7447", "DIR": "creds", "HOST": "127.0.0.1"}


def readme_commands() -> list[str]:
    """The command lines of the README's ``sh`` blocks, in order, continuations joined and
    comments kept (the shell drops them)."""
    out = []
    for block in re.findall(r"```sh\n(.*?)```", README.read_text(), re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip()
            if line.startswith(("ttl ", "make ", "mkdir ")):
                out.append(line)
    return out


def is_template(line: str) -> bool:
    words = shlex.split(line, comments=True)
    return any(w == "..." or any(re.search(rf"\b{p}\b", w) for p in PLACEHOLDERS) for w in words)


def filled(line: str) -> list[str]:
    """A template's words with its placeholders filled, ``...`` dropped and the optional
    ``[--option VALUE]`` groups taken."""
    words = []
    for w in shlex.split(line, comments=True):
        if w == "...":
            continue
        for p, v in PLACEHOLDERS.items():
            w = re.sub(rf"\b{p}\b", v, w)
        words.append(w.strip("[]") if w.startswith("[") or w.endswith("]") else w)
    return words


TEMPLATES = [line for line in readme_commands() if is_template(line)]


def test_the_readme_has_the_commands_this_test_reads():
    commands = readme_commands()
    assert len(commands) > 20 and {c.split()[1] for c in commands if c.startswith("ttl ")} >= {
        "simulate",
        "info",
        "analyze",
        "diagnose",
        "run",
        "inspect",
        "view",
        "control",
        "refit",
        "reprocess",
        "scenarios",
    }


def test_every_readme_command_parses_as_printed(tmp_path, monkeypatch):
    from streamer.tools.parsers import register
    from ttlcore.cli.main import build_parser
    from ttlcore.effects import make_effects
    from ttlcore.effects.registry import injection_from_spec

    monkeypatch.chdir(tmp_path)
    lines = [line for line in readme_commands() if line.startswith("ttl ")]
    # stand-ins of the files the commands read (the parser checks that inputs exist)
    for line in lines:
        for w in filled(line):
            if w.endswith(".h5") and "*" not in w:
                Path(w).parent.mkdir(parents=True, exist_ok=True)
                Path(w).touch()
    for d in ("recordings/day3", "data"):
        Path(d).mkdir(parents=True, exist_ok=True)
    Path("data/day1.h5").touch()
    Path("data/day2.h5").touch()
    for line in lines:
        words = []
        for w in filled(line)[1:]:
            words += (sorted(glob.glob(w)) or [w]) if "*" in w else [w]
        try:
            args = build_parser(register).parse_args(words)
        except SystemExit as exc:
            pytest.fail(f"README: {line!r} does not parse (exit {exc.code})")
        if getattr(args, "effects", None):
            make_effects(args.effects)
        for spec in getattr(args, "inject", None) or []:
            injection_from_spec(spec)


@pytest.mark.science
@pytest.mark.timeout(5400)
def test_the_readme_walk_through_runs_as_printed(tmp_path):
    """About 30 minutes on 2 cores: four 1-day simulations, two diagnoses, a 3-day and a
    1-day ``ttl run`` (the second with the live loop's diagnoses), the refit and the
    reprocessing of five days (the 3-day ``ttl run`` alone took 294 s)."""
    skipped = ("ttl view ", "make ")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    env["OPENBLAS_NUM_THREADS"] = "1"
    ran = []
    for line in readme_commands():
        # the paper's whole scenario set takes hours (see the module docstring)
        if line.startswith(skipped) or line in TEMPLATES or line.startswith("ttl scenarios"):
            continue
        start = time.perf_counter()
        r = subprocess.run(["bash", "-c", line], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=3600)
        ran.append(f"{time.perf_counter() - start:7.1f} s  {line.split('#')[0].strip()}")
        print(ran[-1])
        assert r.returncode == 0, f"README: {line}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
        assert "Traceback" not in r.stderr, f"README: {line}\n{r.stderr[-3000:]}"
    assert len(ran) >= 12, ran

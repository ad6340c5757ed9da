"""What the launcher of ``ttl run`` keeps on disk: its journal (``launcher.jsonl``), the
board it believes (``board.json``), read back by ``ttl run --resume``, and the lock that
keeps a second launcher off its run directory (``launcher.lock``, :func:`lock_run`).

See :mod:`streamer.launch.launcher`, "Journal and resuming".
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path

from ..runtime.progress import Progress
from ..runtime.rangeset import RangeSet
from .input_pins import compare
from .launch_plan import LaunchError

# the logger of these lines before the launcher was split into parts: log lines unchanged
log = logging.getLogger("streamer.launch.launcher")


def append_journal(run_dir: Path, kind: str, message: str, **details) -> None:
    """Append a record to ``<run_dir>/launcher.jsonl`` (``ttl inspect`` reads it)."""
    rec = {"time": time.time(), "launcher_pid": os.getpid(), "kind": kind, "message": message, **details}
    try:
        with open(run_dir / "launcher.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")
    except OSError as exc:
        log.warning("cannot write %s: %s", run_dir / "launcher.jsonl", exc)


def save_board(run_dir: Path, run: str, progress: Mapping[str, Progress]) -> None:
    """Write the board (what the launcher believes of every stage) to ``board.json``,
    atomically: a launcher that dies leaves the last one whole."""
    path = run_dir / "board.json"
    tmp = path.with_name(".board.json.tmp")
    try:
        tmp.write_text(json.dumps({s: p.message(run) for s, p in progress.items()}))
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("cannot write %s: %s", path, exc)


def read_board(path: Path, expected: list[str], total: int | None) -> dict[str, Progress] | None:
    """The progress of each expected stage in ``board.json``; None when there is no file.

    Raises
    ------
    OSError, ValueError
        The file is there but unreadable.
    """
    try:
        board = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    progress = {}
    for stage, msg in board.items():
        if stage in expected and isinstance(msg, dict):
            progress[stage] = Progress(stage)
            progress[stage].update(msg, total)
    return progress


def _below(indices: RangeSet, first: int) -> RangeSet:
    out = RangeSet()
    for a, b in indices.ranges():
        if a < first:
            out.add_range(a, min(b, first - 1))
    return out


def cut_board(progress: Mapping[str, Progress], expected: list[str], total: int | None) -> tuple[int, dict]:
    """The first segment some expected stage has not handled (``m``), and the board cut
    before it: every segment before ``m`` taken as handled by every stage, nothing from ``m``
    on (the publishers' caches of the earlier processes are gone with them)."""

    def first_missing(stage: str) -> int:
        if stage not in progress or not total:
            return 0
        missing = progress[stage].handled.missing(0, total - 1)
        return missing[0][0] if missing else total

    first = min(first_missing(s) for s in expected)
    if first == 0:
        return 0, {}
    cut = {
        stage: Progress(
            stage,
            _below(p.done, first),
            _below(p.failed, first),
            total,
            _below(p.gaps, first),
            extra={n: _below(v, first) for n, v in p.extra.items()},
        )
        for stage, p in progress.items()
    }
    return first, cut


def check_resumed_inputs(run_dir: Path, plan: Mapping | None) -> None:
    """``--resume``: the input files must be those the run was planned with, unchanged (the
    pins of ``<run_dir>/plan.json`` against those of the new ``plan``; docs/operations.md,
    "Pinned inputs").  Nothing to compare without a plan file or pins.

    Raises
    ------
    LaunchError
        Naming the file and what changed.
    """
    path = run_dir / "plan.json"
    try:
        before = json.loads(path.read_text())
    except FileNotFoundError:
        return
    except (OSError, ValueError) as exc:
        raise LaunchError(f"--resume: {path}: unreadable ({exc})") from None
    planned = before.get("inputs") or [] if isinstance(before, dict) else []
    now = {p["path"]: p for p in (plan or {}).get("inputs") or ()}
    for pin in planned:
        current = now.get(pin.get("path"))
        what = "not an input of the resumed run" if current is None else compare(pin, current)
        if what:
            raise LaunchError(
                f"--resume: {pin.get('path')}: {what}; the segments already handled came from the file "
                f"as it was (give a new --run-id to run on this one)"
            )


def lock_run(run_dir: Path):
    """Hold ``run_dir/launcher.lock`` for as long as the launcher lives (an exclusive
    ``flock``, released by the kernel when the process ends, however it ends: a killed
    launcher leaves no stale lock, and ``--resume`` takes it again).  The file names the
    holder's pid.  Returns the open file (keep it: closing it releases the lock).

    Raises
    ------
    LaunchError
        Another launcher holds the run (two ``ttl run`` with one ``--run-id`` and
        ``--recordings`` would share the board, the journal and every recording).
    """
    path = run_dir / "launcher.lock"
    f = open(path, "a+")  # noqa: SIM115 - held open for the launcher's life
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.seek(0)
        holder = f.read().strip() or "another process"
        f.close()
        raise LaunchError(
            f"run {run_dir.name} is in use: its launcher ({holder}) holds {path}; "
            "give another --run-id, or wait for that run to end"
        ) from None
    f.seek(0)
    f.truncate()
    f.write(f"ttl run pid {os.getpid()}\n")
    f.flush()
    return f

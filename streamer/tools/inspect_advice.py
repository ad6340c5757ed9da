"""What ``ttl inspect`` advises for the fitter's live diagnoses: a command that works where
it is read.

A diagnosis recorded during a run carries the ``ttl control`` command that applies its
recommendation to the live fitter (:func:`stages.fitter.live_diagnosis.control_command`), with
the router's address of that moment.  Once the run has ended that router is gone: pasted,
the command could only fail.  So :func:`run_state` finds whether the run is live now (the
launcher's journal, ``launcher.jsonl``: a ``start`` without its ``end`` whose launcher
process is alive on this host, and the router it started answering at its address; for a
run without a journal, a router answering at the recorded address), and :func:`advise`
gives each diagnosis the command to print:

* live: ``ttl control`` with the router's live address and the run's credentials (which
  must exist here);
* ended (or not reachable from here): ``ttl refit RUN_DIR --effects ... --segments A:B``,
  the same model refitted offline on the window the fitter diagnosed.
"""

from __future__ import annotations

import json
import os
import shlex
import socket
import time
from pathlib import Path
from typing import NotRequired, TypedDict

from ..bus.reach import listening


def _journal_start(run_dir: Path) -> tuple[dict | None, dict | None]:
    """The last ``start`` record of ``launcher.jsonl`` and the ``end`` that follows it (None)."""
    start = end = None
    try:
        lines = (run_dir / "launcher.jsonl").read_text(errors="replace").splitlines()
    except OSError:
        return None, None
    for line in lines:
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if isinstance(rec, dict) and rec.get("kind") == "start":
            start, end = rec, None
        elif isinstance(rec, dict) and rec.get("kind") == "end" and start is not None:
            end = rec
    return start, end


def process_alive_since(pid, since: float | None) -> bool:
    """Whether process ``pid`` exists and (on Linux) was started by ``since`` [Unix time]:
    not another process that was given the same number later."""
    try:
        os.kill(int(pid), 0)
    except (OSError, ValueError, TypeError):
        return False
    if since is None:
        return True
    try:
        fields = Path(f"/proc/{int(pid)}/stat").read_text().rsplit(")", 1)[1].split()
        boot = next(
            float(ln.split()[1]) for ln in Path("/proc/stat").read_text().splitlines() if ln.startswith("btime")
        )
        started = boot + int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return True  # not Linux: the pid alone
    return started <= float(since) + 2.0


class RunState(TypedDict):
    """Whether a run is live now and how it is reached (:func:`run_state`)."""

    live: bool
    why: str
    router: str | None
    credentials: str | None
    control: bool
    checked: NotRequired[float]  # when (time.time()), set by :func:`advise`


def _recorded(command: str | None) -> dict[str, str]:
    """``--run``, ``--connect``, ``--credentials`` and the stage of a recorded ``ttl control`` command."""
    try:
        words = shlex.split(command or "")
    except ValueError:
        return {}
    out: dict[str, str] = {}
    rest, i = [], 2
    while i < len(words):
        if words[i] in ("--run", "--connect", "--credentials") and i + 1 < len(words):
            out.setdefault(words[i][2:], words[i + 1])
            i += 2
        else:
            rest.append(words[i])
            i += 1
    if rest:
        out["stage"] = rest[0]
    return out


def run_state(run_dir, recorded_command: str | None = None) -> RunState:
    """Whether the run of ``run_dir`` is live now, and how it is reached.

    Returns ``{"live", "why", "router", "credentials", "control"}``: ``live`` the run goes on
    and its router answers at ``router``; ``control`` a ``ttl control`` command can work
    from here (live, and the credentials, if the run has any, are in ``credentials``).
    """
    run_dir = Path(run_dir)
    seen = _recorded(recorded_command)
    start, end = _journal_start(run_dir)
    router, credentials = seen.get("connect"), seen.get("credentials")
    try:
        zenoh = json.loads((run_dir / "fitter.config.json").read_text()).get("zenoh") or {}
        router, credentials = (zenoh.get("connect") or [router])[0], zenoh.get("credentials") or credentials
    except (OSError, ValueError, AttributeError, IndexError):
        pass
    if start is not None:
        router = start.get("router") or router
        credentials = start.get("credentials", credentials)
    state: RunState = {"live": False, "why": "", "router": router, "credentials": credentials, "control": False}
    if end is not None:
        state["why"] = f"ttl run ended (exit status {end.get('status')})"
        return state
    if start is not None and start.get("host") in (None, socket.gethostname()):
        pid = start.get("launcher_pid")
        if not process_alive_since(pid, start.get("time")):
            state["why"] = f"ttl run (pid {pid}) is gone: killed, or ended without its end record"
            return state
        state["why"] = f"ttl run (pid {pid}) is running"
    elif start is None:
        state["why"] = "no launcher journal (stages started by hand?)"
    else:
        state["why"] = f"ttl run ran on host {start.get('host')}"
    if not router or not listening(router, timeout=1.0):
        state["why"] += f"; no router answers at {router or '(no address recorded)'}"
        return state
    state["live"] = True
    state["why"] += f"; its router answers at {router}"
    if credentials and not (Path(credentials) / "control.pem").exists():
        state["why"] += f"; the run's credentials are not here ({credentials}/control.pem): ttl control needs them"
        return state
    state["control"] = True
    return state


def control_command(run: str, stage: str, state: RunState, effects: list[str]) -> str:
    """``ttl control`` that puts ``effects`` in the model of the live fitter ``stage``."""
    parts = ["ttl", "control", "--run", run, "--connect", str(state["router"])]
    if state.get("credentials"):
        parts += ["--credentials", str(state["credentials"])]
    return shlex.join([*parts, stage, "model", json.dumps({"effects": list(effects)})])


def refit_command(run_dir, effects: list[str], baseline: list[str] | None, segments) -> str:
    """``ttl refit`` of the recorded segments ``segments`` (first, last) with ``effects``
    against ``baseline`` (the model diagnosed; ``ttl refit``'s own default when linear-ttl)."""
    parts = ["ttl", "refit", str(run_dir), "--effects", ",".join(effects)]
    if baseline and list(baseline) != ["linear-ttl"]:
        parts += ["--baseline", ",".join(baseline)]
    if isinstance(segments, (list, tuple)) and len(segments) == 2 and all(isinstance(s, int) for s in segments):
        parts += ["--segments", f"{segments[0]}:{segments[1]}"]
    return shlex.join(parts)


def advise(model: dict, run_dir, run: str) -> RunState | dict:
    """Give each diagnosis of ``model`` (:func:`streamer.tools.inspect_model.model_report`) the
    command to print (``advice``, and each proposed removal's), live or offline; returns
    the run's state (:func:`run_state`, with the time it was checked)."""
    diagnoses = model.get("diagnoses") or []
    recorded = next((d.get("command") for d in diagnoses if d.get("command")), None)
    recorded = recorded or next((x.get("command") for d in diagnoses for x in d.get("removal") or []), None)
    if not diagnoses:
        return {}
    state = run_state(run_dir, recorded)
    state["checked"] = time.time()
    seen = _recorded(recorded)
    run, stage = seen.get("run") or run, seen.get("stage") or "fitter"
    for d in diagnoses:
        current = [str(e) for e in d.get("model") or []]

        def command(effects: list[str], d=d, current=current) -> str:
            if state["control"]:
                return control_command(run, stage, state, effects)
            return refit_command(run_dir, effects, current, d.get("segments"))

        if d.get("effects"):
            d["advice"] = command([str(e) for e in d["effects"]])
        for x in d.get("removal") or []:
            x["advice"] = command([e for e in current if e != x.get("spec")])
    return state

"""The configuration of one stage process (:class:`StageConfig`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .session import DEFAULT_CACHE, SessionSettings


@dataclass
class StageConfig:
    """Configuration of one stage process.

    Attributes
    ----------
    run : str
        Run identifier (a key chunk: letters, digits, ``.``, ``_``, ``-``).
    stage : str
        Stage name (default: the class's :attr:`Stage.name`).
    zenoh : SessionSettings
        How to open the session (default: peer on loopback, no multicast scouting).
    recordings : Path
        Recordings directory; the stage writes ``<recordings>/<run>/<stage>.mcap``.
    cache : int
        Segments kept per output topic for late joiners.
    history : int or None
        Segments asked from each input topic's publisher cache at start and on publisher
        appearance (the last ``history``); None: everything the cache holds.
    record_inputs : bool
        Record input segments whole (header and payload) in the MCAP file; when False
        (``ttl run``: the producer's file holds the payload) only their headers, on
        ``<topic>/input``, whose checksum refers to the payload in the producer's file.
    record_outputs : bool
        Record output segments (header and payload, see :attr:`Output.record_arrays`).
    poll_interval : float
        Longest wait for a message before checking for shutdown and calling :meth:`Stage.tick` [s].
    gap_grace : float
        A segment index skipped on arrival is reported as a gap only if it has not come
        within this many seconds [s] (segments of different keys may arrive out of order).
    hold : float
        Seconds an accepted input segment waits before the stage uses it [s]: a different
        copy of the same segment arriving meanwhile keeps both out (``docs/operations.md``).
        0: used at once (a conflicting copy then refuses only the later one).
    options : dict
        Stage-specific options.
    plan : dict, optional
        The run's plan (:class:`streamer.plan.Plan`); every input message is checked
        against it (:class:`streamer.plan.Validator`).  None: learned from the messages.
    launcher_pid : int, optional
        Process id of the launcher that started this stage: the stage stops (exit status
        3, recording closed) as soon as its parent is no longer that process.
    progress_from : {"stages", "launcher"}
        Whose progress messages a pipeline stage follows: the stages' own
        (``control/progress/<stage>``), or, in a run of ``ttl run``, the launcher's verified
        board (``control/board/<stage>``: only what the launcher believed).
    orphan_grace : float
        Once the launcher's liveliness token ``ttl/<run>/alive/launcher`` has been seen, the
        stage stops when it has been gone this long [s] (a launcher on another host).
    """

    run: str
    stage: str = ""
    zenoh: SessionSettings = field(default_factory=SessionSettings)
    recordings: Path = Path("recordings")
    cache: int = DEFAULT_CACHE
    history: int | None = None
    record_inputs: bool = True
    record_outputs: bool = True
    poll_interval: float = 0.2
    gap_grace: float = 10.0
    hold: float = 1.0
    options: dict = field(default_factory=dict)
    plan: dict | None = None
    launcher_pid: int | None = None
    orphan_grace: float = 60.0
    progress_from: str = "stages"

    def to_dict(self) -> dict:
        return {
            "run": self.run,
            "stage": self.stage,
            "zenoh": self.zenoh.to_dict(),
            "recordings": str(self.recordings),
            "cache": self.cache,
            "history": self.history,
            "record_inputs": self.record_inputs,
            "record_outputs": self.record_outputs,
            "poll_interval": self.poll_interval,
            "gap_grace": self.gap_grace,
            "hold": self.hold,
            "options": self.options,
            "plan": self.plan,
            "launcher_pid": self.launcher_pid,
            "orphan_grace": self.orphan_grace,
            "progress_from": self.progress_from,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StageConfig:
        d = dict(d)
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"stage configuration: unknown field {sorted(unknown)[0]!r}")
        if "run" not in d:
            raise ValueError("stage configuration: field 'run' missing")
        d["zenoh"] = SessionSettings.from_dict(d.get("zenoh"))
        if "recordings" in d:
            d["recordings"] = Path(d["recordings"])
        return cls(**d)

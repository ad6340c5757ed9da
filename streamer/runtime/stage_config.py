"""The configuration of one stage process (:class:`StageConfig`): a typed dataclass, checked
field by field on construction and read from and written to JSON by the one converter of
:mod:`streamer.runtime.settings` (errors name the field)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from ..bus.keys import KeyExprError, check_name
from ..bus.session import DEFAULT_CACHE, SessionSettings
from .plan import Plan
from .settings import above, at_least, check_fields, from_dict, to_dict

WHAT = "stage configuration"


def _run_id(run: str) -> str | None:
    try:
        check_name(run, "run id")
    except KeyExprError as exc:
        return str(exc)
    return None


def _plan(plan: dict) -> str | None:
    try:
        Plan.from_dict(plan)
    except (ValueError, TypeError, KeyError) as exc:
        return f"not a plan: {exc}"
    return None


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
        The run's plan (:class:`streamer.runtime.plan.Plan`); every input message is checked
        against it (:class:`streamer.runtime.plan.Validator`).  None: learned from the messages.
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

    run: str = field(metadata={"check": _run_id})
    stage: str = ""
    zenoh: SessionSettings = field(default_factory=SessionSettings)
    recordings: Path = Path("recordings")
    cache: int = field(default=DEFAULT_CACHE, metadata={"check": at_least(1)})
    history: int | None = field(default=None, metadata={"check": at_least(0)})
    record_inputs: bool = True
    record_outputs: bool = True
    poll_interval: float = field(default=0.2, metadata={"check": above(0)})
    gap_grace: float = field(default=10.0, metadata={"check": at_least(0)})
    hold: float = field(default=1.0, metadata={"check": at_least(0)})
    options: dict[str, Any] = field(default_factory=dict)
    plan: dict[str, Any] | None = field(default=None, metadata={"check": _plan})
    launcher_pid: int | None = None
    orphan_grace: float = field(default=60.0, metadata={"check": at_least(0)})
    progress_from: Literal["stages", "launcher"] = "stages"

    def __post_init__(self) -> None:
        check_fields(self, WHAT)

    def check(self) -> StageConfig:
        """Check the fields again (after they were set one by one); returns self."""
        check_fields(self, WHAT)
        return self

    def to_dict(self) -> dict:
        """The JSON form (the configuration file; the ``config`` of a recording's metadata)."""
        return to_dict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StageConfig:
        """Inverse of :meth:`to_dict`; a field that is unknown, missing or does not fit
        raises :class:`streamer.runtime.settings.SettingsError` (a ValueError) naming it."""
        d = dict(d)
        if "zenoh" in d and d["zenoh"] is None:  # as before: no settings, the defaults
            del d["zenoh"]
        return from_dict(cls, d, WHAT)

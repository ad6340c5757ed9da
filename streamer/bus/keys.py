"""Zenoh key expressions of a run.

Every key of a run starts with ``ttl/<run>/``:

``ttl/<run>/<topic>``
    the segment messages of a stage's output topic (:data:`DATA_TOPICS`), one stream per
    topic: the segment index travels in the message header.  One long-lived publisher per
    topic keeps a stage's memory flat; a publisher per segment key grew every subscriber
    and the router by 13-38 kB per segment (``bench/soak.py``, docs/operations.md).
``ttl/<run>/<topic>/<segment index>``
    the *name* of one segment, used in logs, error reports and recordings; and the key of
    the error reports (``ttl/<run>/errors/<index>``), which may use ``unknown`` in place of
    the index, for a message whose index could not be read.
``ttl/<run>/alive/<stage>``
    liveliness token of a running stage.
``ttl/<run>/control/<...>``
    commands (e.g. ``ttl/<run>/control/stop``, ``ttl/<run>/control/<stage>/stop``), and the
    progress of the stages: ``control/progress/<stage>`` as each stage reports it,
    ``control/board/<stage>`` as the launcher believed and republished it
    (:mod:`streamer.runtime.progress`).

Builders check every chunk they insert; parsers raise :class:`KeyExprError` naming the
key at fault.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass

from .topology import OUTPUT_TOPIC

#: First chunk of every key of this project.
PREFIX = "ttl"
#: Topic of the error reports (any stage publishes there).
ERRORS = "errors"
#: Data topics: the stages' outputs in pipeline order, each one stream ``ttl/<run>/<topic>``.
DATA_TOPICS = tuple(OUTPUT_TOPIC.values())
#: Segment topics: the data topics, then the errors.
TOPICS = (*DATA_TOPICS, ERRORS)
#: Chunk used for the liveliness tokens of stages.
ALIVE = "alive"
#: Chunk under which commands live.
CONTROL = "control"
#: Index chunk of an error about a message whose segment index is unknown.
UNKNOWN_INDEX = "unknown"
#: Control chunk of the progress a stage reports (``ttl/<run>/control/progress/<stage>``).
PROGRESS = "progress"
#: Control chunk of the progress the launcher has verified (``ttl/<run>/control/board/<stage>``).
BOARD = "board"

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


class KeyExprError(ValueError):
    """A key expression (or a chunk to put in one) is malformed.

    Parameters
    ----------
    key : str
        The key (or chunk) at fault.
    what : str
        What is wrong with it.
    """

    def __init__(self, key: str, what: str):
        self.key = key
        self.what = what
        super().__init__(f"key {key!r}: {what}")


@dataclass(frozen=True)
class SegmentKey:
    """The parts of ``ttl/<run>/<topic>/<index>``.

    Attributes
    ----------
    run : str
        Run identifier.
    topic : str
        One of :data:`TOPICS`.
    index : int or None
        Segment index; None only for ``ttl/<run>/errors/unknown``.
    """

    run: str
    topic: str
    index: int | None

    def __str__(self) -> str:
        return segment_key(self.run, self.topic, self.index)


def check_name(name: str, what: str = "name") -> str:
    """Check that ``name`` can be one chunk of a key (run id, stage name).

    Allowed: letters, digits, ``.``, ``_`` and ``-``, starting with a letter or digit.

    Raises
    ------
    KeyExprError
        If it cannot.
    """
    if not isinstance(name, str) or not _NAME.match(name):
        raise KeyExprError(str(name), f"not a valid {what} (letters, digits, '.', '_', '-')")
    return name


def _check_topic(topic: str) -> str:
    if topic not in TOPICS:
        raise KeyExprError(str(topic), f"unknown topic (expected one of {', '.join(TOPICS)})")
    return topic


def segment_key(run: str, topic: str, index: int | None) -> str:
    """``ttl/<run>/<topic>/<index>``.

    Parameters
    ----------
    run : str
        Run identifier.
    topic : str
        One of :data:`TOPICS`.
    index : int or None
        Segment index (>= 0); None is allowed on the errors topic only (``unknown``).
    """
    check_name(run, "run id")
    _check_topic(topic)
    if index is None:
        if topic != ERRORS:
            raise KeyExprError(f"{PREFIX}/{run}/{topic}/?", "a segment key needs an index")
        chunk = UNKNOWN_INDEX
    else:
        if isinstance(index, bool) or not isinstance(index, int) or index < 0:
            raise KeyExprError(f"{PREFIX}/{run}/{topic}/{index}", "segment index must be an integer >= 0")
        chunk = str(index)
    return f"{PREFIX}/{run}/{topic}/{chunk}"


def stream_key(run: str, topic: str) -> str:
    """``ttl/<run>/<topic>``: the key every segment of a data topic is published on."""
    check_name(run, "run id")
    if _check_topic(topic) == ERRORS:
        raise KeyExprError(f"{PREFIX}/{run}/{topic}", "error reports go on ttl/<run>/errors/<index>")
    return f"{PREFIX}/{run}/{topic}"


def topic_pattern(run: str, topic: str) -> str:
    """Every message of one topic.

    ``ttl/<run>/<topic>/**`` for a data topic (the stream key and, so that a stray message
    is seen and refused rather than missed, any key under it); ``ttl/<run>/errors/*``.
    """
    check_name(run, "run id")
    if _check_topic(topic) == ERRORS:
        return f"{PREFIX}/{run}/{ERRORS}/*"
    return f"{PREFIX}/{run}/{topic}/**"


def errors_key(run: str, index: int | None) -> str:
    """``ttl/<run>/errors/<index>`` (``unknown`` when the index is None)."""
    return segment_key(run, ERRORS, index)


def alive_key(run: str, stage: str) -> str:
    """``ttl/<run>/alive/<stage>``: the liveliness token of one stage."""
    return f"{PREFIX}/{check_name(run, 'run id')}/{ALIVE}/{check_name(stage, 'stage name')}"


def alive_pattern(run: str) -> str:
    """``ttl/<run>/alive/*``: the liveliness tokens of all stages of a run."""
    return f"{PREFIX}/{check_name(run, 'run id')}/{ALIVE}/*"


def control_key(run: str, *parts: str) -> str:
    """``ttl/<run>/control/<part>/<part>...`` (at least one part)."""
    if not parts:
        raise KeyExprError(f"{PREFIX}/{run}/{CONTROL}", "a control key needs at least one part")
    return "/".join([PREFIX, check_name(run, "run id"), CONTROL, *(check_name(p, "control part") for p in parts)])


def control_pattern(run: str) -> str:
    """``ttl/<run>/control/**``: every command of a run."""
    return f"{PREFIX}/{check_name(run, 'run id')}/{CONTROL}/**"


def stage_control_pattern(run: str, stage: str) -> str:
    """``ttl/<run>/control/<stage>/*``: the commands of one stage (its queryable: the
    verdict goes back to the sender, :mod:`streamer.runtime.controls`)."""
    return f"{PREFIX}/{check_name(run, 'run id')}/{CONTROL}/{check_name(stage, 'stage')}/*"


def progress_key(run: str, stage: str) -> str:
    """``ttl/<run>/control/progress/<stage>``: the progress ``stage`` reports."""
    return control_key(run, PROGRESS, stage)


def board_key(run: str, stage: str) -> str:
    """``ttl/<run>/control/board/<stage>``: ``stage``'s progress as the launcher verified it."""
    return control_key(run, BOARD, stage)


def progress_pattern(run: str, board: bool = False) -> str:
    """``ttl/<run>/control/progress/*`` (``.../board/*`` with ``board``): every stage's progress."""
    return f"{PREFIX}/{check_name(run, 'run id')}/{CONTROL}/{BOARD if board else PROGRESS}/*"


def parse_progress_key(key: str) -> tuple[str, str]:
    """``ttl/<run>/control/progress/<stage>`` (or ``.../board/<stage>``) -> ``(run, stage)``.

    Raises
    ------
    KeyExprError
        If ``key`` is not a progress key.
    """
    run, parts = parse_control_key(key)
    if len(parts) != 2 or parts[0] not in (PROGRESS, BOARD) or not _NAME.match(parts[1]):
        raise KeyExprError(str(key), f"expected 'ttl/<run>/control/{PROGRESS}/<stage>'")
    return run, parts[1]


def _chunks(key: str) -> list[str]:
    key = str(key)
    chunks = key.split("/")
    if len(chunks) < 3 or chunks[0] != PREFIX:
        raise KeyExprError(key, f"expected '{PREFIX}/<run>/...'")
    if not _NAME.match(chunks[1]):
        raise KeyExprError(key, f"run id {chunks[1]!r} is not valid")
    return chunks


def parse_stream_key(key: str) -> str:
    """The topic of a data-topic stream key ``ttl/<run>/<topic>``.

    Raises
    ------
    KeyExprError
        If ``key`` is not a stream key (message names the key).
    """
    chunks = _chunks(key)
    if len(chunks) != 3 or chunks[2] not in DATA_TOPICS:
        raise KeyExprError(str(key), f"expected 'ttl/<run>/<topic>' with a topic of {', '.join(DATA_TOPICS)}")
    return chunks[2]


def parse_segment_key(key: str) -> SegmentKey:
    """Split ``ttl/<run>/<topic>/<index>`` into its parts.

    Raises
    ------
    KeyExprError
        If ``key`` is not a segment key (message names the key).
    """
    chunks = _chunks(key)
    if len(chunks) != 4:
        raise KeyExprError(str(key), "expected 'ttl/<run>/<topic>/<segment index>'")
    _, run, topic, chunk = chunks
    if topic not in TOPICS:
        raise KeyExprError(str(key), f"unknown topic {topic!r} (expected one of {', '.join(TOPICS)})")
    if topic == ERRORS and chunk == UNKNOWN_INDEX:
        return SegmentKey(run, topic, None)
    if not chunk.isdigit() or (len(chunk) > 1 and chunk.startswith("0")):
        raise KeyExprError(str(key), f"segment index {chunk!r} is not a non-negative integer")
    return SegmentKey(run, topic, int(chunk))


def parse_alive_key(key: str) -> tuple[str, str]:
    """``ttl/<run>/alive/<stage>`` -> ``(run, stage)``.

    Raises
    ------
    KeyExprError
        If ``key`` is not a liveliness key.
    """
    chunks = _chunks(key)
    if len(chunks) != 4 or chunks[2] != ALIVE or not _NAME.match(chunks[3]):
        raise KeyExprError(str(key), "expected 'ttl/<run>/alive/<stage>'")
    return chunks[1], chunks[3]


def parse_control_key(key: str) -> tuple[str, tuple[str, ...]]:
    """``ttl/<run>/control/<parts...>`` -> ``(run, parts)``.

    Raises
    ------
    KeyExprError
        If ``key`` is not a control key.
    """
    chunks = _chunks(key)
    if len(chunks) < 4 or chunks[2] != CONTROL:
        raise KeyExprError(str(key), "expected 'ttl/<run>/control/<...>'")
    return chunks[1], tuple(chunks[3:])


# ---------------------------------------------------------------------------- segment indices


def to_ranges(indices: Iterable[int]) -> list[list[int]]:
    """``{0, 1, 2, 5}`` -> ``[[0, 2], [5, 5]]``."""
    out: list[list[int]] = []
    for i in sorted(set(indices)):
        if out and i == out[-1][1] + 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return out


#: Largest index :func:`from_ranges` expands without a limit.
MAX_EXPANDED = 10_000_000


def from_ranges(ranges, limit: int | None = None) -> set[int]:
    """Inverse of :func:`to_ranges` (ignores malformed entries), clipped to ``[0, limit)``
    (default :data:`MAX_EXPANDED`): a hostile ``[[0, 2**40]]`` cannot allocate 2^40 entries."""
    limit = MAX_EXPANDED if limit is None else min(int(limit), MAX_EXPANDED)
    out: set[int] = set()
    for r in ranges or ():
        try:
            a, b = max(int(r[0]), 0), min(int(r[1]), limit - 1)
        except (TypeError, ValueError, IndexError, OverflowError):
            continue
        out.update(range(a, b + 1))
    return out

"""The C allocator's settings of a stage process: memory that a long run gives back.

A stage process allocates and frees arrays of megabytes for every segment (the replayer's
noise blocks, FFT work arrays, the codec's payloads).  glibc's ``malloc`` serves a block
above its *mmap threshold* (128 kB at start) with its own ``mmap`` and returns it to the
system on ``free``; below it, from the heap, where freed memory stays in the process.  The
threshold is *dynamic*: each time a block served by ``mmap`` is freed, the threshold rises
to that block's size (up to 32 MB on 64-bit), so after the first large temporaries every
later one of that size comes from the heap, and the heap keeps what the largest burst
needed.  In a soak (``bench/soak.py``) this showed as steps of 13-85 MB in the replayer's
RSS each time a new 1.5-day noise block was computed (``docs/operations.md``, Measuring).

:func:`configure` fixes the threshold (``mallopt(M_MMAP_THRESHOLD)``, which also turns the
dynamic adjustment off), so that blocks above :data:`MMAP_THRESHOLD` always go back to the
system when freed, whatever the process did before; and it can cap the number of malloc
arenas (``mallopt(M_ARENA_MAX)``: every thread that allocates may otherwise get its own
arena, up to eight per core, each keeping its own free memory).  The environment variables
``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_ARENA_MAX`` set by a user win (the setting is
then left to glibc).  Elsewhere than glibc (macOS, musl) nothing is changed and a debug
line says so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

log = logging.getLogger(__name__)

#: ``mallopt`` parameter numbers of glibc (``malloc.h``).
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
#: Blocks of at least this many bytes are mmap'd and returned to the system when freed [bytes].
#: 256 kB: the messages of 10-min segments (the telemetry payload of one is 4 arrays of
#: 6 x 2400 float64, 0.46 MB) are then mmap'd too.  At 1 MB they came from the heap, and the
#: monitor, which reads four topics, grew 5.2 +- 0.7 kB per segment over the 3-day soak in
#: 10-min segments (2 +- 1 kB with 256 kB, "flat"; ``docs/operations.md``, Measuring).
MMAP_THRESHOLD = 1 << 18
#: Environment variables with which a user sets the same thing (they win).
ENV_MMAP_THRESHOLD = "MALLOC_MMAP_THRESHOLD_"
ENV_ARENA_MAX = "MALLOC_ARENA_MAX"


def _glibc():
    """The C library as a :class:`ctypes.CDLL` when it is glibc, else None."""
    try:
        if not (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc"):
            return None
    except (AttributeError, ValueError, OSError):  # no confstr, or not glibc
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        libc.mallopt.restype = ctypes.c_int
    except (OSError, AttributeError):
        return None
    return libc


def configure(
    mmap_threshold: int | None = MMAP_THRESHOLD, arena_max: int | None = None, environ=None
) -> dict[str, int]:
    """Set glibc's mmap threshold (and the arena cap) for this process.

    Call it early, before the threads that allocate start (an arena cap does not merge
    arenas already made).

    Parameters
    ----------
    mmap_threshold : int or None
        Blocks of at least this many bytes [bytes] are served by ``mmap`` and returned to
        the system on ``free``; None leaves glibc's dynamic threshold.
    arena_max : int or None
        Largest number of malloc arenas; None leaves glibc's default (8 per core).
    environ : mapping, optional
        Environment to look for the user's own ``MALLOC_*`` settings (default ``os.environ``).

    Returns
    -------
    dict
        What was set (``{"M_MMAP_THRESHOLD": bytes, "M_ARENA_MAX": n}``); empty when nothing
        was (not glibc, or the environment sets it).

    Raises
    ------
    ValueError
        If a value is not a positive integer.
    """
    env = os.environ if environ is None else environ
    wanted = {}
    for name, param, value, var in (
        ("M_MMAP_THRESHOLD", M_MMAP_THRESHOLD, mmap_threshold, ENV_MMAP_THRESHOLD),
        ("M_ARENA_MAX", M_ARENA_MAX, arena_max, ENV_ARENA_MAX),
    ):
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ValueError(f"allocator {name}: expected a positive integer, got {value!r}")
        if env.get(var):
            log.debug("allocator %s left to the environment (%s=%s)", name, var, env[var])
            continue
        wanted[name] = (param, value)
    if not wanted:
        return {}
    libc = _glibc()
    if libc is None:
        log.debug("allocator settings %s not applied: the C library is not glibc", sorted(wanted))
        return {}
    done = {}
    for name, (param, value) in wanted.items():
        if libc.mallopt(param, value) == 1:
            done[name] = value
        else:
            log.warning("allocator: mallopt(%s, %d) failed", name, value)
    log.debug("allocator: %s", done)
    return done

"""The options that describe a simulation, declared on an :mod:`argparse` parser.

Kept apart from :mod:`ttlcore.cli.simulation` (which turns them into a configuration and imports the
simulator) so that the ``ttl`` parser is built without importing the science: ``ttl --help``
and argument errors answer at once.
"""

from __future__ import annotations

import argparse

from ..conventions import parse_duration
from ..errors import TTLError


def duration(text: str) -> str:
    """An :mod:`argparse` ``type`` for a duration (``1d``, ``6h``, ``30min``, seconds): the text
    is kept (the configuration parses it again), but a bad one fails at parse time, before any work."""
    try:
        parse_duration(text)
    except (ValueError, TTLError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def add_simulation_options(p) -> None:
    """The options that define a simulation (``ttl simulate`` and ``ttl run --simulate``)."""
    p.add_argument("--duration", default="1d", type=duration, help="length, e.g. 1d, 6h, 30min or seconds (default 1d)")
    p.add_argument(
        "--orbit",
        default="unequal",
        help="equal | unequal (paper's static arms) | keplerian | FILE (a lisaorbits orbit file, optionally FILE:tps/ppr or FILE:tcb/ltt) (default unequal)",
    )
    p.add_argument(
        "--coeffs", default="paper", help="paper (2.3 mm/rad) | lisainstrument | random | JSON FILE (default paper)"
    )
    p.add_argument("--seed", type=int, default=0, help="master random seed (default 0)")
    p.add_argument("--t0", type=float, default=0.0, help="mission time of the first sample [s] (default 0)")
    p.add_argument("--fs", type=float, default=4.0, help="telemetry sampling rate [Hz] (default 4)")
    p.add_argument(
        "--noises",
        default="all",
        help="noises on: 'all', 'none', or a list like 'all,-laser,-dws' "
        "(laser, oms, backlink, telescope, test_mass, sc_jitter, mosa_jitter, dws, ttl)",
    )
    p.add_argument(
        "--drift", default="", metavar="NAME=MM_PER_DAY,...", help="linear coefficient drifts in mm/rad per day"
    )
    p.add_argument(
        "--step",
        action="append",
        default=[],
        metavar="T:NAME=MM,...",
        help="coefficient step at mission time T (s, or e.g. 1.5d) of MM mm/rad; repeatable",
    )
    p.add_argument("--order", type=int, default=31, help="Lagrange interpolation order of the delays (odd, default 31)")
    p.add_argument(
        "--gw",
        default="",
        metavar="SOURCES",
        help="gravitational waves to inject, comma-separated: "
        "hmcnc, ztfj1539, vb, galaxy, sgwb, mbhb1, mbhb2 (merging mid-run), all, or a lisagwresponse "
        "FILE[:tps/y|tcb/y] (docs/gw.md)",
    )
    p.add_argument(
        "--inject",
        action="append",
        default=[],
        metavar="EFFECT[:key=value,...]",
        help="model effect(s) to inject (truth in the truth file only), in the grammar of --effects, e.g. "
        "drift:12.phi.rx=2e-3 or glitch:t=3h,tm=12,beta=35s,all=1e-9; repeatable (docs/cli.md, Effect specs)",
    )
    p.add_argument(
        "--effect-module",
        action="append",
        default=[],
        metavar="PATH",
        help="Python file (or module) defining user effects for --inject; repeatable",
    )

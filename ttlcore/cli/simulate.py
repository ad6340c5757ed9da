"""``ttl simulate``: simulated telemetry and its truth file (options: :mod:`ttlcore.cli.main`)."""

from __future__ import annotations

import sys
from pathlib import Path

from ..conventions import DAY, parse_duration
from ..io.truth import NOISE_COMPONENTS
from ..sim.simulator import simulate_to_file
from .progress import progress_bar
from .simulation import simulation_config_from_args


def run(args) -> int:
    out = Path(args.telemetry or args.out)
    chunk = parse_duration(args.chunk, "--chunk")
    truth_noises = (
        tuple(NOISE_COMPONENTS)
        if args.truth_noises == "all"
        else tuple(s.strip() for s in args.truth_noises.split(",") if s.strip())
    )
    config = simulation_config_from_args(args, truth_noises)
    with progress_bar(f"simulate {out.name}", quiet=args.quiet) as progress:
        tpath, rpath = simulate_to_file(config, out, chunk_size=int(round(chunk * args.fs)), progress=progress)
    if not args.quiet:  # a status line: the files are the result
        print(f"wrote {tpath} ({config.size} samples, {config.duration / DAY:g} d at {args.fs:g} Hz) and {rpath}")
    if args.out is not None and not args.quiet:  # after the work: an error stays one line
        print(
            "ttl simulate: note: --out FILE is now --telemetry FILE (--out names a directory in every "
            "other command); it still works",
            file=sys.stderr,
        )
    return 0

"""``ttl scenarios``: the paper's scenarios with and without GW (options: :mod:`ttlcore.cli.main`;
the work: :mod:`ttlcore.app.scenarios`)."""

from __future__ import annotations

from pathlib import Path

from ..app.cluster import dask_client, dask_log_level
from ..app.scenarios import run_scenarios
from ..conventions import parse_duration
from ..errors import TTLError
from .progress import status_line


def run(args) -> int:
    """``ttl scenarios`` (options: :mod:`ttlcore.cli.main`): the cases on a Dask client with
    ``--scheduler`` or ``--workers``, serially otherwise; one line per case on stdout."""

    duration = parse_duration(args.duration, "--duration")
    cases = None if args.cases in ("all-cases", "") else [c.strip() for c in args.cases.split(",") if c.strip()]
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]

    if args.workers < 0:
        raise TTLError(f"--workers: must be >= 0, got {args.workers}")
    with status_line("ttl scenarios", args.quiet) as progress:  # in place on a terminal
        options = dict(
            cases=cases,
            variants=variants,
            duration=duration,
            seed=args.seed,
            figures=not args.no_figures,
            progress=progress,
        )
        if args.scheduler or args.workers:
            level = dask_log_level(args.verbose)  # no Dask INFO lines
            with dask_client(args.scheduler, workers=args.workers or 2, log_level=level) as client:
                s = run_scenarios(args.out, client=client, **options)
        else:
            s = run_scenarios(args.out, **options)
    for vname, v in s["variants"].items():
        print(f"[{vname}] {v['title']}")
        for r in v["cases"]:
            gi = r["gw_intact"]
            gtxt = (
                ""
                if not r["gw"]
                else (
                    f", GW intact {'ok' if gi['pass'] else 'FAIL'} ({gi['n_bins']} bins)"
                    if gi["pass"] is not None
                    else ", GW never 10x TTL residual"
                )
            )
            print(
                f"  {r['case']:<15} max |err| {r['max_abs_error_mm']:.4f} mm/rad "
                f"({'ok' if r['error_within_limit'] else 'ABOVE ' + str(r['limit_mm'])}), chi2/dof {r['chi2_dof']:.3f}, "
                f"shift {r['shift_over_sigma_max']:.2f} sigma{gtxt}"
            )
    print(f"wrote {Path(args.out) / 'summary.md'}, summary.json and figures ({s['timings_s']['total']:.0f} s)")
    return 0

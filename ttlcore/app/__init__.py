"""The commands' work: orchestrators that drive the science and its figures.

Above the science and the figures, below the command line (:mod:`ttlcore.cli` parses the
arguments and calls these): ``analysis`` (``ttl analyze``: TDI, fit, subtraction,
``fit.json`` and figures of one file), ``reprocessing`` (``ttl reprocess``: many days on
Dask, the analysis and the diagnosis of each, the trends across them), ``scenarios``
(``ttl scenarios``: the paper's cases with and without GW) and ``cluster`` (the Dask client
of both).

::

    from ttlcore.app import analyze
    out = analyze("day.h5", truth_path="day.truth.h5", out_dir="day-analysis")
"""

from .analysis import analyze
from .cluster import dask_client
from .reprocessing import DayJob, reprocess
from .scenarios import run_scenarios

__all__ = ["DayJob", "analyze", "dask_client", "reprocess", "run_scenarios"]

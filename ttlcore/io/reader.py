"""Reading telemetry whatever its format: format detection and dispatch.

Our own HDF5 telemetry (:mod:`ttlcore.io.telemetry`), our truth files (:mod:`ttlcore.io.truth`)
and lisainstrument 2.x measurement files (:mod:`ttlcore.io.lisainstrument`) are told apart by
their root attributes; :func:`read_telemetry` returns a :class:`~ttlcore.io.telemetry.Telemetry`
for either telemetry format.
"""

from __future__ import annotations

from ..errors import TelemetryError
from .hdf5 import open_h5, text_attr
from .lisainstrument import is_lisainstrument, read_lisainstrument
from .telemetry import FORMAT, Telemetry, read_ttl_telemetry
from .truth import FORMAT as TRUTH_FORMAT

__all__ = ["file_kind", "read_telemetry"]


def file_kind(path) -> str:
    """``"ttl"`` for our telemetry files, ``"truth"`` for our truth files,
    ``"lisainstrument"`` for lisainstrument output; raises :class:`TelemetryError` otherwise."""
    with open_h5(path) as f:
        fmt = text_attr(f, "format")
        if fmt == FORMAT:
            return "ttl"
        if fmt == TRUTH_FORMAT:
            return "truth"
        if is_lisainstrument(f):
            return "lisainstrument"
    raise TelemetryError(
        path, "neither a ttl telemetry file (root attribute format='ttl-telemetry') nor a lisainstrument output file"
    )


def read_telemetry(path, start: int = 0, stop: int | None = None, **ingest_options) -> Telemetry:
    """Read telemetry from our HDF5 format or a lisainstrument output file (auto-detected).

    Parameters
    ----------
    path : str or Path
    start, stop : int
        Sample range to read (our format reads only that range from disk).
    **ingest_options
        Passed to :func:`ttlcore.io.lisainstrument.read_lisainstrument` for
        lisainstrument files (interpolation orders).

    Raises
    ------
    TelemetryError
        Naming the file and the dataset or attribute at fault.
    """
    kind = file_kind(path)
    if kind == "ttl":
        return read_ttl_telemetry(path, start, stop)
    if kind == "truth":
        raise TelemetryError(path, "this is a truth file; give the telemetry file beside it")
    tm = read_lisainstrument(path, **ingest_options)
    if start or stop is not None:
        tm = tm.slice(start, tm.size if stop is None else stop)
    return tm

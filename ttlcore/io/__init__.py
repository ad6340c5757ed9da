"""File formats: telemetry and truth HDF5 files, lisainstrument measurement files, atomic writes.

``telemetry`` reads and writes our telemetry files, ``reader`` detects the format and reads any, ``truth`` the
ground-truth files kept apart from it, ``lisainstrument`` reads lisainstrument 2.x output,
``hdf5`` holds the shared HDF5 helpers and ``atomic`` writes to a temporary name and renames.

::

    from ttlcore.io import read_telemetry, read_truth
    tm = read_telemetry("day.h5")          # our format or lisainstrument's, detected
    truth = read_truth("day.truth.h5")

The names below are imported on first use, so that ``import ttlcore.io.atomic`` stays light.
"""

from .._lazy import lazy_face

#: name -> module it lives in
_EXPORTS = {
    "Telemetry": "telemetry",
    "read_header": "telemetry",
    "write_telemetry": "telemetry",
    "file_kind": "reader",
    "read_telemetry": "reader",
    "Truth": "truth",
    "read_truth": "truth",
    "read_lisainstrument": "lisainstrument",
    "lisainstrument_truth": "lisainstrument",
    "write_json": "atomic",
    "write_text": "atomic",
}
__getattr__, __dir__ = lazy_face(__name__, _EXPORTS, globals())

__all__ = list(_EXPORTS)

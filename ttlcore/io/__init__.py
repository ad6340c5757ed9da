"""File formats: telemetry and truth HDF5 files, lisainstrument measurement files, atomic writes.

``telemetry`` reads and writes our telemetry files, ``reader`` detects the format and reads any, ``truth`` the
ground-truth files kept apart from it, ``lisainstrument`` reads lisainstrument 2.x output,
``hdf5`` holds the shared HDF5 helpers and ``atomic`` writes to a temporary name and renames.
"""

__all__ = ["atomic", "hdf5", "lisainstrument", "reader", "telemetry", "truth"]

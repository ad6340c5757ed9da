"""Exceptions that name what is at fault (file, dataset, field)."""

from __future__ import annotations


class TTLError(Exception):
    """Base class of the project's user-facing errors: one line, no traceback needed."""


class TelemetryError(TTLError, ValueError):
    """A telemetry or truth file is unreadable, incomplete or inconsistent.

    Parameters
    ----------
    path : str
        The file at fault.
    what : str
        What is wrong.
    dataset : str, optional
        The HDF5 dataset or attribute at fault.
    """

    def __init__(self, path, what: str, dataset: str | None = None):
        self.path = str(path)
        self.dataset = dataset
        self.what = what
        where = f"{self.path}" + (f" [{dataset}]" if dataset else "")
        super().__init__(f"{where}: {what}")


class ConfigError(TTLError, ValueError):
    """A simulation or run configuration value is invalid; the message names the field."""

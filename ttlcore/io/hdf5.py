"""Atomic, chunk-by-chunk HDF5 writing and checked reading, shared by telemetry and truth files."""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np

from ..errors import TelemetryError


def temporary_path(path: Path) -> Path:
    """Temporary sibling of ``path`` for atomic writes (same directory, same filesystem)."""
    path = Path(path)
    return path.with_name(f".{path.name}.tmp{os.getpid()}")


class AtomicSeriesWriter:
    """Write fixed-size time series datasets of shape ``(rows, size)`` chunk by chunk.

    The file is written under a temporary name and renamed into place by :meth:`close`
    once every dataset holds ``size`` samples; on error the temporary file is removed,
    so no half-written output is ever left under the final name.

    Parameters
    ----------
    path : path-like
        Final file name.
    size : int
        Number of samples of every dataset.
    datasets : dict
        ``name -> (row labels, unit)``; ``name`` may contain ``/`` for groups.
    attrs : dict
        Root attributes (dicts and lists are stored as JSON strings).
    compress : set of str
        Datasets to store with gzip (e.g. slowly varying truth series).
    """

    def __init__(self, path, *, size: int, datasets: dict, attrs: dict, compress: frozenset = frozenset()):
        self.path = Path(path)
        self.tmp = temporary_path(self.path)
        self.size = int(size)
        self.datasets = dict(datasets)
        self.written = {name: 0 for name in self.datasets}
        self._file = h5py.File(self.tmp, "w")
        try:
            for key, value in attrs.items():
                if isinstance(value, (dict, list, tuple)):
                    value = json.dumps(value, sort_keys=True)
                self._file.attrs[key] = value
            for name, (labels, unit) in self.datasets.items():
                rows = len(labels)
                chunk = (rows, max(1, min(self.size, 1 << 15)))
                kwargs = dict(compression="gzip", compression_opts=1, shuffle=True) if name in compress else {}
                ds = self._file.create_dataset(name, shape=(rows, self.size), dtype="f8", chunks=chunk, **kwargs)
                ds.attrs["units"] = unit
                ds.attrs["rows"] = ",".join(labels)
        except Exception:
            self.abort()
            raise

    def append(self, name: str, values: np.ndarray) -> None:
        """Append ``values`` (shape ``(rows, n)``) to dataset ``name``."""
        values = np.asarray(values, dtype=float)
        start = self.written[name]
        n = values.shape[-1]
        if start + n > self.size:
            raise ValueError(f"{self.path} [{name}]: writing {n} samples past the declared size {self.size}")
        self._file[name][:, start : start + n] = values
        self.written[name] = start + n

    def close(self) -> Path:
        """Check that every dataset is complete, close, and rename into place."""
        if self._file is None:
            return self.path
        incomplete = {k: v for k, v in self.written.items() if v != self.size}
        self._file.close()
        self._file = None
        if incomplete:
            self.tmp.unlink(missing_ok=True)
            raise ValueError(f"{self.path}: incomplete datasets {incomplete} (declared size {self.size})")
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Discard the temporary file."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self.tmp.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False


def open_h5(path) -> h5py.File:
    """Open ``path`` read-only, turning every failure into a :class:`TelemetryError`."""
    path = Path(path)
    if not path.exists():
        raise TelemetryError(path, "no such file")
    if path.is_dir():
        raise TelemetryError(path, "is a directory, not an HDF5 file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise TelemetryError(path, f"not a readable HDF5 file ({exc}); truncated or corrupt?") from None


def text_attr(f: h5py.File, name: str, default=None):
    """A root attribute as ``str`` (decoding bytes), or ``default``."""
    value = f.attrs.get(name, default)
    if isinstance(value, bytes):
        value = value.decode()
    return value


def number_attr(f: h5py.File, path, name: str, kind=float, positive: bool = False):
    """A root attribute converted by ``kind``; errors name the file and the attribute."""
    if name not in f.attrs:
        raise TelemetryError(path, "missing root attribute", f"@{name}")
    raw = f.attrs[name]
    try:
        value = kind(raw)
    except (TypeError, ValueError):
        raise TelemetryError(path, f"root attribute has a bad value {raw!r}", f"@{name}") from None
    if positive and not (np.isfinite(value) and value > 0):
        raise TelemetryError(path, f"must be positive and finite, got {raw!r}", f"@{name}")
    return value


def json_attr(f: h5py.File, path, name: str) -> dict:
    """A root attribute holding JSON, decoded; errors name the file and attribute."""
    raw = text_attr(f, name, "{}")
    try:
        return json.loads(raw)
    except json.JSONDecodeError as exc:
        raise TelemetryError(path, f"not valid JSON ({exc})", f"@{name}") from None


def read_series(
    f: h5py.File,
    path,
    name: str,
    rows: int,
    size: int,
    start: int = 0,
    stop: int | None = None,
    allow_nan: bool = False,
) -> np.ndarray:
    """Read ``f[name][:, start:stop]`` checking presence, shape and finiteness.

    With ``allow_nan`` NaN (a gap in the data: no sample) is accepted, infinities are not.
    """
    if name not in f:
        raise TelemetryError(path, "missing dataset", name)
    ds = f[name]
    if not isinstance(ds, h5py.Dataset) or ds.shape != (rows, size):
        shape = getattr(ds, "shape", "a group")
        raise TelemetryError(path, f"expected shape ({rows}, {size}), found {shape}", name)
    stop = size if stop is None else min(int(stop), size)
    try:
        values = np.asarray(ds[:, max(int(start), 0) : stop], dtype=float)
    except (OSError, RuntimeError, ValueError) as exc:
        raise TelemetryError(path, f"cannot read data ({exc}); truncated file?", name) from None
    finite = np.isfinite(values) | (np.isnan(values) if allow_nan else False)
    if not finite.all():
        bad = int(np.argmax(~finite.all(axis=0))) + max(int(start), 0)
        raise TelemetryError(path, f"non-finite values (first at sample {bad})", name)
    return values

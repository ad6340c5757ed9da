"""Telemetry in memory and on disk (HDF5, schema in ``docs/telemetry-format.md``).

A :class:`Telemetry` holds what the pipeline may use: the six ``eta_ij`` variables
(fractional frequency), the DWS readouts ``phi`` and ``eta`` of the six MOSAs (rad/s), the
light travel times used as delays (s), the sampling, and the configuration that produced
them.  Ground truth lives in a separate truth file (:mod:`ttlcore.io.truth`), so nothing
downstream can use it by accident.

Every reader accepts both this project's files and lisainstrument 2.x output files
(auto-detected, see :mod:`ttlcore.io.lisainstrument`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._version import __version__
from ..conventions import LINKS, MOSAS
from ..errors import TelemetryError
from .hdf5 import (
    AtomicSeriesWriter,
    json_attr,
    number_attr,
    open_h5,
    read_series,
    text_attr,
)

log = logging.getLogger(__name__)

#: Value of the root attribute ``format`` of our telemetry files.
FORMAT = "ttl-telemetry"
#: Current schema version (integer, bumped on incompatible change).
SCHEMA_VERSION = 1

#: Datasets of a telemetry file: name -> (row labels, unit).
DATASETS: dict[str, tuple[tuple[str, ...], str]] = {
    "eta": (LINKS, "fractional frequency"),
    "dws/phi": (MOSAS, "rad/s"),
    "dws/eta": (MOSAS, "rad/s"),
    "ltt": (LINKS, "s"),
}
_FIELDS = {"eta": "eta", "dws/phi": "dws_phi", "dws/eta": "dws_eta", "ltt": "ltt"}


@dataclass
class Telemetry:
    """One stretch of mission telemetry at the eta level.

    Attributes
    ----------
    t0 : float
        Mission time of the first sample [s].
    fs : float
        Sampling frequency [Hz].
    eta : ndarray, shape (6, n)
        ``eta_ij`` in fractional frequency, links in :data:`~ttlcore.conventions.LINKS` order.
    dws_phi, dws_eta : ndarray, shape (6, n)
        DWS angular-velocity readouts [rad/s] of the six MOSAs (same order).
    ltt : ndarray, shape (6, n)
        Light travel times ``tau_ij`` used as delays [s].
    config : dict
        Configuration that produced the data (simulation settings or source metadata).
    source : str
        Where the data came from (a path, or ``"memory"``).
    """

    t0: float
    fs: float
    eta: np.ndarray
    dws_phi: np.ndarray
    dws_eta: np.ndarray
    ltt: np.ndarray
    config: dict = field(default_factory=dict)
    source: str = "memory"

    def __post_init__(self):
        n = np.shape(self.eta)[-1]
        for name in _FIELDS.values():
            arr = getattr(self, name)
            if np.shape(arr) != (6, n):
                raise TelemetryError(self.source, f"expected shape (6, {n}), got {np.shape(arr)}", name)

    @property
    def size(self) -> int:
        """Number of samples."""
        return self.eta.shape[-1]

    @property
    def duration(self) -> float:
        """Duration [s]."""
        return self.size / self.fs

    @property
    def t(self) -> np.ndarray:
        """Sample times [s]."""
        return self.t0 + np.arange(self.size) / self.fs

    def missing(self) -> np.ndarray:
        """Samples where an eta or DWS series is not finite (a gap in the data), shape (n,)."""
        return ~(
            np.isfinite(self.eta).all(axis=0)
            & np.isfinite(self.dws_phi).all(axis=0)
            & np.isfinite(self.dws_eta).all(axis=0)
        )

    def nan_stretches(self) -> list[list[int]]:
        """Sample ranges ``[start, stop)`` of the gaps (:meth:`missing`)."""
        edges = np.flatnonzero(np.diff(np.concatenate([[0], self.missing().astype(np.int8), [0]])))
        return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2])]

    def slice(self, start: int, stop: int) -> Telemetry:
        """Samples ``start:stop`` as a new :class:`Telemetry` (views, no copy)."""
        start, stop, _ = slice(start, stop).indices(self.size)
        return Telemetry(
            t0=self.t0 + start / self.fs,
            fs=self.fs,
            **{name: getattr(self, name)[:, start:stop] for name in _FIELDS.values()},
            config=self.config,
            source=self.source,
        )


class TelemetryWriter(AtomicSeriesWriter):
    """Write a telemetry file chunk by chunk, atomically (temporary name, then rename).

    Example
    -------
    >>> with TelemetryWriter("day.h5", t0=0.0, fs=4.0, size=345600, config=cfg) as w:
    ...     for chunk in chunks:
    ...         w.append_telemetry(chunk)
    """

    def __init__(self, path, *, t0: float, fs: float, size: int, config: dict):

        attrs = {
            "format": FORMAT,
            "schema_version": SCHEMA_VERSION,
            "t0": float(t0),
            "fs": float(fs),
            "size": int(size),
            "duration": int(size) / float(fs),
            "links": ",".join(LINKS),
            "config": config,
            "producer": f"ttlcore {__version__}",
        }
        super().__init__(path, size=size, datasets=DATASETS, attrs=attrs)

    def append_telemetry(self, tm: Telemetry) -> None:
        """Append the samples of ``tm`` after those already written."""
        for name, fieldname in _FIELDS.items():
            self.append(name, getattr(tm, fieldname))


def write_telemetry(path, tm: Telemetry) -> Path:
    """Write ``tm`` to ``path`` atomically; returns the path."""
    with TelemetryWriter(path, t0=tm.t0, fs=tm.fs, size=tm.size, config=tm.config) as w:
        w.append_telemetry(tm)
    return Path(path)


def read_header(path) -> dict:
    """Root attributes of one of our telemetry files, checked: t0, fs, size, duration, config."""
    with open_h5(path) as f:
        return _header(f, path)


def _header(f, path) -> dict:
    version = number_attr(f, path, "schema_version", int)
    if version > SCHEMA_VERSION:
        raise TelemetryError(
            path, f"schema version {version} is newer than this ttlcore supports ({SCHEMA_VERSION})", "@schema_version"
        )
    fs = number_attr(f, path, "fs", positive=True)
    size = number_attr(f, path, "size", int, positive=True)
    t0 = number_attr(f, path, "t0")
    if "duration" in f.attrs:
        duration = number_attr(f, path, "duration", positive=True)
        if abs(duration - size / fs) > 1e-9 * duration:
            raise TelemetryError(
                path, f"sampling inconsistent: size/fs = {size / fs} s but duration = {duration} s", "@fs"
            )
    for name in DATASETS:
        if name in f and f[name].shape[-1] != size:
            raise TelemetryError(path, f"{f[name].shape[-1]} samples, but @size = {size}", name)
    return {
        "schema_version": version,
        "t0": t0,
        "fs": fs,
        "size": size,
        "duration": size / fs,
        "config": json_attr(f, path, "config"),
        "producer": text_attr(f, "producer", ""),
    }


def read_ttl_telemetry(path, start: int = 0, stop: int | None = None) -> Telemetry:
    """Read one of our telemetry files (samples ``start:stop``); :func:`ttlcore.io.reader.read_telemetry`
    reads any supported format."""
    with open_h5(path) as f:
        head = _header(f, path)
        size = head["size"]
        start, stop, _ = slice(start, stop).indices(size)
        # NaN in eta and the DWS series is a gap in the data (no sample): read as such, the
        # consumers mask it; NaN light travel times are bridged (bridged_ltt), as the
        # lisainstrument reader fills the MPRs
        arrays = {
            fieldname: read_series(f, path, name, 6, size, start, stop, allow_nan=True)
            for name, fieldname in _FIELDS.items()
        }
    arrays["ltt"] = _finite_ltt(path, arrays["ltt"])
    return Telemetry(
        t0=head["t0"] + start / head["fs"], fs=head["fs"], config=head["config"], source=str(path), **arrays
    )


def _finite_ltt(path, ltt: np.ndarray) -> np.ndarray:
    """The light travel times read, each link's NaN bridged (:func:`bridged_ltt`); a link
    with none finite is a :class:`TelemetryError` naming the dataset."""
    bad = ~np.isfinite(ltt)
    if not bad.any():
        return ltt
    out = np.array(ltt, dtype=float)
    for row, link in enumerate(LINKS):
        if bad[row].all():
            raise TelemetryError(
                path, f"no finite light travel time on link {link}: the delays cannot be bridged", "ltt"
            )
        if bad[row].any():
            out[row] = bridged_ltt(out[row : row + 1], bad[row])[0]
            log.info("%s: %d NaN light travel times of link %s bridged", path, int(bad[row].sum()), link)
    return out


def bridged_ltt(ltt: np.ndarray, missing: np.ndarray) -> np.ndarray:
    """Light travel times [s] (6, n) with the samples ``missing`` (n,) bridged: a straight
    line between the valid samples on either side; before the first valid sample and after
    the last, the line of the trend of the valid stretch there (its 14400 samples nearest
    the edge at most: an hour at 4 Hz).

    A stretch whose readouts are missing (a gap the pipeline steps over) must still carry
    delays that join those on either side: TDI interpolates the delays smoothly over its
    blocks (~2.2 h, :mod:`ttlcore.tdi.engine`), and a step in them - the last value held
    over the mission week's 7-h gap (``bench/mission.py``) steps by 21 us - spoils the delays of
    the valid samples the block shares with the gap, leaving laser noise in hours of data
    after the gap (chi2/dof ~100 in every band).  The delays curve slowly (~1e-15 s/s^2 on a
    Keplerian orbit), so a chord across a gap of T misses by ~1e-15 T^2 / 8: 8 ns over 2 h,
    0.1 us over 7 h - in samples whose readouts are missing anyway.

    Parameters
    ----------
    ltt : ndarray (6, n)
        Light travel times [s]; the values at ``missing`` are not read.
    missing : ndarray of bool (n,)
        Samples to bridge.

    Returns
    -------
    ndarray (6, n)
        A copy; ``ltt`` itself when nothing is missing.

    Raises
    ------
    ValueError
        When every sample is missing (nothing to bridge from).
    """
    missing = np.asarray(missing, dtype=bool)
    if not missing.any():
        return ltt
    good = np.flatnonzero(~missing)
    if good.size == 0:
        raise ValueError("bridged_ltt: every sample is missing, nothing to bridge the light travel times from")
    out = np.array(ltt, dtype=float)
    k = np.arange(out.shape[-1])
    inside = missing & (k > good[0]) & (k < good[-1])
    for row in out:
        row[inside] = np.interp(k[inside], good, row[good])
    # before the first valid sample and after the last: the trend of the valid stretch there
    first_stop = good[0] + np.argmax(missing[good[0] :]) if missing[good[0] :].any() else k.size
    last_start = good[-1] + 1 - np.argmax(missing[good[-1] :: -1])  # after the last gap before it
    if not missing[: good[-1]].any():
        last_start = 0
    edges = (
        (k[: good[0]], np.arange(good[0], min(first_stop, good[0] + 14400))),
        (k[good[-1] + 1 :], np.arange(max(last_start, good[-1] - 14399), good[-1] + 1)),
    )
    for outside, stretch in edges:
        if outside.size:
            slope = np.zeros(out.shape[0]) if stretch.size < 2 else np.polyfit(stretch, out[:, stretch].T, 1)[0]
            anchor = stretch[0] if outside[0] < stretch[0] else stretch[-1]
            out[:, outside] = out[:, anchor, None] + slope[:, None] * (outside - anchor)[None]
    return out

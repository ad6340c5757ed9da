"""Ground truth of a simulation, kept in a file of its own beside the telemetry.

``day.h5`` holds what the instrument would deliver; ``day.truth.h5`` holds what only a
simulation knows: the true coefficients over time, the TTL contribution of each link,
the true angles and angular velocities of the MOSAs and, when asked, each noise alone as
it enters ``eta``.  Pipeline code reads telemetry only; truth is opened explicitly
(``ttl analyze --truth``), so it cannot leak into an estimate by accident.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..conventions import COEFFICIENT_NAMES, LINKS, MOSAS
from ..errors import TelemetryError
from .hdf5 import AtomicSeriesWriter, json_attr, number_attr, open_h5, read_series, text_attr

FORMAT = "ttl-truth"
SCHEMA_VERSION = 1

#: Always-present truth datasets: name -> (rows, unit).
CORE_DATASETS: dict[str, tuple[tuple[str, ...], str]] = {
    "ttl": (LINKS, "fractional frequency"),
    "coefficients": (COEFFICIENT_NAMES, "m/rad"),
    "angles/phi": (MOSAS, "rad"),
    "angles/eta": (MOSAS, "rad"),
    "angular_velocity/phi": (MOSAS, "rad/s"),
    "angular_velocity/eta": (MOSAS, "rad/s"),
}
#: Noise components that can be stored alone, as they enter eta (or the DWS readout).
NOISE_COMPONENTS: dict[str, tuple[tuple[str, ...], str]] = {
    "laser": (LINKS, "fractional frequency"),
    "oms": (LINKS, "fractional frequency"),
    "backlink": (LINKS, "fractional frequency"),
    "telescope": (LINKS, "fractional frequency"),
    "test_mass": (LINKS, "fractional frequency"),
    "dws_phi": (MOSAS, "rad/s"),
    "dws_eta": (MOSAS, "rad/s"),
}


def truth_path(telemetry_path) -> Path:
    """``day.h5`` -> ``day.truth.h5``."""
    p = Path(telemetry_path)
    return p.with_name(p.name[: -len(p.suffix)] + ".truth" + p.suffix) if p.suffix else p.with_name(p.name + ".truth")


class TruthWriter(AtomicSeriesWriter):
    """Atomic chunked writer of a truth file (see :class:`ttlcore.io.hdf5.AtomicSeriesWriter`)."""

    def __init__(self, path, *, t0: float, fs: float, size: int, config: dict, noises=(), injections=()):
        unknown = set(noises) - set(NOISE_COMPONENTS)
        if unknown:
            raise ValueError(f"unknown noise components {sorted(unknown)}")
        datasets = dict(CORE_DATASETS)
        datasets.update({f"noises/{n}": NOISE_COMPONENTS[n] for n in noises})
        datasets.update({f"injections/{n}": (LINKS, "fractional frequency") for n in injections})
        attrs = {
            "format": FORMAT,
            "schema_version": SCHEMA_VERSION,
            "t0": float(t0),
            "fs": float(fs),
            "size": int(size),
            "duration": int(size) / float(fs),
            "config": config,
        }
        super().__init__(path, size=size, datasets=datasets, attrs=attrs, compress=frozenset({"coefficients"}))


@dataclass
class Truth:
    """Ground truth read back from a truth file (arrays shaped ``(rows, n)``)."""

    t0: float
    fs: float
    ttl: np.ndarray
    coefficients: np.ndarray
    angles: dict
    angular_velocity: dict
    noises: dict = field(default_factory=dict)
    injections: dict = field(default_factory=dict)
    config: dict = field(default_factory=dict)
    source: str = "memory"

    @property
    def size(self) -> int:
        return self.ttl.shape[-1]

    def mean_coefficients(self) -> np.ndarray:
        """Time-averaged true coefficients [m/rad], shape (24,)."""
        return self.coefficients.mean(axis=1)


def read_truth(path, start: int = 0, stop: int | None = None) -> Truth:
    """Read a truth file; errors name the file and dataset."""
    with open_h5(path) as f:
        if text_attr(f, "format") != FORMAT:
            raise TelemetryError(
                path, f"not a truth file (root attribute format={text_attr(f, 'format')!r})", "@format"
            )
        fs = number_attr(f, path, "fs", positive=True)
        size = number_attr(f, path, "size", int, positive=True)
        t0 = number_attr(f, path, "t0")
        start, stop, _ = slice(start, stop).indices(size)

        def get(name, rows):
            return read_series(f, path, name, len(rows), size, start, stop)

        noises = {}
        if "noises" in f:
            for name in f["noises"]:
                rows = NOISE_COMPONENTS.get(name, (LINKS, ""))[0]
                noises[name] = get(f"noises/{name}", rows)
        injections = {name: get(f"injections/{name}", LINKS) for name in f.get("injections", {})}
        return Truth(
            t0=t0 + start / fs,
            fs=fs,
            ttl=get("ttl", LINKS),
            coefficients=get("coefficients", COEFFICIENT_NAMES),
            angles={a: get(f"angles/{a}", MOSAS) for a in ("phi", "eta")},
            angular_velocity={a: get(f"angular_velocity/{a}", MOSAS) for a in ("phi", "eta")},
            noises=noises,
            injections=injections,
            config=json_attr(f, path, "config"),
            source=str(path),
        )

"""Gravitational-wave injections for the simulator (``kind: "gw"``, see :mod:`ttlcore.sim.injection`).

Each class below is an injection: ``name``, ``describe()`` (JSON, rebuilt by
:func:`injection_from_description`) and ``link_signal(ctx)`` -> (6, n) link responses in
fractional frequency, added to ``eta`` and stored alone in the truth file as
``injections/<name>``. Sources (``docs/gw.md`` for the physics and references):

============  ===================================================================
``hmcnc``     HM Cnc (6.220 mHz), :data:`ttlcore.gw.sources.VERIFICATION_BINARIES`
``ztfj1539``  ZTF J1539+5027 (4.822 mHz)
``vb``        both verification binaries
``galaxy``    galactic white-dwarf population (:mod:`ttlcore.gw.galaxy`)
``sgwb``      isotropic background, h^2 Omega = 1.15e-12 (f / 3 mHz)^(2/3) (:mod:`ttlcore.gw.sgwb`)
``mbhb1``     the paper's MBHB1 merger (:mod:`ttlcore.gw.mbhb`), merging mid-run unless told
``mbhb2``     the paper's MBHB2 merger
``all``       hmcnc, ztfj1539, galaxy, sgwb and mbhb2 (the paper's all-sources day is MBHB2's)
FILE          link responses of a lisagwresponse file (dataset ``tps/y``, or ``FILE:tcb/y``)
============  ===================================================================

:func:`parse_gw_spec` turns the ``--gw`` option into injections; :func:`rebuild_from_truth`
gives "TTL plus GW only" and "everything but TTL" from a telemetry file and its truth.
"""

from __future__ import annotations

import math
from pathlib import Path

import h5py
import numpy as np
from scipy.interpolate import CubicSpline

from ..errors import ConfigError
from .galaxy import GALAXY_DEFAULTS, BinaryArrays, binaries_link_signal, draw_galaxy
from .mbhb import MBHB, PAPER_MBHBS, MBHBWaveform
from .response import link_response
from .sgwb import StochasticBackgroundGenerator
from .sources import VERIFICATION_BINARIES, GalacticBinary

__all__ = [
    "BinariesInjection",
    "GalaxyInjection",
    "SGWBInjection",
    "MBHBInjection",
    "GWFileInjection",
    "injection_from_description",
    "parse_gw_spec",
    "GW_SOURCES",
    "is_gw",
    "gw_names",
    "rebuild_from_truth",
]

#: Galaxy realisation used by ``--gw galaxy`` (the sky is the same in every run).
GALAXY_SEED = 1


class BinariesInjection:
    """A few galactic binaries (exact :func:`ttlcore.gw.response.link_response` of each; for thousands
    use :class:`GalaxyInjection`).

    Parameters
    ----------
    name : str
    binaries : list of :class:`ttlcore.gw.sources.GalacticBinary` or of their parameter dicts
    """

    def __init__(self, name: str, binaries):

        self.name = str(name)
        self.binaries = [b if isinstance(b, GalacticBinary) else GalacticBinary(**b) for b in binaries]

    @classmethod
    def catalogue(cls, names, name: str | None = None) -> BinariesInjection:
        """From catalogue keys (``"HM Cnc"``, ``"ZTF J1539"``)."""

        return cls(
            name or "_".join(n.replace(" ", "").lower() for n in names), [VERIFICATION_BINARIES[n] for n in names]
        )

    def describe(self) -> dict:
        keys = ("f0", "fdot", "amplitude", "inclination", "psi", "phi0", "beta", "lam", "t_init", "name")
        return {
            "kind": "gw",
            "source": "binaries",
            "name": self.name,
            "binaries": [{k: getattr(b, k) for k in keys} for b in self.binaries],
        }

    def link_signal(self, ctx) -> np.ndarray:
        out = np.zeros((6, ctx.n))
        for b in self.binaries:
            out += link_response(ctx.orbit, ctx.t, b.hplus, b.hcross, b.beta, b.lam, b.psi)
        return out


class GalaxyInjection:
    """Galactic white-dwarf population (:func:`ttlcore.gw.galaxy.draw_galaxy`), summed with
    :func:`ttlcore.gw.galaxy.binaries_link_signal`.

    Parameters
    ----------
    name : str
    seed : int
        Seed of the population draw.
    t_init : float
        Reference time of the binaries' frequencies and phases [s].
    model : dict
        Overrides of :data:`ttlcore.gw.galaxy.GALAXY_DEFAULTS`.
    """

    def __init__(self, name: str = "galaxy", seed: int = GALAXY_SEED, t_init: float = 0.0, model: dict | None = None):

        self.name = str(name)
        self.seed = int(seed)
        self.t_init = float(t_init)
        self.model = dict(model or {})
        unknown = set(self.model) - set(GALAXY_DEFAULTS)
        if unknown:
            raise ConfigError(
                f"galaxy: unknown model parameters {sorted(unknown)}; known: {', '.join(GALAXY_DEFAULTS)}"
            )
        self._binaries: BinaryArrays | None = None

    @property
    def binaries(self):
        if self._binaries is None:
            self._binaries = draw_galaxy(self.seed, t_init=self.t_init, **self.model)
        return self._binaries

    def describe(self) -> dict:
        return {
            "kind": "gw",
            "source": "galaxy",
            "name": self.name,
            "seed": self.seed,
            "t_init": self.t_init,
            "model": self.model,
        }

    def link_signal(self, ctx) -> np.ndarray:

        return binaries_link_signal(ctx.orbit, ctx.t, self.binaries)


# one generator per geometry and settings, shared by injections in this process (the
# filter design takes a few seconds)
_SGWB_CACHE: dict = {}


class SGWBInjection:
    """Isotropic stochastic background (:class:`ttlcore.gw.sgwb.StochasticBackgroundGenerator`).

    The geometry is the orbit's at the first chunk simulated; samples are indexed by their
    absolute index ``ctx.n0 + j``, so the realisation does not depend on the chunking.
    """

    def __init__(
        self,
        name: str = "sgwb",
        seed: int = 0,
        omega_h2: float = 1.15e-12,
        f_ref: float = 3e-3,
        alpha: float = 2.0 / 3.0,
        n_pix: int = 1024,
        filter_length: int = 1 << 14,
    ):
        self.name = str(name)
        self.seed = int(seed)
        self.omega_h2, self.f_ref, self.alpha = float(omega_h2), float(f_ref), float(alpha)
        if not (self.omega_h2 >= 0 and self.f_ref > 0 and math.isfinite(self.alpha)):
            raise ConfigError(f"sgwb: need omega_h2 >= 0, f_ref > 0, finite alpha; got {omega_h2}, {f_ref}, {alpha}")
        self.n_pix, self.filter_length = int(n_pix), int(filter_length)
        self._gen: StochasticBackgroundGenerator | None = None

    def describe(self) -> dict:
        return {
            "kind": "gw",
            "source": "sgwb",
            "name": self.name,
            "seed": self.seed,
            "omega_h2": self.omega_h2,
            "f_ref": self.f_ref,
            "alpha": self.alpha,
            "n_pix": self.n_pix,
            "filter_length": self.filter_length,
        }

    def generator(self, orbit, t: float, fs: float):

        if self._gen is None:
            pos = np.asarray(orbit.positions(np.array([t])), dtype=float)[:, 0, :]
            ltt = np.asarray(orbit.ltt(np.array([t])), dtype=float)[:, 0]
            key = (
                tuple(np.round((pos - pos.mean(axis=0)).ravel(), 0)),
                tuple(np.round(ltt, 9)),
                fs,
                self.seed,
                self.omega_h2,
                self.f_ref,
                self.alpha,
                self.n_pix,
                self.filter_length,
            )
            gen = _SGWB_CACHE.get(key)
            if gen is None:
                gen = StochasticBackgroundGenerator(
                    pos,
                    ltt,
                    fs,
                    seed=self.seed,
                    key=f"sgwb:{self.name}",
                    filter_length=self.filter_length,
                    n_pix=self.n_pix,
                    omega_h2=self.omega_h2,
                    f_ref=self.f_ref,
                    alpha=self.alpha,
                )
                if len(_SGWB_CACHE) > 4:
                    _SGWB_CACHE.clear()
                _SGWB_CACHE[key] = gen
            self._gen = gen
        return self._gen

    def link_signal(self, ctx) -> np.ndarray:
        gen = self.generator(ctx.orbit, float(ctx.t[0]), ctx.fs)
        return gen.get(ctx.n0, ctx.n0 + ctx.n)


class MBHBInjection:
    """A massive black-hole binary merger (:class:`ttlcore.gw.mbhb.MBHB`, closed-form IMR waveform)."""

    def __init__(self, name: str, **params):

        self.name = str(name)
        params["name"] = self.name
        try:
            self.source = MBHB(**params)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"mbhb {name!r}: {exc}") from None
        self._wave: MBHBWaveform | None = None

    @classmethod
    def paper(cls, which: str, t_c: float | None = None) -> MBHBInjection:

        params = dict(PAPER_MBHBS[which])
        params.pop("name", None)
        if t_c is not None:
            params["t_c"] = float(t_c)
        return cls(which, **params)

    @property
    def waveform(self):
        if self._wave is None:
            self._wave = MBHBWaveform(self.source)
        return self._wave

    def describe(self) -> dict:
        d = {"kind": "gw", "source": "mbhb", "name": self.name}
        d.update({k: v for k, v in self.source.to_dict().items() if k != "name"})
        return d

    def link_signal(self, ctx) -> np.ndarray:
        w, s = self.waveform, self.source
        return link_response(ctx.orbit, ctx.t, w.hplus, w.hcross, s.beta, s.lam, s.psi)


class GWFileInjection:
    """Link responses of a lisagwresponse GW file (``dataset`` ``tps/y`` by default, shape (size, 6),
    links ``12, 23, 31, 13, 32, 21``; attributes ``t0``, ``dt``, ``size``). Samples on the
    simulation's grid are taken as they are; other times are interpolated with a cubic spline.
    Times outside the file are an error."""

    def __init__(self, path, dataset: str = "tps/y", name: str | None = None):

        self.path = Path(path)
        self.dataset = str(dataset)
        self.name = name or f"file_{self.path.stem}"
        if not self.path.is_file():
            raise ConfigError(f"--gw: {self.path}: no such file")
        try:
            with h5py.File(self.path, "r") as f:
                if self.dataset not in f:
                    raise ConfigError(
                        f"--gw: {self.path}: no dataset {self.dataset!r} (a lisagwresponse file has tps/y and/or tcb/y)"
                    )
                shape = f[self.dataset].shape
                try:
                    self.t0, self.dt, self.size = float(f.attrs["t0"]), float(f.attrs["dt"]), int(f.attrs["size"])
                except KeyError as exc:
                    raise ConfigError(f"--gw: {self.path}: missing attribute {exc.args[0]!r} (t0, dt, size)") from None
        except OSError as exc:
            raise ConfigError(f"--gw: {self.path}: not a readable HDF5 file ({exc})") from None
        if len(shape) != 2 or shape[1] != 6 or shape[0] != self.size:
            raise ConfigError(f"--gw: {self.path}: dataset {self.dataset} has shape {shape}, expected ({self.size}, 6)")
        if not (self.dt > 0):
            raise ConfigError(f"--gw: {self.path}: attribute dt must be positive, got {self.dt}")

    def describe(self) -> dict:
        return {"kind": "gw", "source": "file", "name": self.name, "path": str(self.path), "dataset": self.dataset}

    def link_signal(self, ctx) -> np.ndarray:

        t = np.asarray(ctx.t, dtype=float)
        pos = (t - self.t0) / self.dt
        if pos[0] < -1e-6 or pos[-1] > self.size - 1 + 1e-6:
            raise ConfigError(
                f"--gw: {self.path} covers {self.t0:g} .. {self.t0 + (self.size - 1) * self.dt:g} s, "
                f"the simulation needs {t[0]:g} .. {t[-1]:g} s"
            )
        idx = np.rint(pos).astype(int)
        with h5py.File(self.path, "r") as f:
            ds = f[self.dataset]
            if np.allclose(pos, idx, atol=1e-6, rtol=0):
                i0, i1 = idx[0], idx[-1] + 1
                block = ds[i0:i1]
                return np.ascontiguousarray(block[idx - i0].T)

            i0 = max(int(math.floor(pos[0])) - 3, 0)
            i1 = min(int(math.ceil(pos[-1])) + 4, self.size)
            block = ds[i0:i1]
        sp = CubicSpline(self.t0 + np.arange(i0, i1) * self.dt, block, axis=0)
        return np.ascontiguousarray(sp(t).T)


def injection_from_description(description: dict):
    """Rebuild a GW injection from its :meth:`describe` output."""
    d = dict(description)
    source = d.pop("source", None)
    d.pop("kind", None)
    name = d.pop("name", None)
    try:
        if source == "binaries":
            return BinariesInjection(name, d["binaries"])
        if source == "galaxy":
            return GalaxyInjection(
                name, seed=d.get("seed", GALAXY_SEED), t_init=d.get("t_init", 0.0), model=d.get("model")
            )
        if source == "sgwb":
            return SGWBInjection(name, **d)
        if source == "mbhb":
            return MBHBInjection(name, **d)
        if source == "file":
            return GWFileInjection(d["path"], d.get("dataset", "tps/y"), name=name)
    except (KeyError, TypeError) as exc:
        raise ConfigError(f"gw injection {name!r}: bad description ({exc})") from None
    raise ConfigError(f"gw injection: unknown source {source!r}; known: binaries, galaxy, sgwb, mbhb, file")


#: The names ``--gw`` knows (besides files).
GW_SOURCES = ("hmcnc", "ztfj1539", "vb", "galaxy", "sgwb", "mbhb1", "mbhb2", "all")


def parse_gw_spec(
    spec: str, *, t0: float = 0.0, duration: float = 86400.0, seed: int = 0, t_c: float | None = None
) -> tuple:
    """Injections for ``--gw`` (module docstring): comma-separated source names or files.

    ``t_c`` (merger time) defaults to the middle of the run, ``t0 + duration / 2``; the
    background's realisation follows ``seed``.
    """
    items = [s.strip() for s in str(spec).split(",") if s.strip()]
    if not items:
        raise ConfigError(f"--gw: empty; use {', '.join(GW_SOURCES)} or a lisagwresponse FILE")
    t_c = t0 + duration / 2 if t_c is None else t_c
    names, files = _gw_items(items)
    out: list = []
    seen = set()
    for n in names:
        if n in seen:
            continue
        seen.add(n)
        out += _named_source(n, seed, t_c)
    for item in files:
        path, dataset = item, "tps/y"
        if ":" in item and not Path(item).exists():
            path, dataset = item.split(":", 1)
        out.append(GWFileInjection(path, dataset))
    names_out = [i.name for i in out]
    if len(set(names_out)) != len(names_out):
        raise ConfigError(f"--gw: two injections share a name: {names_out}")
    return tuple(out)


def _gw_items(items: list[str]) -> tuple[list[str], list[str]]:
    """The items of ``--gw`` as source names (``all`` and ``vb`` expanded) and lisagwresponse
    files (``FILE`` or ``FILE:dataset``); ConfigError naming an item that is neither."""
    names: list[str] = []
    files: list[str] = []
    for item in items:
        key = item.lower()
        if key == "all":
            names += ["hmcnc", "ztfj1539", "galaxy", "sgwb", "mbhb2"]
        elif key == "vb":
            names += ["hmcnc", "ztfj1539"]
        elif key in GW_SOURCES:
            names.append(key)
        else:
            path = item
            if ":" in item and not Path(item).exists():
                path = item.split(":", 1)[0]
            if not Path(path).exists():
                raise ConfigError(
                    f"--gw: unknown source {item!r}; known: {', '.join(GW_SOURCES)}, or an existing "
                    "lisagwresponse file (FILE or FILE:tcb/y)"
                )
            files.append(item)
    return names, files


def _named_source(n: str, seed: int, t_c: float) -> list:
    """The injection of the named source ``n`` (a list of one; empty for a name without
    one): the background's realisation follows ``seed``, a merger is at ``t_c`` [s]."""
    if n == "hmcnc":
        return [BinariesInjection.catalogue(["HM Cnc"], name="hmcnc")]
    if n == "ztfj1539":
        return [BinariesInjection.catalogue(["ZTF J1539"], name="ztfj1539")]
    if n == "galaxy":
        return [GalaxyInjection()]
    if n == "sgwb":
        return [SGWBInjection(seed=seed)]
    if n in ("mbhb1", "mbhb2"):
        return [MBHBInjection.paper(n, t_c=t_c)]
    return []


def is_gw(description_or_injection) -> bool:
    """Whether an injection (or its description) is a gravitational wave."""
    d = description_or_injection
    if not isinstance(d, dict):
        d = d.describe()
    return d.get("kind") == "gw"


def gw_names(config: dict) -> list[str]:
    """Names of the GW injections of a simulation configuration (a telemetry or truth file's ``config``)."""
    return [d.get("name") for d in config.get("injections", []) if d.get("kind") == "gw"]


def rebuild_from_truth(telemetry, truth) -> dict:
    """The data sets of the paper's GW-intact check, from a telemetry and its truth.

    Parameters
    ----------
    telemetry : :class:`ttlcore.io.telemetry.Telemetry`
    truth : :class:`ttlcore.io.truth.Truth`
        Same samples as ``telemetry``.

    Returns
    -------
    dict of (6, n) arrays (``eta``-like, fractional frequency)
        ``gw`` (sum of the GW injections), ``ttl_plus_gw`` (true TTL plus GW, no other
        noise) and ``everything_but_ttl`` (``eta - ttl``). The DWS readouts of
        ``telemetry`` are unchanged in all of them.
    """
    if truth.ttl.shape != telemetry.eta.shape:
        raise ConfigError(
            f"truth {truth.source}: {truth.ttl.shape[-1]} samples, telemetry has {telemetry.eta.shape[-1]}"
        )
    names = [n for n in gw_names(truth.config or telemetry.config) if n in truth.injections]
    gw = sum((truth.injections[n] for n in names), np.zeros_like(truth.ttl))
    return {"gw": gw, "ttl_plus_gw": truth.ttl + gw, "everything_but_ttl": telemetry.eta - truth.ttl}

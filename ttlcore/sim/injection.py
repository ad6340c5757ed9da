"""Extra signals injected into the simulated ``eta`` variables.

The simulator (:mod:`ttlcore.sim.simulator`) forms the noises and the linear TTL of
docs/physics.md; everything else that a study adds to the data - a gravitational wave, a
model effect the fit does not know about - is an *injection*: an object that, given the
state of one simulated chunk (:class:`ChunkContext`), returns the signal it adds to the
six ``eta_ij`` in fractional frequency.  The injected signal of each injection is stored
alone in the truth file (``injections/<name>``), never in the telemetry.

An injection is any object with

``name`` : str
    Unique within a simulation; names the truth dataset ``injections/<name>``.
``describe()`` -> dict
    JSON description with a ``"kind"`` key; :func:`injection_from_description` rebuilds
    the injection from it (so a telemetry file's stored configuration reproduces the run).
``link_signal(ctx)`` -> ndarray, shape (6, n)
    The signal added to ``eta`` on the six links (canonical order) [fractional frequency].

Kinds are resolved lazily by module (``"effect"`` -> :mod:`ttlcore.effects.registry`, ``"gw"`` ->
:mod:`ttlcore.gw.injection`), or by a ``"module"`` key naming any importable module or
Python file that defines ``injection_from_description(description)``.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from ..errors import ConfigError
from .orbits import Orbit

#: Samples past the chunk given to injections (``ChunkContext.*_ahead``): 64 samples,
#: 16 s at 4 Hz, for reading angles a few seconds ahead with centred Lagrange stencils.
LOOKAHEAD = 64

#: kind -> module defining ``injection_from_description(description)``.
KIND_MODULES = {"effect": "ttlcore.effects.registry", "gw": "ttlcore.gw.injection"}


@dataclass
class ChunkContext:
    """What the simulator knows while it forms one chunk (samples ``n0 .. n0+n-1``).

    Arrays with an ``_ext`` time axis start ``h`` samples before the chunk (the history
    the delays need); the last ``n`` samples are the chunk itself.

    Attributes
    ----------
    n0, n, h : int
        First absolute sample, chunk length, history length [samples].
    fs : float
        Sampling rate [Hz].
    t : ndarray (n,)
        Times of the chunk's samples [s].
    t_ext : ndarray (h + n,)
        Times including the history [s].
    ltt : ndarray (6, n)
        True light travel times of the links [s].
    orbit : ttlcore.sim.orbits.Orbit
        The orbit (spacecraft positions for GW responses).
    phi_dot, eta_dot : ndarray (6, h + n)
        True MOSA angular velocities [rad/s], MOSA order (docs/physics.md).
    coefficients : ndarray (24, h + n)
        True linear TTL coefficients [m/rad].
    delayed_onto_links : callable
        ``x`` (6 MOSA-indexed rows, ``h + n`` samples) -> ``D_ij x_ji`` on each link
        ``ij``, shape (6, n), with the true light travel times (the simulator's own
        interpolation).
    interpolation_order : int
        Lagrange order of the simulator's delays.
    phi_dot_ahead, eta_dot_ahead : ndarray (6, LOOKAHEAD)
        The true angular velocities of the :data:`LOOKAHEAD` samples after the chunk (the
        next chunk's first samples, drawn from the same random-access noise streams).
    coefficients_ahead : ndarray (24, LOOKAHEAD)
        The true coefficients there.
    """

    n0: int
    n: int
    h: int
    fs: float
    t: np.ndarray
    t_ext: np.ndarray
    ltt: np.ndarray
    orbit: Orbit
    phi_dot: np.ndarray
    eta_dot: np.ndarray
    coefficients: np.ndarray
    delayed_onto_links: Callable[[np.ndarray], np.ndarray]
    interpolation_order: int
    phi_dot_ahead: np.ndarray | None = None
    eta_dot_ahead: np.ndarray | None = None
    coefficients_ahead: np.ndarray | None = None


@runtime_checkable
class Injection(Protocol):
    name: str

    def describe(self) -> dict: ...

    def link_signal(self, ctx: ChunkContext) -> np.ndarray: ...


def load_module(spec: str):
    """Import a module by dotted name or from a ``.py`` file path."""
    path = Path(spec)
    if spec.endswith(".py") or path.exists():
        if not path.is_file():
            raise ConfigError(f"{spec}: no such Python file")
        mod_name = f"ttl_user_{path.stem}_{abs(hash(str(path.resolve()))) & 0xFFFFFF:06x}"
        module_spec = importlib.util.spec_from_file_location(mod_name, path)
        if module_spec is None or module_spec.loader is None:
            raise ConfigError(f"{spec}: cannot load (not a Python source file)")
        module = importlib.util.module_from_spec(module_spec)
        try:
            module_spec.loader.exec_module(module)
        except Exception as exc:  # a user's file: report it as a configuration error
            raise ConfigError(f"{spec}: cannot load ({type(exc).__name__}: {exc})") from exc
        return module
    try:
        return importlib.import_module(spec)
    except ImportError as exc:
        raise ConfigError(f"cannot import module {spec!r} ({exc})") from exc


def injection_from_description(description: dict) -> Injection:
    """Rebuild an injection from :meth:`Injection.describe` output."""
    if not isinstance(description, dict) or "kind" not in description:
        raise ConfigError(f"injection description needs a 'kind': {description!r}")
    module_name = description.get("module") or KIND_MODULES.get(description["kind"])
    if module_name is None:
        raise ConfigError(f"unknown injection kind {description['kind']!r}; known: {', '.join(KIND_MODULES)}")
    module = load_module(module_name)
    build = getattr(module, "injection_from_description", None)
    if build is None:
        raise ConfigError(f"{module_name} defines no injection_from_description()")
    return build(description)


def check_signal(injection: Injection, signal: np.ndarray, n: int) -> np.ndarray:
    """Validate an injection's output: finite, shape (6, n)."""
    signal = np.asarray(signal, dtype=float)
    if signal.shape != (6, n):
        raise ConfigError(f"injection {injection.name!r}: link_signal returned shape {signal.shape}, expected (6, {n})")
    if not np.all(np.isfinite(signal)):
        raise ConfigError(f"injection {injection.name!r}: link_signal returned non-finite values")
    return signal

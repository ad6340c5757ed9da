"""Mission simulator at the eta level (docs/physics.md, measurement model).

For each link ``ij`` (received at SC ``i`` from SC ``j``) the simulator produces

    eta_ij = D_ij p_j - p_i + ttl_ij + o_ij + b_ij + s_ij + delta_ij + D_ij delta_ji

with ``p_i`` the laser noise of SC ``i``, ``o``, ``b``, ``s`` the effective OMS readout,
backlink and telescope noises of the link (:mod:`ttlcore.sim.noise_models`), ``delta_ij`` the
velocity noise of test mass ``ij`` over ``c``, and the tilt-to-length term (velocities,
lisainstrument's sign convention)

    ttl_ij = -(1/c) [ C[ij,phi,rx] dphi_ij/dt + C[ij,eta,rx] deta_ij/dt
                      + D_ij( C[ji,phi,tx] dphi_ji/dt + C[ji,eta,tx] deta_ji/dt ) ].

MOSA angles are the sum of spacecraft and MOSA jitter,
``phi_ij = phi_SC_i + phi_MOSA_ij`` and
``eta_ij = cos(a_ij) eta_SC_i - sin(a_ij) theta_SC_i + eta_MOSA_ij``; the DWS readout of MOSA
``ij`` is its own total angular velocity, undelayed, plus DWS readout noise.  Jitter is
generated as angular velocity (as lisainstrument does), so the DWS series are the very
quantities the TTL term multiplies.

Laser noise and its delays
--------------------------
X2 must suppress laser noise (about 1e-13/sqrt(Hz)) below secondary noises near 1e-20,
so the delayed laser noise must be accurate to better than 1e-7 up to 0.9 Hz.  As in
lisainstrument, the laser terms ``D_ij p_j - p_i`` are formed at an upsampled physics
rate (16 Hz by default), where order-31 Lagrange interpolation is exact to ~1e-15 in the
band, then passed through a zero-phase Kaiser anti-alias filter (passband 1.1 Hz,
stopband 2.9 Hz, 240 dB, lisainstrument's default) and decimated to 4 Hz.  The filter
commutes with the delays up to terms of order ``dtau/dt ~ 1e-8``, so TDI on the 4-Hz
data cancels the laser noise as it would on the physics-rate data.  All other series
are generated directly at the telemetry rate with their model ASD up to Nyquist.

Chunks
------
Every noise is a random-access :class:`~ttlcore.sim.noise.NoiseStream` indexed by absolute
sample number, so a chunk only asks for the samples it needs (including the history
that delays reach back to).  The output is identical whatever the chunk size, and a
7-day mission needs only one chunk in memory.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, fields

import numpy as np
from scipy import signal

from ..conventions import (
    COEFFICIENT_NAMES,
    DAY,
    FS_TELEMETRY,
    LINKS,
    MOSA_ANGLES_DEG,
    MOSAS,
    REVERSED_INDEX,
    C,
    local_spacecraft,
)
from ..errors import ConfigError
from ..io.telemetry import Telemetry, TelemetryWriter
from ..io.truth import NOISE_COMPONENTS, TruthWriter, truth_path
from ..tdi.interpolation import DEFAULT_ORDER, apply_taps, delay, shift_taps
from . import noise_models
from .coefficients import CoefficientModel, make_coefficients
from .injection import LOOKAHEAD, ChunkContext, check_signal, injection_from_description
from .noise import NoiseStream, default_filter_length, run_block_length
from .orbits import Orbit, make_orbit

log = logging.getLogger(__name__)

#: Noise read around a run beyond its samples [s] (delay history, interpolation stencils,
#: the anti-alias filter): the noise blocks are sized to hold the run and this margin
BLOCK_MARGIN_S = 600.0


@dataclass
class NoiseSwitches:
    """Which noises and couplings are on.  ``dws`` is the DWS readout noise, ``ttl`` the
    coupling of jitter into ``eta``; jitter itself is ``sc_jitter`` and ``mosa_jitter``."""

    laser: bool = True
    oms: bool = True
    backlink: bool = True
    telescope: bool = True
    test_mass: bool = True
    sc_jitter: bool = True
    mosa_jitter: bool = True
    dws: bool = True
    ttl: bool = True

    @classmethod
    def parse(cls, spec: str) -> NoiseSwitches:
        """Parse ``"all"``, ``"none"``, ``"all,-laser,-dws"`` or ``"ttl,sc_jitter,mosa_jitter"``."""
        names = [f.name for f in fields(cls)]
        items = [s.strip() for s in str(spec).split(",") if s.strip()]
        if not items:
            raise ConfigError("--noises: empty; use 'all', 'none' or a list such as 'all,-laser'")
        state = dict.fromkeys(names, False)
        for item in items:
            if item == "all":
                state = dict.fromkeys(names, True)
            elif item == "none":
                state = dict.fromkeys(names, False)
            else:
                on = not item.startswith("-")
                key = item.lstrip("+-").replace("-", "_")
                if key not in state:
                    raise ConfigError(f"--noises: unknown noise {key!r}; known: {', '.join(names)}")
                state[key] = on
        return cls(**state)


@dataclass
class SimulationConfig:
    """Everything that defines a simulated mission stretch.

    Attributes
    ----------
    duration : float
        Length [s].
    t0 : float
        Mission time of the first sample [s].
    fs : float
        Telemetry sampling rate [Hz].
    orbit : str
        ``equal``, ``unequal`` (the paper's static arms), ``keplerian`` or a lisaorbits file.
    coefficients : CoefficientModel
        Truth TTL coefficients, possibly time-varying.
    seed : int
        Master seed; each noise draws from its own named stream, so switching one noise
        off leaves the realisation of the others unchanged.
    noises : NoiseSwitches
    jitter : dict
        Angle ASD levels [rad/sqrt(Hz)] and knee: ``sc``, ``mosa_phi``, ``mosa_eta``,
        ``fknee`` [Hz], optionally ``fhigh`` [Hz] (a high-frequency corner above which the
        jitter falls as ``f^-2``), ``dws`` (readout noise).
    interpolation_order : int
        Lagrange order of the delays.
    laser_upsampling : int
        Physics rate of the laser terms is ``fs * laser_upsampling``.
    truth_noises : tuple of str
        Noise components to store alone in the truth file (see :data:`ttlcore.io.truth.NOISE_COMPONENTS`).
    injections : tuple of :class:`ttlcore.sim.injection.Injection`
        Extra signals added to ``eta`` (gravitational waves, model effects); each is
        stored alone in the truth file as ``injections/<name>``.
    """

    duration: float = DAY
    t0: float = 0.0
    fs: float = FS_TELEMETRY
    orbit: str = "unequal"
    coefficients: CoefficientModel = field(default_factory=lambda: make_coefficients("paper"))
    seed: int = 0
    noises: NoiseSwitches = field(default_factory=NoiseSwitches)
    jitter: dict = field(
        default_factory=lambda: {"sc": 5e-9, "mosa_phi": 2e-9, "mosa_eta": 1e-9, "fknee": 0.8e-3, "dws": 70e-9 / 335}
    )
    interpolation_order: int = DEFAULT_ORDER
    laser_upsampling: int = 4
    truth_noises: tuple = ()
    injections: tuple = ()

    def __post_init__(self):
        if not (np.isfinite(self.duration) and self.duration > 0):
            raise ConfigError(f"duration must be positive, got {self.duration}")
        if not (np.isfinite(self.fs) and self.fs > 0):
            raise ConfigError(f"fs must be positive, got {self.fs}")
        if self.interpolation_order < 1 or self.interpolation_order % 2 == 0:
            raise ConfigError(f"interpolation order must be odd and positive, got {self.interpolation_order}")
        if int(self.laser_upsampling) < 1:
            raise ConfigError(f"laser_upsampling must be >= 1, got {self.laser_upsampling}")
        unknown = set(self.truth_noises) - set(NOISE_COMPONENTS)
        if unknown:
            raise ConfigError(f"unknown truth noise components {sorted(unknown)}; known: {', '.join(NOISE_COMPONENTS)}")
        self.injections = tuple(self.injections)
        names = [inj.name for inj in self.injections]
        if len(set(names)) != len(names):
            raise ConfigError(f"injection names must be unique, got {names}")

    @property
    def size(self) -> int:
        return int(round(self.duration * self.fs))

    def to_dict(self) -> dict:
        """JSON-serialisable form (stored in the telemetry file's ``config`` attribute)."""
        d = {
            "duration": self.duration,
            "t0": self.t0,
            "fs": self.fs,
            "orbit": self.orbit,
            "coefficients": self.coefficients.describe(),
            "seed": self.seed,
            "noises": asdict(self.noises),
            "jitter": dict(self.jitter),
            "interpolation_order": self.interpolation_order,
            "laser_upsampling": self.laser_upsampling,
            "truth_noises": list(self.truth_noises),
        }
        if self.injections:
            d["injections"] = [inj.describe() for inj in self.injections]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SimulationConfig:
        d = dict(d)
        d["coefficients"] = CoefficientModel.from_description(d["coefficients"])
        d["noises"] = NoiseSwitches(**d.get("noises", {}))
        d["truth_noises"] = tuple(d.get("truth_noises", ()))
        d["injections"] = tuple(injection_from_description(x) for x in d.get("injections", ()))
        return cls(**{k: v for k, v in d.items() if k in {f.name for f in fields(cls)}})


def anti_alias_filter(
    fs_physics: float, down: int, attenuation_db: float = 240.0, passband: float = 1.1, stopband: float = 2.9
) -> np.ndarray:
    """Kaiser-window low-pass FIR (lisainstrument's default: 240 dB, 1.1 Hz pass, 2.9 Hz stop).

    The number of taps is odd, and its half-length a multiple of ``down`` so that the
    decimated output samples fall on the filter's centre (zero phase).
    """
    numtaps, beta = signal.kaiserord(attenuation_db, (stopband - passband) / (fs_physics / 2))
    half = -(-(numtaps // 2) // down) * down  # ceil to a multiple of down
    return signal.firwin(2 * half + 1, (passband + stopband) / 2, window=("kaiser", beta), fs=fs_physics)


class Simulator:
    """Chunked, random-access simulator of the six ``eta_ij``, DWS readouts and truth.

    Example
    -------
    >>> sim = Simulator(SimulationConfig(duration=3600))
    >>> tm, truth = sim.chunk(0, 14400)
    """

    def __init__(self, config: SimulationConfig, orbit: Orbit | None = None):
        self.config = config
        self.orbit = orbit if orbit is not None else make_orbit(config.orbit)
        cfg, sw, jit = config, config.noises, config.jitter
        fs = cfg.fs
        self.fs_physics = fs * int(cfg.laser_upsampling)
        vel = noise_models.as_velocity

        def stream(on, key, model, n, rate=fs):
            if not on:
                return None
            # output blocks sized to the run (a short run computes one short block, not 1.5
            # filter lengths); the samples do not depend on it beyond rounding (noise.py)
            taps = default_filter_length(rate)
            block = run_block_length(
                int(math.ceil(cfg.duration * rate)), taps, margin=int(math.ceil(BLOCK_MARGIN_S * rate))
            )
            return NoiseStream(
                model, rate, seed=cfg.seed, key=key, n_channels=n, block_length=block, keep_white=block >= taps // 2
            )

        def jitter_model(level):
            return vel(_Jitter(level, jit["fknee"], jit.get("fhigh")))

        self.streams = {
            "laser": stream(sw.laser, "laser", noise_models.laser, 3, self.fs_physics),
            "oms": stream(sw.oms, "oms", noise_models.oms, 6),
            "backlink": stream(sw.backlink, "backlink", noise_models.backlink, 6),
            "telescope": stream(sw.telescope, "telescope", noise_models.telescope, 6),
            "test_mass": stream(sw.test_mass, "test_mass", noise_models.test_mass, 6),
            # rows: SC1 (phi, eta, theta), SC2 (...), SC3 (...)
            "sc_jitter": stream(sw.sc_jitter, "sc_jitter", jitter_model(jit["sc"]), 9),
            "mosa_jitter_phi": stream(sw.mosa_jitter, "mosa_jitter_phi", jitter_model(jit["mosa_phi"]), 6),
            "mosa_jitter_eta": stream(sw.mosa_jitter, "mosa_jitter_eta", jitter_model(jit["mosa_eta"]), 6),
            # rows: phi of the six MOSAs, then eta
            "dws": stream(sw.dws, "dws", vel(_White(jit["dws"])), 12),
        }
        self.aa_filter = (
            anti_alias_filter(self.fs_physics, int(cfg.laser_upsampling)) if cfg.laser_upsampling > 1 else np.ones(1)
        )
        angles = np.radians([MOSA_ANGLES_DEG[m] for m in MOSAS])
        self._cos, self._sin = np.cos(angles)[:, None], np.sin(angles)[:, None]
        self._sc_of_mosa = np.array([local_spacecraft(m) - 1 for m in MOSAS])
        names = list(COEFFICIENT_NAMES)
        self._rx = [np.array([names.index(f"{m}.{a}.rx") for m in MOSAS]) for a in ("phi", "eta")]
        self._tx = [np.array([names.index(f"{m}.{a}.tx") for m in MOSAS]) for a in ("phi", "eta")]
        self._emitter = np.array([int(l[1]) - 1 for l in LINKS])
        self._receiver = np.array([int(l[0]) - 1 for l in LINKS])

    @property
    def size(self) -> int:
        return self.config.size

    def _get(self, name, start, stop, rows):
        s = self.streams[name]
        return s.get(start, stop) if s is not None else np.zeros((rows, stop - start))

    def _history(self, ltt: np.ndarray, fs: float) -> int:
        """Samples of history that delays up to ``max(ltt)`` need with the Lagrange stencil."""
        return int(np.ceil(np.max(ltt) * fs)) + self.config.interpolation_order // 2 + 3

    def laser_terms(self, n0: int, n: int) -> np.ndarray:
        """``D_ij p_j - p_i`` at the telemetry rate for samples ``n0 .. n0+n-1``, shape (6, n)."""
        cfg = self.config
        up = int(cfg.laser_upsampling)
        fsu = self.fs_physics
        half = (self.aa_filter.size - 1) // 2
        m0, m1 = up * n0 - half, up * (n0 + n - 1) + half + 1
        tu = cfg.t0 + np.arange(m0, m1) / fsu
        lttu = self.orbit.ltt(tu)
        hist = self._history(lttu, fsu)
        p = self.streams["laser"].get(m0 - hist, m1)
        delayed = delay(p[self._emitter], lttu, fsu, cfg.interpolation_order, history=hist)
        term = delayed - p[self._receiver, hist:]
        if up == 1:
            return term
        # zero-phase FIR + decimation: output k sits at term index up*k + half
        out = signal.upfirdn(self.aa_filter, term, up=1, down=up, axis=-1)
        k0 = 2 * half // up
        return out[:, k0 : k0 + n]

    def chunk(self, n0: int, n: int) -> tuple[Telemetry, dict]:
        """Simulate samples ``n0 .. n0+n-1`` (absolute indices from ``t0``).

        Returns
        -------
        Telemetry
            The chunk's telemetry.
        dict
            Truth arrays: ``ttl``, ``coefficients``, ``angular_velocity/phi|eta`` and, if
            asked in the config, ``noises/<name>``.  True angles need the running
            integral and are added by :meth:`chunks`.
        """
        cfg = self.config
        fs = cfg.fs
        t = cfg.t0 + (n0 + np.arange(n)) / fs
        ltt = self.orbit.ltt(t)
        h = self._history(ltt, fs)
        e0, e1 = n0 - h, n0 + n
        t_ext = cfg.t0 + np.arange(e0, e1) / fs

        # angular velocities of the total MOSA angles (rad/s), with history for delays
        # (and LOOKAHEAD samples past the chunk, for injections that read ahead)
        ea = e1 + LOOKAHEAD if cfg.injections else e1
        sc = self._get("sc_jitter", e0, ea, 9).reshape(3, 3, -1)[self._sc_of_mosa]
        phi_dot = sc[:, 0] + self._get("mosa_jitter_phi", e0, ea, 6)
        eta_dot = self._cos * sc[:, 1] - self._sin * sc[:, 2] + self._get("mosa_jitter_eta", e0, ea, 6)
        phi_ahead, eta_ahead = phi_dot[:, h + n :], eta_dot[:, h + n :]
        phi_dot, eta_dot = phi_dot[:, : h + n], eta_dot[:, : h + n]

        coeffs = cfg.coefficients.values(t_ext)
        # D_ij for each link, shared by the TTL Tx terms and the remote test masses
        taps = [shift_taps(-ltt[k] * fs, n, cfg.interpolation_order, offset=h) for k in range(6)]

        def delayed_onto_links(x):  # x: (6 MOSAs/TMs, h + n) -> D_ij x_ji on each link ij
            return np.stack([apply_taps(x[REVERSED_INDEX[k]], taps[k]) for k in range(6)])

        if cfg.noises.ttl:
            rx = coeffs[self._rx[0], h:] * phi_dot[:, h:] + coeffs[self._rx[1], h:] * eta_dot[:, h:]
            tx_source = coeffs[self._tx[0]] * phi_dot + coeffs[self._tx[1]] * eta_dot
            ttl = -(rx + delayed_onto_links(tx_source)) / C
        else:
            ttl = np.zeros((6, n))

        dws_noise = self._get("dws", n0, n0 + n, 12)
        delta = self._get("test_mass", e0, e1, 6)
        components = {
            "laser": self.laser_terms(n0, n) if cfg.noises.laser else np.zeros((6, n)),
            "oms": self._get("oms", n0, n0 + n, 6),
            "backlink": self._get("backlink", n0, n0 + n, 6),
            "telescope": self._get("telescope", n0, n0 + n, 6),
            "test_mass": delta[:, h:] + delayed_onto_links(delta),
        }
        eta = ttl + sum(components.values())
        injected = {}
        if cfg.injections:
            ctx = ChunkContext(
                n0=n0,
                n=n,
                h=h,
                fs=fs,
                t=t,
                t_ext=t_ext,
                ltt=ltt,
                orbit=self.orbit,
                phi_dot=phi_dot,
                eta_dot=eta_dot,
                coefficients=coeffs,
                delayed_onto_links=delayed_onto_links,
                interpolation_order=cfg.interpolation_order,
                phi_dot_ahead=phi_ahead,
                eta_dot_ahead=eta_ahead,
                coefficients_ahead=cfg.coefficients.values(cfg.t0 + np.arange(e1, ea) / fs),
            )
            for inj in cfg.injections:
                injected[inj.name] = check_signal(inj, inj.link_signal(ctx), n)
                eta = eta + injected[inj.name]
        tm = Telemetry(
            t0=float(t[0]),
            fs=fs,
            eta=eta,
            dws_phi=phi_dot[:, h:] + dws_noise[:6],
            dws_eta=eta_dot[:, h:] + dws_noise[6:],
            ltt=ltt,
            config=cfg.to_dict(),
            source="simulation",
        )
        truth = {
            "ttl": ttl,
            "coefficients": coeffs[:, h:],
            "angular_velocity/phi": phi_dot[:, h:],
            "angular_velocity/eta": eta_dot[:, h:],
        }
        components["dws_phi"], components["dws_eta"] = dws_noise[:6], dws_noise[6:]
        for name in cfg.truth_noises:
            truth[f"noises/{name}"] = components[name]
        for name, values in injected.items():
            truth[f"injections/{name}"] = values
        return tm, truth

    def chunks(self, chunk_size: int | None = None) -> Iterator[tuple[Telemetry, dict]]:
        """Iterate over the whole mission in chunks of ``chunk_size`` samples (default 3 h).

        Truth gains ``angles/phi|eta``: the running integral of the true angular
        velocities from zero at ``t0`` (rectangle rule, continuous across chunks).
        """
        chunk_size = int(chunk_size or round(3 * 3600 * self.config.fs))
        angle = {"phi": np.zeros(6), "eta": np.zeros(6)}
        for n0 in range(0, self.size, chunk_size):
            n = min(chunk_size, self.size - n0)
            tm, truth = self.chunk(n0, n)
            for a in ("phi", "eta"):
                integral = angle[a][:, None] + np.cumsum(truth[f"angular_velocity/{a}"], axis=1) / self.config.fs
                truth[f"angles/{a}"] = integral
                angle[a] = integral[:, -1]
            yield tm, truth


@dataclass(frozen=True)
class _Jitter:
    """Angle ASD ``level * sqrt(1 + (fknee/f)^4) / sqrt(1 + (f/fhigh)^4)`` [rad/sqrt(Hz)]:
    white between the knees, ``f^-2`` below ``fknee`` and, with ``fhigh``, ``f^-2`` above it
    (picklable)."""

    level: float
    fknee: float
    fhigh: float | None = None

    def __call__(self, f):
        f = np.asarray(f, dtype=float)
        asd = self.level * np.sqrt(1 + (self.fknee / f) ** 4)
        return asd if self.fhigh is None else asd / np.sqrt(1 + (f / self.fhigh) ** 4)


@dataclass(frozen=True)
class _White:
    """White angle ASD [rad/sqrt(Hz)] (picklable)."""

    level: float

    def __call__(self, f):
        return np.full(np.shape(f), self.level, dtype=float)


def simulate(config: SimulationConfig, chunk_size: int | None = None) -> tuple[Telemetry, dict]:
    """Simulate in memory; returns the telemetry and a dict of truth arrays.

    Convenient for notebooks and tests; use :func:`simulate_to_file` for long missions.
    """
    sim = Simulator(config)
    parts = list(sim.chunks(chunk_size))
    tms = [p[0] for p in parts]
    tm = Telemetry(
        t0=tms[0].t0,
        fs=config.fs,
        eta=np.concatenate([x.eta for x in tms], axis=1),
        dws_phi=np.concatenate([x.dws_phi for x in tms], axis=1),
        dws_eta=np.concatenate([x.dws_eta for x in tms], axis=1),
        ltt=np.concatenate([x.ltt for x in tms], axis=1),
        config=config.to_dict(),
        source="simulation",
    )
    truth = {key: np.concatenate([p[1][key] for p in parts], axis=1) for key in parts[0][1]}
    return tm, truth


def simulate_to_file(
    config: SimulationConfig, out, *, chunk_size: int | None = None, progress: Callable[[int, int], None] | None = None
):
    """Simulate chunk by chunk into ``out`` and its truth file ``out.truth.h5``.

    Both files are written atomically (temporary name, then rename); memory stays bounded
    by one chunk.  ``progress(done_samples, total_samples)`` is called after each chunk.

    Returns
    -------
    (Path, Path)
        The telemetry and truth paths.
    """
    sim = Simulator(config)
    cfg_dict = config.to_dict()
    cfg_dict["orbit_description"] = sim.orbit.describe()
    tpath = truth_path(out)
    with (
        TelemetryWriter(out, t0=config.t0, fs=config.fs, size=sim.size, config=cfg_dict) as tw,
        TruthWriter(
            tpath,
            t0=config.t0,
            fs=config.fs,
            size=sim.size,
            config=cfg_dict,
            noises=config.truth_noises,
            injections=[inj.name for inj in config.injections],
        ) as rw,
    ):
        done = 0
        for tm, truth in sim.chunks(chunk_size):
            tw.append_telemetry(tm)
            for key, values in truth.items():
                rw.append(key, values)
            done += tm.size
            if progress is not None:
                progress(done, sim.size)
    return tw.path, rw.path

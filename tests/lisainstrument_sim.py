"""Run lisainstrument (2.x) to make reference measurement files, for tests and benchmarks.

lisainstrument is a *test* dependency: only this helper (and what imports it) may import it.

How noises are switched off in lisainstrument 2.3 (``lisainstrument/instrument.py``):
``Instrument.disable_clock_noise()`` zeroes the clock ASDs *and* the clock offsets, frequency
offsets and drifts; ``disable_modulation_noise()``, ``disable_ranging_noises()`` (ASDs and
biases), ``disable_laser_noise()``, ``disable_oms_noise()`` (all six interferometers),
``disable_testmass_noise()``, ``disable_backlink_noise()``,
``disable_reciprocal_backlink_noise()``, ``disable_angular_jitters()`` (SC and MOSA),
``disable_longitudinal_jitters()``, ``disable_dws_noise()``; ``disable_all_noises(excluding=
[...])`` calls all of them but the excluded.  They only set ASDs to zero, so they must be
called before ``export_hdf5`` (which builds and runs the stream graph).  TTL has no disabler:
it is switched off by zero coefficients.

Usage::

    from lisainstrument_sim import simulate_lisainstrument
    info = simulate_lisainstrument("m.h5", duration=3600, orbits="keplerian")
"""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path

#: Jitter ASDs of docs/physics.md [rad/sqrt(Hz)]: SC (phi, eta, theta) and MOSA (phi, eta).
SC_JITTER_ASDS = (5e-9, 5e-9, 5e-9)
MOSA_JITTER_ASDS = (2e-9, 1e-9)
#: lisainstrument's default DWS noise, 70/335 nrad/sqrt(Hz) (as docs/physics.md).
DWS_ASD = 7e-8 / 335
#: Margin lisainstrument adds to the orbit file's t0 when ``t0="orbits"`` [s].
ORBIT_T0_MARGIN = 75.0

MOSAS = ("12", "23", "31", "13", "32", "21")


def lisainstrument_ttl_coeffs(ttl_coeffs):
    """Translate a TTL coefficient choice into lisainstrument's ``ttl_coeffs`` argument.

    ``"default"`` / ``"random"`` pass through; a number sets all 24 coefficients (m/rad, the
    paper's 2.3 mm/rad case is ``2.3e-3``); a dict with our flat names
    ``"<mosa>.<phi|eta>.<rx|tx>"`` maps ``rx`` to lisainstrument's *local* and ``tx`` to its
    *distant* coefficient of the same MOSA; a 4-tuple of dicts passes through.
    """
    if isinstance(ttl_coeffs, str) or isinstance(ttl_coeffs, tuple):
        return ttl_coeffs
    if isinstance(ttl_coeffs, (int, float)):
        c = {m: float(ttl_coeffs) for m in MOSAS}
        return (dict(c), dict(c), dict(c), dict(c))
    if isinstance(ttl_coeffs, dict):
        out = []
        for angle, side in (("phi", "rx"), ("phi", "tx"), ("eta", "rx"), ("eta", "tx")):
            out.append({m: float(ttl_coeffs[f"{m}.{angle}.{side}"]) for m in MOSAS})
        return tuple(out)
    raise ValueError(f"bad ttl_coeffs {ttl_coeffs!r}")


def keplerian_orbit_file(path, *, duration: float, t0: float = 0.0) -> Path:
    """Write a lisaorbits Keplerian orbit file covering what lisainstrument needs.

    lisainstrument samples the orbits on its telemetry grid too (one sample a day by
    default, from t0 to ``t0 + (1 + ceil(duration / 1 day))`` days, the "PHYSICS_EXT"
    range), so the file spans that plus margins, sampled every hour (cheap: a few ms).
    """
    import math

    import lisaorbits

    path = Path(path)
    dt = 3600.0
    span = (1 + math.ceil(duration / 86400.0)) * 86400.0 + 6 * 3600.0
    size = int(span // dt) + 2
    lisaorbits.KeplerianOrbits().write(str(path), dt=dt, size=size, t0=t0, mode="w")
    return path


def simulate_lisainstrument(
    path,
    *,
    duration: float = 3600,
    fs: float = 4.0,
    orbits: str = "static",
    ttl: bool = True,
    jitter: bool = True,
    dws_noise: bool = True,
    laser: bool = True,
    oms: bool = True,
    testmass: bool = True,
    backlink: bool = True,
    reciprocal_backlink: bool = True,
    longitudinal_jitter: bool = True,
    clock: bool = False,
    modulation: bool = False,
    ranging: bool = False,
    seed: int = 1,
    ttl_coeffs="default",
    sc_jitter_asds=SC_JITTER_ASDS,
    mosa_jitter_asds=MOSA_JITTER_ASDS,
    keep_all: bool = False,
    t0: float | None = None,
    lock: str = "N1-12",
) -> dict:
    """Run lisainstrument and write its measurement file with its own writer.

    Parameters
    ----------
    path : str or Path
        Output file (overwritten).
    duration : float
        Seconds of measurements at ``fs`` (default 4 Hz).
    orbits : str
        ``"static"`` (lisainstrument's fixed PPRs, unequal arms around 8.3 s),
        ``"keplerian"`` (a lisaorbits Keplerian orbit file is written beside ``path``,
        ``<stem>-orbits.h5``; delays then vary in time, exercising the Doppler terms),
        or the path of an existing orbit file.
    ttl, jitter, dws_noise, laser, oms, testmass, backlink, reciprocal_backlink,
    longitudinal_jitter, clock, modulation, ranging : bool
        Which effects are on.  Clock, modulation and ranging noises are off by default
        (the eta/TDI pipeline does not correct them); everything else follows
        lisainstrument's "realistic" defaults, with the jitter ASDs of docs/physics.md.
    seed : int
        lisainstrument's random seed.
    ttl_coeffs
        See :func:`lisainstrument_ttl_coeffs`; ignored (all zero) when ``ttl`` is False.
    keep_all : bool
        Also write lisainstrument's debug datasets (much bigger file).
    t0 : float, optional
        Start time; default 0 for static orbits, the orbit file's t0 + 75 s otherwise.
    lock : str
        lisainstrument's locking configuration: ``"N1-12"`` (default, one primary laser,
        the others offset-locked) or ``"six"`` (six lasers on cavities, so that an effect
        entering one beam stays in that beam's beat note).

    Returns
    -------
    dict
        ``path``, ``orbit_file`` (or None), ``wall_time_s`` and the ``settings`` used.
    """
    from lisainstrument import Instrument

    path = Path(path)
    started = time.perf_counter()
    orbit_file = None
    if orbits == "static":
        orbit_arg = "static"
        t0_arg = 0.0 if t0 is None else float(t0)
    else:
        if orbits == "keplerian":
            orbit_file = keplerian_orbit_file(path.with_name(f"{path.stem}-orbits.h5"), duration=duration)
        else:
            orbit_file = Path(orbits)
        orbit_arg = str(orbit_file)
        t0_arg = "orbits" if t0 is None else float(t0)

    coeffs = lisainstrument_ttl_coeffs(ttl_coeffs) if ttl else lisainstrument_ttl_coeffs(0.0)
    size = int(round(duration * fs))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        logging.getLogger("lisainstrument").setLevel(logging.ERROR)
        instrument = Instrument(
            size=size,
            dt=1.0 / fs,
            t0=t0_arg,
            seed=int(seed),
            orbits=orbit_arg,
            ttl_coeffs=coeffs,
            sc_angular_jitter_asds=tuple(float(a) for a in sc_jitter_asds),
            mosa_angular_jitter_asds=tuple(float(a) for a in mosa_jitter_asds),
            dws_asds=DWS_ASD,
            lock=lock,
        )
        switches = {
            "clock": (clock, instrument.disable_clock_noise),
            "modulation": (modulation, instrument.disable_modulation_noise),
            "ranging": (ranging, instrument.disable_ranging_noises),
            "laser": (laser, instrument.disable_laser_noise),
            "oms": (oms, instrument.disable_oms_noise),
            "testmass": (testmass, instrument.disable_testmass_noise),
            "backlink": (backlink, instrument.disable_backlink_noise),
            "reciprocal_backlink": (reciprocal_backlink, instrument.disable_reciprocal_backlink_noise),
            "jitter": (jitter, instrument.disable_angular_jitters),
            "longitudinal_jitter": (longitudinal_jitter, instrument.disable_longitudinal_jitters),
            "dws_noise": (dws_noise, instrument.disable_dws_noise),
        }
        for _, (keep, disable) in switches.items():
            if not keep:
                disable()
        instrument.export_hdf5(str(path), overwrite=True, keep_all=keep_all)
    settings = {name: bool(keep) for name, (keep, _) in switches.items()}
    settings.update(
        ttl=bool(ttl),
        duration=float(duration),
        fs=float(fs),
        orbits=str(orbits),
        seed=int(seed),
        lock=lock,
        ttl_coeffs=ttl_coeffs if isinstance(ttl_coeffs, (str, int, float)) else "custom",
    )
    return {
        "path": path,
        "orbit_file": orbit_file,
        "wall_time_s": time.perf_counter() - started,
        "settings": settings,
    }


if __name__ == "__main__":  # quick timing: python tests/lisainstrument_sim.py OUT.h5 [duration] [orbits]
    import sys

    out = sys.argv[1]
    dur = float(sys.argv[2]) if len(sys.argv) > 2 else 3600.0
    orb = sys.argv[3] if len(sys.argv) > 3 else "static"
    info = simulate_lisainstrument(out, duration=dur, orbits=orb)
    print(f"{dur:g} s of lisainstrument data ({orb} orbits) in {info['wall_time_s']:.1f} s -> {out}")

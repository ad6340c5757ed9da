"""Read lisainstrument 2.x measurement files directly.

lisainstrument (the LISA consortium's instrument simulator) writes one HDF5 file per run
with :meth:`lisainstrument.Instrument.export_hdf5`.  This module turns such a file into a
:class:`~ttlcore.io.telemetry.Telemetry` without importing lisainstrument or pytdi (they are
test dependencies only): it reads the beat notes, reduces them to the six ``eta_ij``
variables exactly as pytdi does, and takes the DWS readouts and the delays as they are.

File layout (lisainstrument 2.0 to 2.3; the four writers
``lisainstrument/instru/instru_store_v2_{0,1,2}_0.py`` and ``instru_store.py`` differ only in
datasets and metadata this module does not use):

- Root attributes: ``version`` and ``version_format`` (the package version that wrote the
  file, e.g. ``"2.3.0"``), ``git_url`` (``https://gitlab.in2p3.fr/lisa-simulation/instrument``),
  optional ``description``, and ``metadata_json``: one JSON object holding every simulation
  parameter (``dt``, ``fs``, ``size``, ``t0``, ``central_freq``, noise ASDs, TTL coefficients,
  orbit file, ...).
- One dataset per quantity and MOSA, ``<quantity>/<mosa>`` for quantities lisainstrument
  calls "actual" (available in flight) and ``debug/<quantity>/<mosa>`` for the others.
  Each dataset has attributes ``index_start``/``index_stop`` (its sample range, ``0`` and
  ``size`` for the measurement rate); a *constant* series is stored as a scalar dataset.
- Used here (all at the measurement rate ``fs = 1/dt``):

  ==================================  ==========================================  =======
  dataset                             what                                        unit
  ==================================  ==========================================  =======
  ``debug/sci_carrier_fluctuations``  inter-spacecraft IFO carrier beat note,     Hz
                                      frequency fluctuations
  ``debug/tmi_carrier_fluctuations``  test-mass IFO carrier fluctuations          Hz
  ``debug/ref_carrier_fluctuations``  reference IFO carrier fluctuations          Hz
  ``mprs``                            measured pseudo-ranges (delays)             s
  ``sci_dws_phis``, ``sci_dws_etas``  DWS readouts of the MOSA angles             rad/s
  ==================================  ==========================================  =======

  These are exactly the datasets pytdi 2.2.1 uses for files of version >= 2.0
  (``pytdi.interface.Data._from_instrument_file`` with ``signals="fluctuations"``: the
  ``debug`` group for the beat notes, ``mprs`` at the root for the delays).

Reduction to ``eta`` (pytdi ``intervar.ETA_SET = ETA_ij_XI @ XI_SET``, evaluated by
``pytdi.intervar.compute_etas`` with ``unit="frequency"``)::

    eta_12 = sci_12 + ref_12/2 - tmi_12/2 + (1 - d'_12) D_12[ref_21 - ref_23/2 - tmi_21/2]
    eta_13 = sci_13 + ref_12/2 - tmi_13/2 + (1 - d'_13) D_13[ref_31/2 - tmi_31/2]

and cyclic permutations (1->2->3->1): 23, 31 follow 12; 21, 32 follow 13.  ``D_ij`` is the
delay by the MPR ``d_ij`` (Lagrange interpolation of order ``order``), and ``(1 - d'_ij)`` is
pytdi's Doppler factor for *frequency* data (``pytdi.core``: each term is multiplied by
``1 + derivative`` of its total shift, the shift of ``D_ij`` being ``-d_ij``), with
``d'_ij = numpy.gradient(d_ij, 1/fs)`` as ``Data.compute_delay_derivatives`` computes it.
The eta variables contain single delays only (no nested ``D_ij D_jk``), so pytdi's
``delay_order`` (the interpolation order of delays *of delays*) plays no role here; it is
accepted and validated for symmetry with pytdi's ``compute_etas``.  The result, in Hz, is
divided by the file's ``central_freq`` (nu0) to give fractional frequency.

Leading samples: a delayed term at sample ``k`` needs the beat notes at
``k - d_ij fs - order/2`` and earlier, which the file does not hold for the first
``ceil(d_ij fs) + (order - 1)/2`` samples or so (49 samples, 12 s, at 4 Hz with 8.3 s delays
and order 31).  pytdi zero-pads the data there (``pytdi.dsp.timeshift`` uses ``np.pad`` with
zeros), so its first samples are finite but wrong.  We evaluate them as NaN instead and
**drop** them (and any trailing ones, none in practice) from every series, moving ``t0``
forward accordingly; the number dropped is ``config["dropped_leading_samples"]``.  They are
found from the delays alone (where the stencil of ``D_ij`` leaves the file), so that a gap at
the start of the file stays a gap and does not move ``t0``.

Gaps: NaN in a dataset is missing data (lisa-gap's masks with ``treat_as_nan=True`` multiply
the series by NaN over a gap), read as a gap in the telemetry, as our own files are
(:meth:`~ttlcore.io.telemetry.Telemetry.missing`); an infinity stays an error naming the dataset.

- A NaN beat-note sample makes NaN every eta sample that depends on it: an undelayed term at
  the same sample, a delayed one wherever its interpolation stencil covers the sample, that
  is one delay later, widened by the stencil.  A gap ``[a, b)`` in every beat note is
  therefore missing from ``eta`` over ``[a, b + ceil(d fs) + (order - 1)/2)``: it grows by
  the delay (~8.3 s) plus the interpolation half-stencil, 49 samples (12.25 s) at 4 Hz with
  order 31 (:func:`gap_reach`).
- A NaN DWS sample is NaN in the DWS readout, no more.
- A NaN MPR sample is filled for the light travel times, which must stay finite (the MPRs
  are smooth: linear interpolation across the gap), and ``eta_ij`` is NaN where its delay
  or Doppler factor reads the missing sample (the MPR's gap and one sample each side).
- The gaps are recorded in ``config["gaps"]``: the telemetry's missing samples and their
  spans [s], how far a gap spreads, and the NaN of each dataset of the file; a file with no
  complete sample at all is refused.

Conventions verified in lisainstrument 2.3's source (``instru/instru_model.py``,
``instru/instru_formulas.py``):

- TTL sign: ``carrier_fluctuations = local - (nu0 + offset) (distant_ttls - x)/c`` is what
  MOSA ``ji`` emits; it is delayed by ``pprs[ij]`` to MOSA ``ij`` (``_lock_on_distant`` and
  friends: ``self.distant_ttls[mosa.distant.value]`` delayed by ``self.pprs[mosa.value]``),
  where ``distant_carrier_fluctuations = propagated - nu (local_ttls_ij - x)/c`` and
  ``sci = distant - local``.  ``local_ttls = C_local_phi * phidot + C_local_eta * etadot``
  with the angular *velocities* (``NoiseDefAngularJitter`` generates rad/s), so in the sci
  beat note, in fractional frequency, ``ttl_ij = -(1/c)[C_rx,ij . angdot_ij +
  D_ij(C_tx,ji . angdot_ji)]`` -- the sign convention of docs/physics.md.
- Coefficient indexing: lisainstrument's ``distant`` coefficient of MOSA ``ij`` multiplies
  MOSA ``ij``'s own jitter (``distant_ttls[ij]`` uses ``mosa_total_jitter_*[ij]``) and reaches
  the receiver through link ``ji`` (the beam MOSA ``ij`` sends).  It is therefore our
  ``ij.*.tx`` (coefficients indexed by the MOSA whose jitter they multiply); its ``local``
  coefficient of MOSA ``ij`` multiplies MOSA ``ij``'s jitter on link ``ij``: our ``ij.*.rx``.
- DWS readouts: ``tps_sci_dws_phis = mosa_total_jitter_phis + dws_phi_noises`` (same for
  eta), so the ``sci_dws_*`` datasets *include* the DWS noise (``dws_asds``, an angle ASD,
  generated as a violet angular-velocity noise by ``NoiseDefDWS``); they are the MOSA total
  angular velocities (``phi = phi_SC + phi_MOSA``, ``eta = cos(a) eta_SC - sin(a) theta_SC +
  eta_MOSA``) in rad/s, undelayed, filtered and decimated like the beat notes.
"""

# size: one reader of one outside format: lisainstrument 2.x's layouts, units, clock and orbit
# conventions and its truth, kept together so that a change of that format is one module's change.

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import h5py
import numpy as np

from .._lagrange import Taps, apply_taps, shift_taps
from ..conventions import COEFFICIENT_NAMES, LINKS, MOSAS
from ..errors import TelemetryError
from .telemetry import Telemetry, bridged_ltt

#: ``git_url`` root attribute that lisainstrument writes.
GIT_URL_MARK = "lisa-simulation/instrument"
#: Supported major version of the file format.
SUPPORTED_MAJOR = 2

#: Beat-note datasets (carrier frequency fluctuations, Hz), keyed by interferometer.
BEATNOTE_DATASETS: dict[str, str] = {
    "sci": "debug/sci_carrier_fluctuations",
    "tmi": "debug/tmi_carrier_fluctuations",
    "ref": "debug/ref_carrier_fluctuations",
}
#: Measured pseudo-ranges, used as delays [s].
MPR_DATASET = "mprs"
#: DWS readouts [rad/s].
DWS_PHI_DATASET = "sci_dws_phis"
DWS_ETA_DATASET = "sci_dws_etas"

#: Metadata keys of lisainstrument's TTL coefficients -> our (angle, side).
TTL_METADATA_KEYS: dict[str, tuple[str, str]] = {
    "ttl_coeffs_local_phis": ("phi", "rx"),
    "ttl_coeffs_distant_phis": ("phi", "tx"),
    "ttl_coeffs_local_etas": ("eta", "rx"),
    "ttl_coeffs_distant_etas": ("eta", "tx"),
}

#: The eta reduction, pytdi's ``ETA_SET`` after simplification:
#: link -> (undelayed terms, terms delayed by D_link), each term ``(measurement, factor)``.
ETA_TERMS: dict[str, tuple[tuple[tuple[str, float], ...], tuple[tuple[str, float], ...]]] = {
    "12": ((("sci_12", 1.0), ("ref_12", 0.5), ("tmi_12", -0.5)), (("ref_21", 1.0), ("ref_23", -0.5), ("tmi_21", -0.5))),
    "23": ((("sci_23", 1.0), ("ref_23", 0.5), ("tmi_23", -0.5)), (("ref_32", 1.0), ("ref_31", -0.5), ("tmi_32", -0.5))),
    "31": ((("sci_31", 1.0), ("ref_31", 0.5), ("tmi_31", -0.5)), (("ref_13", 1.0), ("ref_12", -0.5), ("tmi_13", -0.5))),
    "13": ((("sci_13", 1.0), ("ref_12", 0.5), ("tmi_13", -0.5)), (("ref_31", 0.5), ("tmi_31", -0.5))),
    "32": ((("sci_32", 1.0), ("ref_31", 0.5), ("tmi_32", -0.5)), (("ref_23", 0.5), ("tmi_23", -0.5))),
    "21": ((("sci_21", 1.0), ("ref_23", 0.5), ("tmi_21", -0.5)), (("ref_12", 0.5), ("tmi_12", -0.5))),
}

#: Output samples evaluated per interpolation block (bounds memory for long files).
_BLOCK = 1 << 16
#: At most this many spans are listed per entry of ``config["gaps"]`` (the count is always whole).
MAX_LISTED_SPANS = 1000


# ---------------------------------------------------------------------------
# Detection
# ---------------------------------------------------------------------------


def _str_attr(f: h5py.File, name: str) -> str | None:
    value = f.attrs.get(name)
    if value is None:
        return None
    if isinstance(value, bytes):
        value = value.decode(errors="replace")
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
        if isinstance(value, bytes):
            value = value.decode(errors="replace")
    return value if isinstance(value, str) else None


def is_lisainstrument(f: h5py.File) -> bool:
    """Whether the open HDF5 file ``f`` is a lisainstrument measurement file.

    True when the root has a ``version`` attribute and either lisainstrument's ``git_url``,
    the 2.x ``metadata_json`` attribute with the ``mprs`` group, or the ``mprs`` dataset of
    1.x files.  Files of unsupported versions (1.x) are recognised too, so that
    :func:`read_lisainstrument` can say why it rejects them.  Never raises.
    """
    try:
        if _str_attr(f, "version") is None and _str_attr(f, "version_format") is None:
            return False
        url = _str_attr(f, "git_url") or ""
        if GIT_URL_MARK in url:
            return True
        if "metadata_json" in f.attrs and MPR_DATASET in f:
            return True
        return MPR_DATASET in f and ("isi_carrier_fluctuations" in f or "isc_carrier_fluctuations" in f)
    except Exception:  # noqa: BLE001 - detection must not fail on odd files
        return False


def _parse_version(text: str) -> tuple[int, int] | None:
    m = re.match(r"^\s*v?(\d+)\.(\d+)", text)
    return (int(m.group(1)), int(m.group(2))) if m else None


# ---------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------


def _open(path: Path) -> h5py.File:
    if not path.exists():
        raise TelemetryError(path, "no such file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise TelemetryError(
            path, f"not a readable HDF5 file ({exc.__class__.__name__}: {exc}); truncated or corrupt?"
        ) from None


class _Metadata:
    """Checked access to the ``metadata_json`` root attribute."""

    def __init__(self, path: Path, f: h5py.File):
        self.path = path
        text = _str_attr(f, "metadata_json")
        if text is None:
            raise TelemetryError(
                path, "missing root attribute (lisainstrument 2.x files carry their metadata there)", "@metadata_json"
            )
        try:
            self.data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise TelemetryError(path, f"metadata is not valid JSON ({exc})", "@metadata_json") from None
        if not isinstance(self.data, dict):
            raise TelemetryError(path, "metadata is not a JSON object", "@metadata_json")

    def where(self, key: str) -> str:
        return f"@metadata_json[{key}]"

    def number(self, key: str, *, positive: bool = False) -> float:
        if key not in self.data:
            raise TelemetryError(self.path, "missing metadata entry", self.where(key))
        value = self.data[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TelemetryError(self.path, f"expected a number, got {value!r}", self.where(key))
        value = float(value)
        if not math.isfinite(value):
            raise TelemetryError(self.path, f"must be finite, got {value}", self.where(key))
        if positive and value <= 0:
            raise TelemetryError(self.path, f"must be positive, got {value:g}", self.where(key))
        return value

    def integer(self, key: str) -> int:
        value = self.number(key)
        if value != int(value) or value <= 0:
            raise TelemetryError(self.path, f"must be a positive integer, got {self.data[key]!r}", self.where(key))
        return int(value)


def _sampling(path: Path, meta: _Metadata) -> tuple[float, float, int, float]:
    """``(t0, fs, size, central_freq)`` from the metadata, cross-checked."""
    dt = meta.number("dt", positive=True)
    fs = 1.0 / dt
    if "fs" in meta.data:
        fs_meta = meta.number("fs", positive=True)
        if abs(fs_meta * dt - 1.0) > 1e-9:
            raise TelemetryError(
                path, f"sampling frequency {fs_meta:g} Hz disagrees with dt = {dt:g} s", meta.where("fs")
            )
        fs = fs_meta
    size = meta.integer("size")
    if "duration" in meta.data:
        duration = meta.number("duration", positive=True)
        if abs(duration - size * dt) > 1e-6 * max(1.0, duration):
            raise TelemetryError(
                path, f"duration {duration:g} s disagrees with size * dt = {size * dt:g} s", meta.where("duration")
            )
    t0 = meta.number("t0")
    nu0 = meta.number("central_freq", positive=True)
    return t0, fs, size, nu0


class _DatasetReader:
    """Read ``<group>/<mosa>`` datasets, checking them against the expected sample range."""

    def __init__(self, path: Path, f: h5py.File, size: int):
        self.path = path
        self.f = f
        self.size = size
        self.range: tuple[int, int] | None = None  # (index_start, index_stop) shared by all
        self.missing: dict[str, np.ndarray] = {}  # dataset -> where its samples are NaN (gaps)

    def read(self, group: str, mosa: str) -> np.ndarray:
        """The samples of ``<group>/<mosa>`` (a scalar broadcast to ``size``); NaN is a gap
        (recorded in ``missing``).  TelemetryError naming the dataset when it is missing,
        not real, of another length or sample range, unreadable or infinite."""
        name = f"{group}/{mosa}"
        ds = self._dataset(group, name)
        rng = self._range(ds, name)
        try:
            data = np.asarray(ds[()], dtype=float)
        except (OSError, RuntimeError, ValueError) as exc:
            raise TelemetryError(self.path, f"cannot read data ({exc}); truncated file?", name) from None
        if data.shape == ():
            data = np.full(self.size, float(data))
        infinite = np.isinf(data)
        if infinite.any():
            raise TelemetryError(self.path, f"infinite values (first at sample {int(np.argmax(infinite))})", name)
        missing = np.isnan(data)
        if missing.any():  # a gap in the data (lisa-gap's treat_as_nan): no sample there
            self.missing[name] = missing
        if self.range is None:
            self.range = rng
        elif rng != self.range:
            raise TelemetryError(
                self.path, f"sample range {rng} differs from that of the other datasets {self.range}", name
            )
        return data

    def _dataset(self, group: str, name: str) -> h5py.Dataset:
        """The dataset ``name`` (in ``group``), checked to hold ``size`` real numbers or one."""
        if group not in self.f:
            raise TelemetryError(self.path, "missing dataset group", group)
        if name not in self.f:
            raise TelemetryError(self.path, "missing dataset", name)
        ds = self.f[name]
        if not isinstance(ds, h5py.Dataset):
            raise TelemetryError(self.path, "expected a dataset, found a group", name)
        if ds.dtype.kind not in "fiu":
            raise TelemetryError(self.path, f"expected real numbers, found dtype {ds.dtype}", name)
        if ds.shape not in ((), (self.size,)):
            raise TelemetryError(
                self.path,
                f"expected shape ({self.size},) from metadata size (or a scalar for a constant series), found {ds.shape}",
                name,
            )
        return ds

    def _range(self, ds: h5py.Dataset, name: str) -> tuple[int, int]:
        attrs = ds.attrs
        if "index_start" not in attrs and "index_stop" not in attrs:
            return (0, self.size)
        try:
            start, stop = int(attrs["index_start"]), int(attrs["index_stop"])
        except (KeyError, TypeError, ValueError):
            raise TelemetryError(
                self.path, "bad or incomplete index_start/index_stop attributes", f"{name}@index_start"
            ) from None
        if stop - start != self.size:
            raise TelemetryError(
                self.path,
                f"sample range [{start}, {stop}) holds {stop - start} samples, metadata size is {self.size}",
                f"{name}@index_stop",
            )
        return (start, stop)


def _check_order(order, what: str) -> int:
    if isinstance(order, bool) or int(order) != order or order < 1 or int(order) % 2 == 0:
        raise ValueError(f"{what} must be a positive odd integer, got {order!r}")
    return int(order)


def _delayed(x: np.ndarray, shift: np.ndarray, order: int) -> np.ndarray:
    """``x(k + shift[k])`` by Lagrange interpolation, NaN where the stencil leaves the data.

    Evaluated in blocks of output samples, so that the taps (``order + 1`` weights per
    sample) never need more than a few tens of megabytes.
    """
    n = x.shape[-1]
    out = np.empty(n)
    for a in range(0, n, _BLOCK):
        b = min(a + _BLOCK, n)
        taps = shift_taps(shift[a:b], b - a, order)
        out[a:b] = apply_taps(x, Taps(base=taps.base + a, weights=taps.weights), fill=np.nan)
    return out


def _stencil_inside(d: np.ndarray, fs: float, order: int) -> np.ndarray:
    """Where the stencil of ``D_ij`` (delay ``d`` [s]) lies inside the file's samples.

    The same test as :func:`~ttlcore._lagrange.apply_taps`: sample ``k`` reads
    ``x[base_k .. base_k + order]`` with ``base_k = k + floor(-d[k] fs) - (order - 1)/2``.
    """
    n = d.size
    base = np.arange(n, dtype=np.int64) + np.floor(-d * fs).astype(np.int64) - (order - 1) // 2
    return (base >= 0) & (base + order + 1 <= n)


def _stretches(mask: np.ndarray) -> list[list[int]]:
    """Sample ranges ``[start, stop)`` where ``mask`` is true."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2])]


def _grown(mask: np.ndarray, before: int, after: int) -> np.ndarray:
    """``mask`` with every true stretch extended by ``before`` and ``after`` samples."""
    out = mask.copy()
    for a, b in _stretches(mask):
        out[max(a - before, 0) : b + after] = True
    return out


def _fill_mpr(path: Path, name: str, d: np.ndarray, missing: np.ndarray) -> np.ndarray:
    """The MPR ``d`` with its missing samples bridged (:func:`ttlcore.io.telemetry.bridged_ltt`:
    a straight line between the valid ones, their trend beyond the first or last).

    MPRs vary smoothly (the arm lengths change by metres per second over 2.5 Gm): across a
    gap of an hour a straight line misses the true delay by nanoseconds, so the light travel
    times stay finite and usable; the eta samples that read the missing MPR are marked
    missing by the caller.
    """
    if missing.all():
        raise TelemetryError(path, "no valid sample (all NaN): the delays cannot be interpolated", name)
    return bridged_ltt(d[None], missing)[0]


def compute_etas_hz(
    beatnotes: dict[str, np.ndarray], mprs: dict[str, np.ndarray], fs: float, order: int = 31
) -> np.ndarray:
    """The six ``eta_ij`` [Hz] from beat-note fluctuations [Hz] and MPRs [s].

    Parameters
    ----------
    beatnotes : dict
        ``"sci_12"``, ``"tmi_12"``, ``"ref_12"``, ... -> arrays of shape ``(n,)`` [Hz].
    mprs : dict
        ``"12"``, ... -> delays ``d_ij`` [s], shape ``(n,)``.
    fs : float
        Sampling frequency [Hz].
    order : int
        Lagrange interpolation order of the delays.

    Returns
    -------
    ndarray, shape (6, n)
        In :data:`~ttlcore.conventions.LINKS` order; NaN where a delayed term needs data
        before the first sample (or after the last), and where a term reads a NaN beat-note
        sample (a gap): an undelayed term at that sample, the delayed term wherever its
        interpolation stencil covers it.  The MPRs must be finite.
    """
    order = _check_order(order, "order")
    n = next(iter(mprs.values())).shape[-1]
    eta = np.empty((6, n))
    for row, link in enumerate(LINKS):
        local, remote = ETA_TERMS[link]
        d = np.asarray(mprs[link], dtype=float)
        # one interpolation per link: delaying is linear, so D(sum a_k x_k) = sum a_k D x_k
        combo = np.zeros(n)
        for name, factor in remote:
            combo += factor * beatnotes[name]
        doppler = 1.0 - np.gradient(d, 1.0 / fs)
        total = doppler * _delayed(combo, -d * fs, order)
        for name, factor in local:
            total += factor * beatnotes[name]
        eta[row] = total
    return eta


def _noise_flags(md: dict) -> dict:
    """Which noises were on, from the ASDs and offsets in the metadata."""

    def on(*keys) -> bool:
        for key in keys:
            value = md.get(key)
            if isinstance(value, dict):
                if any(isinstance(v, (int, float)) and v != 0 for v in value.values()):
                    return True
            elif isinstance(value, (int, float)) and not isinstance(value, bool) and value != 0:
                return True
        return False

    ttl = on(*TTL_METADATA_KEYS) or bool(md.get("ttl_file"))
    return {
        "laser": on("laser_asds"),
        "modulation": on("modulation_asds"),
        "clock": on("clock_asds", "clock_offsets", "clock_freqoffsets", "clock_freqlindrifts", "clock_freqquaddrifts"),
        "testmass": on("testmass_asds"),
        "backlink": on("backlink_asds"),
        "reciprocal_backlink": on("reciprocal_backlink_asds"),
        "oms": on(
            "oms_sci_carrier_asds",
            "oms_sci_usb_asds",
            "oms_tmi_carrier_asds",
            "oms_tmi_usb_asds",
            "oms_ref_carrier_asds",
            "oms_ref_usb_asds",
        ),
        "ranging": on("ranging_asds", "ranging_biases"),
        "angular_jitter": on(
            "sc_jitter_phi_asds",
            "sc_jitter_eta_asds",
            "sc_jitter_theta_asds",
            "mosa_jitter_phi_asds",
            "mosa_jitter_eta_asds",
        ),
        "longitudinal_jitter": on("mosa_jitter_x_asds"),
        "dws": on("dws_asds"),
        "moc_time_correlation": on("moc_time_correlation_asds"),
        "ttl": ttl,
        "gws": bool(md.get("gw_file")),
        "glitches": bool(md.get("glitch_file")),
    }


def _ttl_flat(md: dict) -> dict[str, float] | None:
    """lisainstrument's static TTL coefficients as our flat names [m/rad], or None."""
    blocks: dict = {key: md.get(key) for key in TTL_METADATA_KEYS}
    if not all(isinstance(v, dict) for v in blocks.values()):
        return None
    flat = {}
    for key, (angle, side) in TTL_METADATA_KEYS.items():
        for mosa in MOSAS:
            value = blocks[key].get(mosa)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return None
            flat[f"{mosa}.{angle}.{side}"] = float(value)
    return {name: flat[name] for name in COEFFICIENT_NAMES}


def _config(f: h5py.File, md: dict, *, t0, fs, size, nu0, order, delay_order, dropped, trailing, gaps) -> dict:
    version = _str_attr(f, "version")
    return {
        "source_format": "lisainstrument",
        "lisainstrument_version": version,
        "lisainstrument_format_version": _str_attr(f, "version_format") or version,
        "description": _str_attr(f, "description"),
        "central_freq": nu0,
        "dt": 1.0 / fs,
        "fs": fs,
        "size": size,
        "t0": t0,
        "seed": md.get("seed"),
        "orbits": md.get("orbit_file") or "static",
        "orbit_dataset": md.get("orbit_dataset"),
        "lock_config": md.get("lock_config"),
        "interpolation_order_simulation": md.get("interpolation_order"),
        "noises": _noise_flags(md),
        "ttl_coeffs": _ttl_flat(md),
        "ttl_file": md.get("ttl_file"),
        "mosa_angles": md.get("mosa_angles"),
        "eta_reduction": "pytdi ETA_SET (xi_ij then eta_ij), frequency units with Doppler factors (1 - dd_ij/dt), MPRs as delays",
        "order": order,
        "delay_order": delay_order,
        "dropped_leading_samples": dropped,
        "dropped_trailing_samples": trailing,
        "gaps": gaps,
        # everything else the file says, except the long anti-aliasing filter taps
        "lisainstrument_metadata": {k: v for k, v in md.items() if k != "aafilter_coeffs"},
    }


def read_lisainstrument(path, *, order: int = 31, delay_order: int = 5):
    """Read a lisainstrument 2.x measurement file as :class:`~ttlcore.io.telemetry.Telemetry`.

    Parameters
    ----------
    path : str or Path
        The file written by ``Instrument.export_hdf5`` (or ``Instrument.write``).
    order : int
        Lagrange interpolation order of the delays in the eta reduction (odd; pytdi's
        ``compute_etas(order=...)``).
    delay_order : int
        pytdi's interpolation order for delays of delays (odd).  The eta variables hold
        single delays only, so it does not change the result; validated and recorded.

    Returns
    -------
    Telemetry
        ``eta`` in fractional frequency (Hz / ``central_freq``), DWS readouts in rad/s,
        ``ltt`` = the MPRs in s, ``t0`` moved past the dropped leading samples.  NaN in the
        file is a gap: NaN in the eta samples that depend on it (spread by the delay and
        the interpolation stencil) and in the DWS, MPRs interpolated across; the gaps are
        in ``config["gaps"]`` (module docstring).

    Raises
    ------
    TelemetryError
        Naming the file and the dataset or attribute at fault.
    ValueError
        For a bad ``order`` or ``delay_order``.
    """

    order = _check_order(order, "order")
    delay_order = _check_order(delay_order, "delay_order")
    path = Path(path)
    with _open(path) as f:
        if not is_lisainstrument(f):
            raise TelemetryError(
                path, "not a lisainstrument measurement file (no lisainstrument version/git_url root attributes)"
            )
        _check_version(path, f)
        meta = _Metadata(path, f)
        t0, fs, size, nu0 = _sampling(path, meta)

        reader = _DatasetReader(path, f, size)
        beatnotes = {}
        for ifo, group in BEATNOTE_DATASETS.items():
            for mosa in MOSAS:
                beatnotes[f"{ifo}_{mosa}"] = reader.read(group, mosa)
        mprs = _read_mprs(path, reader)
        dws_phi = np.stack([reader.read(DWS_PHI_DATASET, mosa) for mosa in MOSAS])
        dws_eta = np.stack([reader.read(DWS_ETA_DATASET, mosa) for mosa in MOSAS])
        index_start = reader.range[0] if reader.range else 0
        first, last = _valid_span(path, mprs, fs, order, size)
        eta_hz = compute_etas_hz(beatnotes, mprs, fs, order)
        for row, link in enumerate(LINKS):
            # the delay of D_ij at sample k is d_ij[k] and its Doppler factor the centred
            # gradient of d_ij: a missing MPR sample takes eta_ij at k - 1 .. k + 1
            missing_mpr = reader.missing.get(f"{MPR_DATASET}/{link}")
            if missing_mpr is not None:
                eta_hz[row, _grown(missing_mpr, 1, 1)] = np.nan
        t0_file = t0 + index_start / fs
        sl = slice(first, last)
        eta, dws_phi, dws_eta = eta_hz[:, sl] / nu0, dws_phi[:, sl], dws_eta[:, sl]
        missing = ~(np.isfinite(eta).all(axis=0) & np.isfinite(dws_phi).all(axis=0) & np.isfinite(dws_eta).all(axis=0))
        if missing.all():
            named = ", ".join(sorted(reader.missing)[:3]) + (", ..." if len(reader.missing) > 3 else "")
            raise TelemetryError(
                path,
                f"no valid sample: every sample of the {last - first} misses an eta or DWS value (NaN in {named})",
                next(iter(sorted(reader.missing)), None),
            )
        gaps = _gap_record(reader.missing, missing, mprs, t0_file=t0_file, first=first, fs=fs, order=order)
        config = _config(
            f,
            meta.data,
            t0=t0_file,
            fs=fs,
            size=size,
            nu0=nu0,
            order=order,
            delay_order=delay_order,
            dropped=first,
            trailing=size - last,
            gaps=gaps,
        )
    ltt = np.stack([mprs[m] for m in LINKS])
    return Telemetry(
        t0=t0_file + first / fs,
        fs=fs,
        eta=eta,
        dws_phi=dws_phi,
        dws_eta=dws_eta,
        ltt=ltt[:, sl],
        config=config,
        source=str(path),
    )


def _check_version(path: Path, f: h5py.File) -> None:
    """TelemetryError naming the version attribute unless the file's format is 2.x."""
    version_text = _str_attr(f, "version_format") or _str_attr(f, "version") or ""
    version = _parse_version(version_text)
    attr = "@version_format" if _str_attr(f, "version_format") else "@version"
    if version is None:
        raise TelemetryError(path, f"cannot parse the lisainstrument file version {version_text!r}", attr)
    if version[0] != SUPPORTED_MAJOR:
        raise TelemetryError(
            path,
            f"lisainstrument file format {version_text} is not supported (only 2.x; re-simulate or convert)",
            attr,
        )


def _read_mprs(path: Path, reader: _DatasetReader) -> dict[str, np.ndarray]:
    """The measured pseudo-ranges [s] per MOSA, interpolated across their gaps;
    TelemetryError naming the dataset unless they are positive."""
    raw_mprs = {mosa: reader.read(MPR_DATASET, mosa) for mosa in MOSAS}
    mprs = {}
    for mosa, d in raw_mprs.items():
        name = f"{MPR_DATASET}/{mosa}"
        if name in reader.missing:
            d = _fill_mpr(path, name, d, reader.missing[name])
        if np.any(d <= 0):
            raise TelemetryError(
                path, f"measured pseudo-ranges must be positive delays [s], found min {d.min():g}", name
            )
        mprs[mosa] = d
    return mprs


def _valid_span(path: Path, mprs: dict, fs: float, order: int, size: int) -> tuple[int, int]:
    """The first sample and one past the last whose delayed terms lie inside the file, from
    the delays alone (a gap at the start of the file does not move t0); TelemetryError when
    there is none, or when a sample between them has not."""
    inside = np.all([_stencil_inside(mprs[link], fs, order) for link in LINKS], axis=0)
    if not inside.any():
        raise TelemetryError(
            path,
            f"too short for the eta reduction: no sample has its delayed terms (delays {max(d.max() for d in mprs.values()):.3g} s, order {order})",
            MPR_DATASET,
        )
    first = int(np.argmax(inside))
    last = size - int(np.argmax(inside[::-1]))  # one past the last valid sample
    if not inside[first:last].all():
        bad = first + int(np.argmin(inside[first:last]))
        raise TelemetryError(path, f"eta reduction undefined inside the data (sample {bad}); delays jump?", MPR_DATASET)
    return first, last


def gap_reach(mprs, fs: float, order: int) -> tuple[int, int]:
    """How far a gap in a beat note spreads in ``eta`` [samples before, after it].

    The delayed term of ``eta_ij`` at sample ``k`` reads the beat notes at
    ``k + floor(-d_ij fs) - (order - 1)/2 .. k + floor(-d_ij fs) + (order + 1)/2``, so a gap
    ``[a, b)`` of a delayed beat note takes ``eta_ij`` over
    ``[a + ceil(d fs) - (order + 1)/2, b + ceil(d fs) + (order - 1)/2)``: its image one
    delay later, widened by the interpolation stencil.  Together with the undelayed terms
    (the gap itself), the gap in the eta grows by ``ceil(d fs) + (order - 1)/2`` samples after
    its end (49 at 4 Hz, 8.3 s delays and order 31: 12.25 s) and by
    ``max(0, (order + 1)/2 - ceil(d fs))`` before its start (none for LISA's delays).  A
    gap shorter than ``ceil(d fs) - (order + 1)/2`` samples (18, 4.5 s) leaves two pieces:
    itself and its delayed image.  Returns the largest over the links and the file
    (``mprs``: link -> delays [s]).
    """
    dmax = max(float(np.max(d)) for d in mprs.values())
    dmin = min(float(np.min(d)) for d in mprs.values())
    after = math.ceil(dmax * fs) + (order - 1) // 2
    before = max(0, (order + 1) // 2 - math.ceil(dmin * fs))
    return before, after


def _spans_s(stretches: list[list[int]], t0: float, fs: float) -> dict:
    """``spans_s`` (mission times [start, stop) of the sample ranges) and how many were left off."""
    spans = [[t0 + a / fs, t0 + b / fs] for a, b in stretches[:MAX_LISTED_SPANS]]
    return {"spans_s": spans, "spans_left_off": max(0, len(stretches) - MAX_LISTED_SPANS)}


def _gap_record(file_missing: dict, missing: np.ndarray, mprs: dict, *, t0_file, first, fs, order) -> dict:
    """``config["gaps"]``: the gaps of the telemetry and the NaN of the file they come from."""
    t0 = t0_file + first / fs
    before, after = gap_reach(mprs, fs, order)
    return {
        # the telemetry returned: samples where an eta or DWS value is missing
        "samples_missing": int(missing.sum()),
        "seconds_missing": float(missing.sum() / fs),
        **_spans_s(_stretches(missing), t0, fs),
        # how far a gap of a beat note spreads in eta, and that of an MPR (the Doppler
        # factor's centred gradient: one sample each side)
        "reach_before_s": before / fs,
        "reach_after_s": after / fs,
        "mpr_reach_s": 1 / fs,
        # the file: NaN per dataset, over all its samples (the dropped leading ones included)
        "datasets": {
            name: {"samples_missing": int(m.sum()), **_spans_s(_stretches(m), t0_file, fs)}
            for name, m in sorted(file_missing.items())
        },
        "mprs_interpolated": sorted(name for name in file_missing if name.startswith(f"{MPR_DATASET}/")),
    }


def lisainstrument_truth(path) -> dict[str, float]:
    """The file's true TTL coefficients [m/rad] under our flat names ``"<mosa>.<phi|eta>.<rx|tx>"``.

    lisainstrument stores static coefficients in ``metadata_json``
    (``ttl_coeffs_{local,distant}_{phis,etas}``, dictionaries keyed by MOSA, m/rad).
    ``local`` -> ``rx`` and ``distant`` -> ``tx`` of the same MOSA (see the module docstring
    for the evidence).  Keys come in :data:`~ttlcore.conventions.COEFFICIENT_NAMES` order.

    Raises
    ------
    TelemetryError
        If the file is not a lisainstrument 2.x file or its coefficients are time-varying
        (read from a TTL file, ``ttl_file`` set and the static entries null).
    """
    path = Path(path)
    with _open(path) as f:
        if not is_lisainstrument(f):
            raise TelemetryError(path, "not a lisainstrument measurement file")
        meta = _Metadata(path, f)
    md = meta.data
    flat = _ttl_flat(md)
    if flat is None:
        if md.get("ttl_file"):
            raise TelemetryError(
                path,
                f"time-varying TTL coefficients from file {md['ttl_file']!r}; no static truth",
                meta.where("ttl_file"),
            )
        missing = [k for k in TTL_METADATA_KEYS if not isinstance(md.get(k), dict)]
        raise TelemetryError(
            path,
            "missing or malformed TTL coefficients",
            meta.where(missing[0] if missing else "ttl_coeffs_local_phis"),
        )
    return flat

"""Index conventions, physical constants and unit conversions.

Everything here follows ``docs/physics.md`` (and therefore lisainstrument and pytdi):

- Spacecraft 1, 2, 3.  MOSA ``ij`` sits on spacecraft ``i`` and points at ``j``.
- Link ``ij`` is the beam received at spacecraft ``i`` from ``j``; its light travel
  time is ``tau_ij`` (about 8.3 s) and ``D_ij x(t) = x(t - tau_ij(t))``.
- The canonical order of links and MOSAs is ``12, 23, 31, 13, 32, 21``.
- TTL coefficients ``C[ij, phi|eta, rx|tx]`` are indexed by the MOSA whose jitter they
  multiply; their flat names are ``"<mosa>.<phi|eta>.<rx|tx>"``.
- Measurements are fractional frequency deviations ``y`` (dimensionless), DWS readouts
  angular velocities in rad/s, coefficients m/rad, time in seconds.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import ConfigError

#: Speed of light in vacuum [m/s].
C = 299_792_458.0
#: Laser wavelength [m].
LAMBDA = 1064.5e-9
#: Laser central frequency nu0 = c / lambda [Hz].
NU0 = C / LAMBDA
#: Telemetry sampling frequency [Hz].
FS_TELEMETRY = 4.0
#: Nominal LISA arm length [m] (lisaconstants ``nominal_arm_length``).
ARM_LENGTH = 2.5e9
#: One astronomical unit [m] (IAU 2012).
ASTRONOMICAL_UNIT = 149_597_870_700.0
#: Seconds in a day.
DAY = 86_400.0

#: Spacecraft indices.
SPACECRAFT: tuple[int, ...] = (1, 2, 3)
#: Links (= MOSAs) in canonical order (lisainstrument, pytdi).
LINKS: tuple[str, ...] = ("12", "23", "31", "13", "32", "21")
#: MOSAs, same labels and order as the links they receive.
MOSAS: tuple[str, ...] = LINKS
#: Order in which the paper plots coefficients.
PAPER_ORDER: tuple[str, ...] = ("12", "13", "23", "21", "31", "32")
#: Angular degrees of freedom of a MOSA that couple into length.
ANGLES: tuple[str, ...] = ("phi", "eta")
#: Coupling sides: ``rx`` jitter of the receiving MOSA, ``tx`` of the transmitting one.
SIDES: tuple[str, ...] = ("rx", "tx")

#: MOSA opening angles a_ij [deg]: +30 for 12, 23, 31 and -30 for 13, 32, 21.
MOSA_ANGLES_DEG: dict[str, float] = {"12": 30.0, "23": 30.0, "31": 30.0, "13": -30.0, "32": -30.0, "21": -30.0}


def reverse(link: str) -> str:
    """Return the reversed link ``ji`` of ``ij``."""
    return link[::-1]


def link_index(link: str) -> int:
    """Position of ``link`` in :data:`LINKS`."""
    try:
        return LINKS.index(str(link))
    except ValueError:
        raise ValueError(f"unknown link or MOSA {link!r}; expected one of {', '.join(LINKS)}") from None


def local_spacecraft(mosa: str) -> int:
    """Spacecraft that hosts MOSA ``ij`` (that is ``i``)."""
    return int(mosa[0])


#: Index of the reversed link for each link, in canonical order.
REVERSED_INDEX: tuple[int, ...] = tuple(LINKS.index(reverse(link)) for link in LINKS)


def coefficient_names() -> list[str]:
    """The 24 coefficient names ``"<mosa>.<angle>.<side>"`` in canonical order.

    MOSA in :data:`LINKS` order, then angle (``phi``, ``eta``), then side (``rx``, ``tx``):
    ``"12.phi.rx", "12.phi.tx", "12.eta.rx", "12.eta.tx", "23.phi.rx", ..., "21.eta.tx"``.
    """
    return [f"{m}.{a}.{s}" for m in MOSAS for a in ANGLES for s in SIDES]


COEFFICIENT_NAMES: tuple[str, ...] = tuple(coefficient_names())


def parse_coefficient_name(name: str) -> tuple[str, str, str]:
    """Split ``"12.phi.rx"`` into ``("12", "phi", "rx")``, validating each part."""
    parts = str(name).split(".")
    if len(parts) != 3 or parts[0] not in MOSAS or parts[1] not in ANGLES or parts[2] not in SIDES:
        raise ValueError(f"bad coefficient name {name!r}; expected '<mosa>.<phi|eta>.<rx|tx>', e.g. '12.phi.rx'")
    return parts[0], parts[1], parts[2]


def paper_ordered_names() -> list[str]:
    """Coefficient names in the paper's plotting order (MOSA 12, 13, 23, 21, 31, 32)."""
    return [f"{m}.{a}.{s}" for m in PAPER_ORDER for a in ANGLES for s in SIDES]


# ---------------------------------------------------------------------------
# Unit conversions
# ---------------------------------------------------------------------------


def hz_to_ffd(x_hz):
    """Beat-note frequency fluctuation [Hz] -> fractional frequency deviation, ``x / nu0``."""
    return np.asarray(x_hz) / NU0


def ffd_to_hz(y):
    """Fractional frequency deviation -> frequency fluctuation [Hz], ``y * nu0``."""
    return np.asarray(y) * NU0


def ffd_to_displacement_asd(asd_y, f):
    """ASD of fractional frequency [1/sqrt(Hz)] -> displacement ASD [m/sqrt(Hz)].

    ``ASD_x(f) = c * ASD_y(f) / (2 pi f)`` (docs/physics.md, units).
    """
    return C * np.asarray(asd_y) / (2 * np.pi * np.asarray(f))


def displacement_to_ffd_asd(asd_x, f):
    """Displacement ASD [m/sqrt(Hz)] -> fractional-frequency ASD, ``2 pi f ASD_x / c``."""
    return 2 * np.pi * np.asarray(f) * np.asarray(asd_x) / C


def acceleration_to_ffd_asd(asd_a, f):
    """Acceleration ASD [m/s^2/sqrt(Hz)] -> fractional-frequency ASD, ``ASD_a / (2 pi f c)``."""
    return np.asarray(asd_a) / (2 * np.pi * np.asarray(f) * C)


def angle_to_angular_velocity_asd(asd_angle, f):
    """Angle ASD [rad/sqrt(Hz)] -> angular-velocity ASD [rad/s/sqrt(Hz)], ``2 pi f ASD``."""
    return 2 * np.pi * np.asarray(f) * np.asarray(asd_angle)


def angular_velocity_to_angle_asd(asd_velocity, f):
    """Angular-velocity ASD [rad/s/sqrt(Hz)] -> angle ASD [rad/sqrt(Hz)], ``ASD / (2 pi f)``."""
    return np.asarray(asd_velocity) / (2 * np.pi * np.asarray(f))


def finite_number(
    value, what: str, *, positive: bool = False, unit: str = "", error: type[Exception] = ConfigError
) -> float:
    """``float(value)``, checked finite (and > 0 with ``positive``).

    Raises
    ------
    ConfigError (or ``error``)
        Naming ``what`` (e.g. ``"orbit 'ltt[12]'"``): "orbit 'ltt[12]' must be a positive
        finite number of seconds, got 'x'".
    """
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if not math.isfinite(number) or (positive and number <= 0):
        kind = ("a positive finite number" if positive else "a finite number") + (f" of {unit}" if unit else "")
        raise error(f"{what} must be {kind}, got {value!r}")
    return number


def parse_duration(text: str | float | int, option: str | None = None) -> float:
    """Parse a duration such as ``"1d"``, ``"6h"``, ``"30min"``, ``"90s"`` or ``3600`` into seconds.

    Raises
    ------
    ValueError
        If ``text`` is not a positive duration; with ``option`` (the option or field it came
        from), a :class:`~ttlcore.errors.ConfigError` whose message starts with it.
    """
    return _for_option(_parse_duration, text, option)


def _for_option(parse, text, option: str | None) -> float:
    """``parse(text)``; its ValueError as a ConfigError starting with ``option`` when given."""
    try:
        return parse(text)
    except ValueError as exc:
        if option is None:
            raise
        raise ConfigError(f"{option}: {exc}") from None


#: Units of a time or duration (:func:`parse_duration`, :func:`parse_time`), longest first.
TIME_UNITS = (("min", 60.0), ("d", DAY), ("h", 3600.0), ("m", 60.0), ("s", 1.0))


def _parse_duration(text: str | float | int) -> float:
    value = _time_value(text)
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"duration must be positive, got {text!r}")
    return value


def _time_value(text: str | float | int) -> float:
    """A number of seconds, or a number with a unit of :data:`TIME_UNITS` (any sign)."""
    if isinstance(text, (int, float)):
        return float(text)
    s = str(text).strip().lower()
    for suffix, scale in TIME_UNITS:
        if s.endswith(suffix):
            try:
                return float(s[: -len(suffix)]) * scale
            except ValueError:
                break
    try:
        return float(s)
    except ValueError:
        raise ValueError(f"bad duration {text!r}; use e.g. '1d', '6h', '30min' or seconds") from None


def parse_time(text: str | float | int, option: str | None = None) -> float:
    """A time or signed duration [s]: a number (any sign, zero included) or a number with a
    unit of :data:`TIME_UNITS` (``"2.7h"``, ``"-480s"``, ``"1.5d"``); what
    :func:`format_time` prints.

    Raises
    ------
    ValueError
        If ``text`` is not a finite time; with ``option``, a
        :class:`~ttlcore.errors.ConfigError` whose message starts with it.
    """
    return _for_option(_finite_time, text, option)


def _finite_time(text: str | float | int) -> float:
    value = _time_value(text)
    if not np.isfinite(value):
        raise ValueError(f"a time must be finite, got {text!r}")
    return value


def format_number(x: float) -> str:
    """The shortest text that reads back as ``x`` exactly (``1800.0`` -> ``"1800"``,
    ``0.35`` -> ``"0.35"``)."""
    text = repr(float(x))
    return text[:-2] if text.endswith(".0") else text


def format_time(seconds: float) -> str:
    """A time [s] with its unit, read back by :func:`parse_time` (and, when positive, by
    :func:`parse_duration`) as exactly the same float: in days or hours where a number of at
    most 6 significant digits gives it exactly (``86400`` -> ``"1d"``, ``54720`` ->
    ``"15.2h"``), else in seconds (``1800`` -> ``"1800s"``, ``9734.25`` -> ``"9734.25s"``)."""
    v = float(seconds)
    if not np.isfinite(v):
        return repr(v)
    sign, a = ("-" if v < 0 else ""), abs(v)
    for suffix, scale in (("d", DAY), ("h", 3600.0)):
        if a >= scale:
            text = f"{a / scale:.6g}"
            if "e" not in text and float(text) * scale == a:
                return f"{sign}{text}{suffix}"
    return f"{sign}{format_number(a)}s"


#: Units of a frequency (:func:`parse_frequency`).
FREQUENCY_UNITS = (("mhz", 1e-3), ("hz", 1.0))


def parse_frequency(text: str | float | int, option: str | None = None) -> float:
    """A frequency [Hz]: a number of hertz or a number with its unit (``"0.0718Hz"``,
    ``"71.8mHz"``); what :func:`format_frequency` prints.  ConfigError (ValueError
    without ``option``) unless finite and positive."""
    return _for_option(_positive_frequency, text, option)


def _positive_frequency(text: str | float | int) -> float:
    value = _frequency_value(text)
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"frequency must be positive, got {text!r}")
    return value


def _frequency_value(text: str | float | int) -> float:
    if isinstance(text, (int, float)):
        return float(text)
    s = str(text).strip().lower()
    for suffix, scale in FREQUENCY_UNITS:
        if s.endswith(suffix):
            s, factor = s[: -len(suffix)], scale
            break
    else:
        factor = 1.0
    try:
        return float(s) * factor
    except ValueError:
        raise ValueError(f"bad frequency {text!r}; use e.g. '0.0718Hz', '71.8mHz' or hertz") from None


def format_frequency(hz: float) -> str:
    """A frequency [Hz] with its unit, read back by :func:`parse_frequency` exactly
    (``0.0718`` -> ``"0.0718Hz"``)."""
    return f"{format_number(hz)}Hz"

"""TTL coupling coefficients: standard sets and time-varying truth models.

The 24 coefficients ``C[ij, phi|eta, rx|tx]`` [m/rad] are indexed by the MOSA whose jitter
they multiply and ordered as :data:`ttlcore.conventions.COEFFICIENT_NAMES`
(``"12.phi.rx", "12.phi.tx", "12.eta.rx", "12.eta.tx", "23.phi.rx", ...``).

Standard sets (docs/physics.md):

- ``paper``: 2.3 mm/rad for all 24 (Hartig et al., section III).
- ``lisainstrument``: lisainstrument's fixed "default" set (``instru_defaults.py``, values
  drawn once from U(-2.2, 2.2) mm/rad for local = rx and U(-2.4, 2.4) mm/rad for distant =
  tx coefficients); lisainstrument's distant coefficient of MOSA ``ij`` multiplies MOSA
  ``ij``'s jitter delayed onto link ``ji``, i.e. our ``ij.*.tx``.
- ``random``: drawn from those same uniform distributions with a seed.

A :class:`CoefficientModel` adds time dependence for simulations: a linear drift, steps at
given times and/or a piecewise-linear table.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..conventions import COEFFICIENT_NAMES, DAY, parse_coefficient_name
from ..errors import ConfigError

#: lisainstrument 2.x default TTL coefficients [m/rad] (``lisainstrument/instru/instru_defaults.py``):
#: (local phi, distant phi, local eta, distant eta) per MOSA.
_LISAINSTRUMENT_DEFAULT = {
    "12": (2.005835e-03, 1.623910e-03, -1.670389e-03, -1.076470e-03),
    "23": (2.105403e-04, 1.522873e-04, 1.460681e-03, 5.228848e-04),
    "31": (-1.815399e-03, -1.842871e-03, -1.039064e-03, -5.662766e-05),
    "13": (-2.865050e-04, -2.091585e-03, 1.640473e-04, 1.960050e-03),
    "32": (-1.986657e-03, 1.300866e-03, 1.205353e-03, 9.021890e-04),
    "21": (9.368319e-04, -8.445374e-04, -9.205764e-04, 1.908239e-03),
}


def as_vector(values) -> np.ndarray:
    """Turn a mapping ``name -> m/rad`` (all 24 names) or a length-24 sequence into a vector."""
    if isinstance(values, dict):
        unknown = set(values) - set(COEFFICIENT_NAMES)
        for name in unknown:
            parse_coefficient_name(name)  # raises with a clear message
        missing = [n for n in COEFFICIENT_NAMES if n not in values]
        if missing:
            raise ConfigError(f"coefficients missing for {', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}")
        return np.array([float(values[n]) for n in COEFFICIENT_NAMES])
    vec = np.asarray(values, dtype=float).reshape(-1)
    if vec.size != len(COEFFICIENT_NAMES):
        raise ConfigError(f"expected 24 coefficients, got {vec.size}")
    return vec


def as_mapping(vector) -> dict[str, float]:
    """Vector of 24 coefficients -> ``{name: value}``."""
    return {n: float(v) for n, v in zip(COEFFICIENT_NAMES, np.asarray(vector, dtype=float))}


def paper_set(value: float = 2.3e-3) -> np.ndarray:
    """The paper's truth: the same value (default 2.3 mm/rad) for all 24 coefficients [m/rad]."""
    return np.full(len(COEFFICIENT_NAMES), float(value))


def lisainstrument_set() -> np.ndarray:
    """lisainstrument's fixed default set [m/rad] (|C| from 0.06 to 2.1 mm/rad)."""
    out = {}
    for mosa, (lphi, dphi, leta, deta) in _LISAINSTRUMENT_DEFAULT.items():
        out[f"{mosa}.phi.rx"], out[f"{mosa}.phi.tx"] = lphi, dphi
        out[f"{mosa}.eta.rx"], out[f"{mosa}.eta.tx"] = leta, deta
    return as_vector(out)


def random_set(seed: int, rx_max: float = 2.2e-3, tx_max: float = 2.4e-3) -> np.ndarray:
    """Coefficients drawn uniformly in ``[-rx_max, rx_max]`` (rx) and ``[-tx_max, tx_max]`` (tx) [m/rad]."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x77C0EF]))
    limits = np.array([rx_max if name.endswith(".rx") else tx_max for name in COEFFICIENT_NAMES])
    return rng.uniform(-limits, limits)


@dataclass(frozen=True)
class CoefficientModel:
    """Time-dependent truth coefficients ``C(t)`` [m/rad].

    ``C(t) = base + drift * (t - t_ref) + sum_{t_k <= t} step_k + table(t)``

    Attributes
    ----------
    base : ndarray, shape (24,)
        Values at ``t_ref`` [m/rad].
    drift : ndarray, shape (24,)
        Linear drift rates [m/rad/s].
    t_ref : float
        Reference time of the drift [s].
    steps : tuple of (float, ndarray)
        ``(t_k [s], jump [m/rad], shape (24,))``; the jump applies for ``t >= t_k``.
    table_t, table_values : ndarray or None
        Optional piecewise-linear additive table: times [s] (increasing) and values
        [m/rad], shape (24, k); held constant outside the table.
    """

    base: np.ndarray
    drift: np.ndarray = field(default_factory=lambda: np.zeros(len(COEFFICIENT_NAMES)))
    t_ref: float = 0.0
    steps: tuple = ()
    table_t: np.ndarray | None = None
    table_values: np.ndarray | None = None

    @property
    def is_constant(self) -> bool:
        return not np.any(self.drift) and not self.steps and self.table_t is None

    def values(self, t) -> np.ndarray:
        """Coefficients at times ``t``: shape ``(24, n)`` [m/rad]."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        out = self.base[:, None] + self.drift[:, None] * (t - self.t_ref)[None, :]
        for t_step, jump in self.steps:
            out = out + np.asarray(jump)[:, None] * (t >= t_step)[None, :]
        if self.table_t is not None and self.table_values is not None:
            out = out + np.stack([np.interp(t, self.table_t, row) for row in self.table_values])
        return out

    def mean(self, t_start: float, t_stop: float, n: int = 4097) -> np.ndarray:
        """Average of ``C(t)`` over ``[t_start, t_stop]`` [m/rad], shape (24,)."""
        return self.values(np.linspace(t_start, t_stop, n)).mean(axis=1)

    def describe(self) -> dict:
        """JSON-serialisable description (m/rad, m/rad/s, s); inverse: :meth:`from_description`."""
        d = {"base": as_mapping(self.base), "t_ref": self.t_ref}
        if np.any(self.drift):
            d["drift_per_s"] = {n: v for n, v in as_mapping(self.drift).items() if v}
        if self.steps:
            d["steps"] = [{"t": float(t), "jump": {n: v for n, v in as_mapping(j).items() if v}} for t, j in self.steps]
        if self.table_t is not None and self.table_values is not None:
            d["table"] = {
                "t": list(map(float, self.table_t)),
                "values": {n: list(map(float, row)) for n, row in zip(COEFFICIENT_NAMES, self.table_values)},
            }
        return d

    @classmethod
    def from_description(cls, d: dict) -> CoefficientModel:
        """Build from :meth:`describe` output (also the JSON file format of ``--coeffs FILE``)."""
        if "base" not in d:
            raise ConfigError("coefficient description needs a 'base' mapping of the 24 names to m/rad")
        zeros = dict.fromkeys(COEFFICIENT_NAMES, 0.0)
        drift = as_vector({**zeros, **d.get("drift_per_s", {})})
        if "drift_per_day" in d:
            drift = drift + as_vector({**zeros, **d["drift_per_day"]}) / DAY
        steps = tuple((float(s["t"]), as_vector({**zeros, **s.get("jump", {})})) for s in d.get("steps", []))
        table_t = table_values = None
        if "table" in d:
            table_t = np.asarray(d["table"]["t"], dtype=float)
            vals = d["table"]["values"]
            table_values = np.array([vals.get(n, np.zeros_like(table_t)) for n in COEFFICIENT_NAMES], dtype=float)
            if table_values.shape != (24, table_t.size) or np.any(np.diff(table_t) <= 0):
                raise ConfigError("coefficient table needs increasing 't' and one value per time for each name")
        return cls(
            base=as_vector(d["base"]),
            drift=drift,
            t_ref=float(d.get("t_ref", 0.0)),
            steps=steps,
            table_t=table_t,
            table_values=table_values,
        )

    def with_drift(self, rates_per_day: dict[str, float]) -> CoefficientModel:
        """Copy with added linear drifts, given in m/rad per day."""
        extra = np.zeros(len(COEFFICIENT_NAMES))
        for name, rate in rates_per_day.items():
            extra[_index(name)] += float(rate) / DAY
        return CoefficientModel(self.base, self.drift + extra, self.t_ref, self.steps, self.table_t, self.table_values)

    def with_step(self, t_step: float, jumps: dict[str, float]) -> CoefficientModel:
        """Copy with an added step at ``t_step`` [s]; ``jumps`` in m/rad."""
        jump = np.zeros(len(COEFFICIENT_NAMES))
        for name, value in jumps.items():
            jump[_index(name)] += float(value)
        steps = tuple(sorted(self.steps + ((float(t_step), jump),), key=lambda s: s[0]))
        return CoefficientModel(self.base, self.drift, self.t_ref, steps, self.table_t, self.table_values)


def _index(name: str) -> int:
    parse_coefficient_name(name)
    return COEFFICIENT_NAMES.index(name)


def make_coefficients(spec: str, seed: int = 0) -> CoefficientModel:
    """Coefficient model from a CLI spec: ``paper``, ``lisainstrument``, ``random`` or a JSON file.

    The JSON file holds either a flat mapping of the 24 names to m/rad, or a
    :meth:`CoefficientModel.describe`-style object (``base``, optional ``drift_per_day``,
    ``drift_per_s``, ``steps``, ``table``).
    """
    spec = str(spec)
    if spec == "paper":
        return CoefficientModel(paper_set())
    if spec == "lisainstrument":
        return CoefficientModel(lisainstrument_set())
    if spec == "random":
        return CoefficientModel(random_set(seed))
    path = Path(spec)
    if not path.exists():
        raise ConfigError(f"--coeffs: {spec!r} is neither paper, lisainstrument, random nor an existing JSON file")
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read coefficients ({exc})") from None
    if not isinstance(d, dict):
        raise ConfigError(f"{path}: expected a JSON object")
    try:
        if "base" in d:
            return CoefficientModel.from_description(d)
        return CoefficientModel(as_vector(d))
    except (ConfigError, ValueError) as exc:
        raise ConfigError(f"{path}: {exc}") from None

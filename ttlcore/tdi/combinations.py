"""Second-generation time-delay interferometry on the eta variables.

A TDI combination is a sum of delayed ``eta`` terms, ``sum_k f_k D_{chain_k} eta_{link_k}``,
where a chain ``(a_1, ..., a_m)`` of links stands for the nested delay
``D_{a_1} D_{a_2} ... D_{a_m}`` (leftmost outermost):

    D_a D_b x(t) = x(t - tau_a(t) - tau_b(t - tau_a(t)))

(docs/physics.md).  The second-generation Michelson combination (pytdi's ``X2_ETA``) is

    X2 = (1 - D_121 - D_12131 + D_1312121)(eta_13 + D_13 eta_31)
       - (1 - D_131 - D_13121 + D_1213131)(eta_12 + D_12 eta_21),

with ``D_121 = D_12 D_21`` and so on; Y2 and Z2 follow by the cyclic permutation
1 -> 2 -> 3 -> 1, and ``A = (Z - X)/sqrt(2)``, ``E = (X - 2Y + Z)/sqrt(6)``,
``T = (X + Y + Z)/sqrt(3)`` (Hartig et al., eqs. 5-7).

:meth:`Combination.build` binds a combination to a light-travel-time series; evaluating it
runs the block engine :func:`ttlcore.tdi.engine.tdi_columns` (nested delays at a few nodes
per block, interpolation weights as Chebyshev polynomials in time, all terms of a link as
one FIR applied by FFT).  Because TDI is linear, the same engine turns witness series
placed on links (the TTL regressors) into regressor columns
(:meth:`BuiltCombination.apply_on_links`, :func:`ttlcore.tdi.data.compute_tdi`).

Delays carry no Doppler factor here: ``D x(t) = x(t - tau(t))``, the operator of docs/physics.md
and of pytdi's ``unit="phase"`` evaluation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..conventions import LINKS
from .engine import DEFAULT_DELAY_ORDER, Part, tdi_columns
from .interpolation import DEFAULT_ORDER, apply_taps, shift_taps

Chain = tuple[str, ...]


def _permute_link(link: str, mapping: dict[str, str]) -> str:
    return "".join(mapping[c] for c in link)


@dataclass(frozen=True)
class Combination:
    """A linear TDI combination of the six ``eta_ij``.

    Attributes
    ----------
    name : str
    terms : tuple of (float, str, tuple of str)
        ``(factor, link, chain)``: ``factor * D_chain eta_link``.
    """

    name: str
    terms: tuple

    def permuted(self, mapping: dict[int, int], name: str | None = None) -> Combination:
        """Relabel spacecraft indices, e.g. ``{1: 2, 2: 3, 3: 1}``."""
        m = {str(k): str(v) for k, v in mapping.items()}
        terms = tuple((f, _permute_link(l, m), tuple(_permute_link(c, m) for c in chain)) for f, l, chain in self.terms)
        return Combination(name or self.name, terms)

    def rotated(self, name: str | None = None) -> Combination:
        """Cyclic permutation 1 -> 2 -> 3 -> 1 (X -> Y -> Z)."""
        return self.permuted({1: 2, 2: 3, 3: 1}, name)

    @property
    def chains(self) -> set:
        return {chain for _, _, chain in self.terms}

    @property
    def max_chain_length(self) -> int:
        return max(len(chain) for _, _, chain in self.terms)

    def build(
        self,
        ltt: np.ndarray,
        fs: float,
        order: int = DEFAULT_ORDER,
        delay_order: int = DEFAULT_DELAY_ORDER,
        history: int = 0,
    ) -> BuiltCombination:
        """Bind to a delay series; see :func:`build`."""
        return build([self], ltt, fs, order=order, delay_order=delay_order, history=history)[0]


def _michelson_x2() -> Combination:
    """pytdi's ``X2_ETA``, expanded into its 16 delayed terms."""

    def poly(a: str, b: str):
        # 1 - D_{1a1} - D_{1a1 1b1} + D_{1b1 1a1 1a1}
        aa, bb = ("1" + a, a + "1"), ("1" + b, b + "1")
        return [(1.0, ()), (-1.0, aa), (-1.0, aa + bb), (1.0, bb + aa + aa)]

    terms = []
    for sign, a, b in ((1.0, "3", "2"), (-1.0, "2", "3")):
        # sign * P_ab (eta_1a + D_1a eta_a1)
        for f, chain in poly(b, a):
            terms.append((sign * f, "1" + a, chain))
            terms.append((sign * f, a + "1", chain + ("1" + a,)))
    return Combination("X2", tuple(terms))


X2 = _michelson_x2()
Y2 = X2.rotated("Y2")
Z2 = Y2.rotated("Z2")
MICHELSON = (X2, Y2, Z2)
#: Channel names of the Michelson combinations and of the orthogonal ones made from them.
XYZ = tuple(c.name for c in MICHELSON)
AET = ("A", "E", "T")

#: Orthogonal combinations from X, Y, Z: rows give the weights of (X, Y, Z).
AET_MATRIX = np.array(
    [
        [-1 / np.sqrt(2), 0.0, 1 / np.sqrt(2)],
        [1 / np.sqrt(6), -2 / np.sqrt(6), 1 / np.sqrt(6)],
        [1 / np.sqrt(3), 1 / np.sqrt(3), 1 / np.sqrt(3)],
    ]
)


def aet(xyz: np.ndarray) -> np.ndarray:
    """A, E, T from X, Y, Z stacked on the first axis: ``A = (Z - X)/sqrt 2``,
    ``E = (X - 2Y + Z)/sqrt 6``, ``T = (X + Y + Z)/sqrt 3``."""
    xyz = np.asarray(xyz)
    return np.tensordot(AET_MATRIX, xyz, axes=(1, 0))


def nested_delays(chains, ltt: np.ndarray, fs: float, delay_order: int = DEFAULT_DELAY_ORDER) -> dict:
    """Total delay [s] of each chain at every sample: ``Delta_chain(t)``.

    ``Delta_{a_1..a_m}(t) = Delta_{a_1..a_{m-1}}(t) + tau_{a_m}(t - Delta_{a_1..a_{m-1}}(t))``,
    with ``tau`` read at earlier times by Lagrange interpolation of order ``delay_order``.
    Prefixes are shared between chains.  Samples whose interpolation leaves the series
    are NaN.

    Parameters
    ----------
    chains : iterable of tuple of str
    ltt : ndarray, shape (6, n)
        Light travel times [s] in :data:`~ttlcore.conventions.LINKS` order.
    """
    ltt = np.asarray(ltt, dtype=float)
    n = ltt.shape[-1]
    out: dict[Chain, np.ndarray] = {(): np.zeros(n)}
    for chain in sorted(set(chains), key=len):
        for m in range(1, len(chain) + 1):
            prefix = chain[:m]
            if prefix in out:
                continue
            previous = out[prefix[:-1]]
            tau = ltt[LINKS.index(prefix[-1])]
            if not prefix[:-1]:
                out[prefix] = tau.copy()
            else:
                # tau_{a_m}(t - Delta_prev(t)): shift by -Delta_prev * fs samples
                shifted = apply_taps(tau, shift_taps(-previous * fs, n, delay_order))
                out[prefix] = previous + shifted
    return out


@dataclass
class BuiltCombination:
    """A combination bound to a light-travel-time series (see :func:`build`).

    Call it on ``eta`` (shape ``(6, history + n)``) or use :meth:`apply_on_links` for
    witness channels; both run the block engine :func:`ttlcore.tdi.engine.tdi_columns`.
    Output samples whose delays reach before the data are NaN.
    """

    combination: Combination
    ltt: np.ndarray = field(repr=False)
    fs: float
    order: int = DEFAULT_ORDER
    delay_order: int = DEFAULT_DELAY_ORDER
    history: int = 0

    @property
    def n(self) -> int:
        """Number of output samples."""
        return self.ltt.shape[-1] - self.history

    @cached_property
    def terms_by_link(self) -> dict:
        """``link -> [(factor, chain), ...]``: the delay polynomial acting on each link."""
        d: dict[str, list] = {link: [] for link in LINKS}
        for f, link, chain in self.combination.terms:
            d[link].append((f, tuple(chain)))
        return d

    def columns(self, parts, ncolumns: int) -> np.ndarray:
        """:func:`~ttlcore.tdi.engine.tdi_columns` of ``parts`` for this combination: ``(ncolumns, n)``."""
        return tdi_columns(
            parts,
            ncolumns,
            self.ltt,
            self.fs,
            history=self.history,
            combinations=(self.combination,),
            order=self.order,
            delay_order=self.delay_order,
        )[0]

    def __call__(self, eta: np.ndarray) -> np.ndarray:
        """Evaluate the combination on ``eta`` (shape ``(6, history + n)``); returns ``(n,)``."""
        eta = np.asarray(eta)
        return self.columns([Part(0, link, (), eta[k]) for k, link in enumerate(LINKS)], 1)[0]

    def apply_on_links(self, witnesses: dict) -> dict:
        """TDI of witness channels that each live on one link.

        Parameters
        ----------
        witnesses : dict
            ``(link, extra_chain) -> array (k, history + n)``: ``k`` channels placed on
            ``link`` after the extra delays ``extra_chain`` (``("12",)`` for a Tx witness
            ``D_12 w``); the extra delay is applied first at every input sample
            (:func:`ttlcore.tdi.engine.predelayed`), as the simulator forms the Tx term.

        Returns
        -------
        dict
            Same keys, arrays ``(k, n)``; zeros for links that do not enter the combination.
        """
        out = {}
        for (link, extra), x in witnesses.items():
            x = np.asarray(x)
            rows = x.reshape(-1, x.shape[-1])
            res = self.columns([Part(j, link, tuple(extra), r) for j, r in enumerate(rows)], rows.shape[0])
            out[(link, tuple(extra))] = res.reshape(x.shape[:-1] + (self.n,))
        return out


def build(
    combinations,
    ltt: np.ndarray,
    fs: float,
    order: int = DEFAULT_ORDER,
    delay_order: int = DEFAULT_DELAY_ORDER,
    history: int = 0,
) -> list:
    """Bind several combinations to one delay series.

    Parameters
    ----------
    combinations : sequence of Combination
    ltt : ndarray, shape (6, history + n)
        Light travel times [s] at every input sample.
    fs : float
        Sampling rate [Hz].
    order : int
        Lagrange order of the data interpolation (odd, default 31).
    delay_order : int
        Lagrange order for reading delays at earlier times (default 5, as pytdi).
    history : int
        Number of leading input samples that precede the first output sample (kept from
        the previous segment in streaming use).  Outputs have ``n`` samples.
    """
    ltt = np.asarray(ltt, dtype=float)
    return [BuiltCombination(comb, ltt, float(fs), int(order), int(delay_order), int(history)) for comb in combinations]


def max_delay_samples(combination_or_list, ltt_max: float, fs: float, order: int = DEFAULT_ORDER) -> int:
    """Samples of history a combination needs: longest chain times the largest delay, plus the stencil."""
    combos = combination_or_list if isinstance(combination_or_list, (list, tuple)) else [combination_or_list]
    longest = max(c.max_chain_length for c in combos) + 1
    return int(np.ceil(longest * ltt_max * fs)) + order // 2 + 2


def chain_delay_static(chain: Chain, ltt: dict) -> float:
    """Total delay [s] of a chain for constant light travel times ``{link: tau}``."""
    return float(sum(ltt[link] for link in chain))


def link_responses(combination: Combination, f: np.ndarray, ltt, extra: Chain = ()) -> np.ndarray:
    """Frequency response of a combination to a signal on each link, for static delays.

    ``H_link(f) = sum_{terms on link} factor * exp(-2 pi i f Delta_{chain + extra})``, so
    that a stationary process ``x`` placed on ``link`` (after the extra delays ``extra``)
    appears in the combination with PSD ``|H_link(f)|^2 S_x(f)``.

    Parameters
    ----------
    combination : Combination
    f : ndarray, shape (m,)
        Frequencies [Hz].
    ltt : dict or array_like
        Constant light travel times [s]: ``{link: tau}`` or six values in LINKS order
        (time series are averaged).
    extra : tuple of str
        Extra delays applied to the signal before it enters the link.

    Returns
    -------
    ndarray, shape (6, m), complex
        One row per link in LINKS order.
    """
    if not isinstance(ltt, dict):
        arr = np.asarray(ltt, dtype=float)
        arr = arr.mean(axis=-1) if arr.ndim == 2 else arr
        ltt = dict(zip(LINKS, arr))
    f = np.asarray(f, dtype=float)
    out = np.zeros((6, f.size), dtype=complex)
    for factor, link, chain in combination.terms:
        d = chain_delay_static(tuple(chain) + tuple(extra), ltt)
        out[LINKS.index(link)] += factor * np.exp(-2j * np.pi * f * d)
    return out

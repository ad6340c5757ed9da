"""The TDI engine: combinations of series placed on links, in blocks with their history.

Every TDI in ``ttlcore`` (the data and the TTL regressors of :func:`ttlcore.tdi.data.compute_tdi`,
the streaming :class:`~ttlcore.tdi.data.TDIStream`, the diagnosis' effect columns) goes
through :func:`tdi_columns`.  A *column* is a sum of *parts*, each a series placed on a link
after extra delays (a TTL Tx witness ``D_ij w`` sits on link ``ij`` with extra chain
``("ij",)``; ``eta`` is the column with one part per link and no extra delay).  Because TDI
is linear, the output of a column is ``sum_parts sum_terms f D_chain (D_extra x_part)``, the
extra delays applied first at every input sample (:func:`predelayed`), as the simulator
forms the Tx TTL term.

How it is evaluated (the operator is the one of docs/physics.md and of pytdi's
``unit="phase"``: ``D_{a_1..a_m} x(t) = x(t - Delta_{a_1..a_m}(t))`` with nested delays
``Delta_{a_1..a_m}(t) = Delta_{a_1..a_{m-1}}(t) + tau_{a_m}(t - Delta_{a_1..a_{m-1}}(t))``, the
light travel times read at earlier times by Lagrange interpolation of order ``delay_order``,
and the data by centred Lagrange interpolation of order ``order``):

1. The output is cut in blocks of a few thousand samples; each block reads its inputs from
   ``history`` samples before its first output (the longest chain plus the stencil), so a
   block needs nothing from the previous one and memory does not grow with the data.
2. Within a block every delay is a fixed integer shift plus a fractional part ``eps(t)``
   that moves by less than ``1e-2`` sample (light travel times change by ~``3e-8`` s/s).
   The Lagrange weights ``w_m(eps(t))`` are therefore represented by their Chebyshev
   interpolant of degree ``degree`` in time, ``w_m(t) = sum_q A_{mq} T_q(u(t))``, from the
   nested delays evaluated at ``degree + 1`` Chebyshev nodes of the block only.
3. Then ``D x = sum_q T_q(u) (A_q * x)``: for each power ``q`` the delay is a fixed FIR, and
   the terms of a column on one link, across all its chains, add up into one FIR.  These
   are applied by FFT (one forward transform per input series and block, one inverse per
   output, combination and ``q``), so the cost does not depend on the number of terms.

Accuracy: the Chebyshev interpolant of the weights over a block where ``eps`` moves by
``delta`` samples errs by about ``(pi delta / 2)^(degree+1) / (degree+1)! / 2^degree`` relative
to the signal at Nyquist; with blocks of ~4000 s and ``degree = 3`` that is below ``1e-12``,
far under the order-31 interpolation error itself (``2e-7`` at 0.9 Hz of 4 Hz data), and FFT
rounding is ~``1e-16`` of the block's largest input.  Outputs whose stencil reaches before
the first input sample are NaN, as are outputs whose stencil touches a non-finite input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft

from ..conventions import LINKS
from .interpolation import DEFAULT_ORDER, _check_order, lagrange_weights

Chain = tuple[str, ...]

#: Lagrange order used to interpolate light travel times inside nested delays (pytdi's default).
DEFAULT_DELAY_ORDER = 5
#: Degree of the Chebyshev interpolant of the interpolation weights over one block.
DEFAULT_DEGREE = 2
#: FFT length of one block (outputs per block = this minus the history).
DEFAULT_NFFT = 1 << 15


@dataclass(frozen=True)
class Part:
    """One series placed on a link: ``series`` enters ``link`` after the delays ``extra``.

    ``series`` has one sample per input sample (history included)."""

    column: int
    link: str
    extra: Chain
    series: np.ndarray


def _history(chains, ltt_max: float, fs: float, order: int, delay_order: int) -> int:
    """Input samples the chains reach back to: the longest chain times the largest light
    travel time, plus the stencils of the data and of the delay interpolation (and a margin)."""
    longest = max((len(c) for c in chains), default=0)
    return int(np.ceil(longest * ltt_max * fs)) + 2 * (order // 2 + 1) + delay_order + 8


@dataclass(frozen=True)
class _Delay:
    """The one-term combination ``D_link x`` on ``link`` (a pre-delay)."""

    link: str

    @property
    def terms(self) -> tuple:
        return ((1.0, self.link, (self.link,)),)


def _chebyshev_nodes(degree: int) -> np.ndarray:
    return np.cos(np.pi * (np.arange(degree + 1) + 0.5) / (degree + 1))


def _chebyshev_coefficients(values: np.ndarray, degree: int) -> np.ndarray:
    """Coefficients ``A_q`` of the degree-``degree`` interpolant at the Chebyshev nodes;
    ``values`` has the nodes on its first axis."""
    u = _chebyshev_nodes(degree)
    T = np.polynomial.chebyshev.chebvander(u, degree)  # (nodes, q)
    A = (2.0 / (degree + 1)) * np.tensordot(T.T, values, axes=(1, 0))
    A[0] /= 2
    return A


class _Plan:
    """Per-combination delay polynomials of every (link, extra) group of parts."""

    def __init__(self, combinations, groups):
        self.combinations = tuple(combinations)
        # (link, extra) -> [(c, [(factor, chain + extra), ...]), ...]
        self.terms: dict = {}
        chains: set = set()
        for key in groups:
            link, extra = key
            per = []
            for c, comb in enumerate(self.combinations):
                poly = [(f, tuple(chain) + tuple(extra)) for f, lnk, chain in comb.terms if lnk == link]
                if poly:
                    per.append((c, poly))
                    chains.update(ch for _, ch in poly)
            self.terms[key] = per
        self.chains = sorted(chains, key=lambda ch: (len(ch), ch))


def _edge_lines(ltt: np.ndarray, fs: float):
    """``f(rows, positions)``: the least-squares straight lines of each row of ``ltt`` over
    its first and last minute, evaluated at positions before and after the data."""
    m = ltt.shape[-1]
    k = max(2, min(m, int(60 * fs)))
    x = np.arange(k, dtype=float)
    head = np.polynomial.polynomial.polyfit(x, ltt[:, :k].T, 1)  # (2, rows)
    tail = np.polynomial.polynomial.polyfit(x + (m - k), ltt[:, m - k :].T, 1)

    def line(rows, pos):
        c = np.where(pos < m / 2, head[:, rows], tail[:, rows])
        return c[0] + c[1] * pos

    return line


def _nested_delays(chains, ltt: np.ndarray, pos: np.ndarray, fs: float, delay_order: int) -> dict:
    """``Delta_chain`` [s] at input positions ``pos`` for every chain and prefix, one chain
    length at a time (all prefixes of a length in one interpolation)."""
    out: dict[Chain, np.ndarray] = {(): np.zeros(pos.size)}
    prefixes = {chain[:m] for chain in chains for m in range(1, len(chain) + 1)}
    for length in range(1, max((len(c) for c in chains), default=0) + 1):
        level = sorted(p for p in prefixes if len(p) == length)
        prev = np.stack([out[p[:-1]] for p in level])  # (k, nodes)
        rows = np.array([LINKS.index(p[-1]) for p in level])
        read = (pos[None, :] - prev * fs).ravel()
        k = np.floor(read)
        w = lagrange_weights(read - k, delay_order)  # (order + 1, k * nodes)
        idx = k.astype(np.int64)[None, :] + np.arange(-(delay_order - 1) // 2, (delay_order + 1) // 2 + 1)[:, None]
        m = ltt.shape[-1]
        outside = (idx[0] < 0) | (idx[-1] > m - 1)
        idx = np.clip(idx, 0, m - 1)
        every = np.repeat(rows, pos.size)
        tau = np.einsum("jp,jp->p", w, ltt[every[None, :], idx])
        if outside.any():
            # reads before (after) the data, at the nodes of a first (last) block: outputs that
            # need them are NaN, but the nodes shape the block's Chebyshev weights, so the
            # light travel time is continued by its straight line over the first (last) minute
            tau[outside] = _edge_lines(ltt, fs)(every[outside], read[outside])
        tau = tau.reshape(prev.shape)
        for i, p in enumerate(level):
            out[p] = prev[i] + tau[i]
    return out


def predelayed(parts, ltt: np.ndarray, fs: float, **options) -> list:
    """The parts with their extra delays applied at every input sample, extra chains emptied.

    A Tx witness ``D_ij w`` is formed as the simulator (and lisainstrument) form the Tx TTL
    term: ``w`` delayed by ``tau_ij`` at every sample first, then placed on link ``ij`` -- two
    Lagrange interpolations, which the TDI chain then reads.  (Folding the pre-delay into the
    nested delay would be one interpolation: equal in the fit band, but above 1 Hz, where
    order-31 interpolation of 4 Hz data errs by 1e-5..1, it would not reproduce the data.)
    The first ``tau * fs + order / 2`` samples are NaN.  ``options`` go to :func:`tdi_columns`.
    """
    out = [p for p in parts if not p.extra]
    pending = [(p, tuple(p.extra)) for p in parts if p.extra]
    while pending:
        by_delay: dict = {}
        for i, (_p, extra) in enumerate(pending):
            by_delay.setdefault(extra[-1], []).append(i)  # innermost delay first
        done: list = [None] * len(pending)
        for d, idx in by_delay.items():
            moved = tdi_columns(
                [Part(j, d, (), pending[i][0].series) for j, i in enumerate(idx)],
                len(idx),
                ltt,
                fs,
                combinations=(_Delay(d),),
                **options,
            )[0]
            for j, i in enumerate(idx):
                p, extra = pending[i]
                done[i] = (Part(p.column, p.link, extra[:-1], moved[j]), extra[:-1])
        out += [p for p, extra in done if not extra]
        pending = [(p, extra) for p, extra in done if extra]
    return out


def tdi_columns(
    parts,
    ncolumns: int,
    ltt: np.ndarray,
    fs: float,
    *,
    combinations,
    history: int = 0,
    order: int = DEFAULT_ORDER,
    delay_order: int = DEFAULT_DELAY_ORDER,
    degree: int = DEFAULT_DEGREE,
    nfft: int = DEFAULT_NFFT,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """TDI of columns made of parts placed on links (see the module docstring).

    Parameters
    ----------
    parts : iterable of Part
        ``Part(column, link, extra, series)``; ``series`` shape ``(history + n,)``.
    ncolumns : int
        Number of output columns.
    ltt : ndarray, shape (6, history + n)
        Light travel times [s] at every input sample, LINKS order.
    fs : float
        Sampling rate [Hz].
    history : int
        Leading input samples before the first output sample.
    combinations : sequence of Combination
        E.g. :data:`ttlcore.tdi.combinations.MICHELSON` (anything with ``terms``).
    order, delay_order : int
        Lagrange orders of the data and of the light-travel-time interpolation.
    degree : int
        Chebyshev degree of the weights over one block.
    nfft : int
        FFT length of a block.
    out : ndarray, shape (len(combinations), ncolumns, n), optional
        Output array to fill.

    Returns
    -------
    ndarray, shape (len(combinations), ncolumns, n)
        Zero for columns whose links a combination does not use; NaN where a stencil
        reaches before the data or touches a non-finite input.
    """
    combinations = tuple(combinations)
    order = _check_order(order)
    ltt = np.asarray(ltt, dtype=float)
    total = ltt.shape[-1]
    history = int(history)
    n = total - history
    ncomb = len(combinations)
    if out is None:
        out = np.zeros((ncomb, ncolumns, n))
    else:
        out[...] = 0.0
    parts = list(parts)
    if n <= 0 or not parts:
        return out
    for p in parts:
        if np.shape(p.series)[-1] != total:
            raise ValueError(
                f"part of column {p.column} on link {p.link} has {np.shape(p.series)[-1]} samples, the delays {total}"
            )
    groups: dict = {}
    for p in predelayed(parts, ltt, fs, order=order, delay_order=delay_order, degree=degree, nfft=nfft):
        groups.setdefault((p.link, ()), []).append((p.column, np.asarray(p.series, dtype=float)))
    plan = _Plan(combinations, groups)

    ltt_max = float(np.nanmax(ltt))
    hist = _history(plan.chains, ltt_max, fs, order, delay_order)
    lead = order // 2 + 1  # stencil samples after the read position
    nfft = max(int(nfft), sp_fft.next_fast_len(2 * (hist + lead + 1), real=True))
    block = nfft - hist - lead - 1
    half = (order - 1) // 2
    st = _Stencil(
        fs, order, delay_order, degree, hist, lead, np.arange(-half, (order + 1) // 2 + 1), _chebyshev_nodes(degree)
    )
    # a block's work arrays (returned) are held until the next block has made its own, as
    # when the blocks were one loop: freed at once, they went back to the system and every
    # block faulted them in again (4.5 times the page faults, +35 % CPU time for a day's TDI)
    held = None
    for a in range(0, n, block):
        held = _block(out, a, min(a + block, n), history, total, plan, groups, ltt, st)
    del held
    return out


@dataclass(frozen=True)
class _Stencil:
    """What every block of :func:`tdi_columns` shares: the sampling rate [Hz], the Lagrange
    orders of the data and of the delays, the Chebyshev degree of the weights, the input
    samples a block reads before its first output (``hist``) and after an output's read
    position (``lead``), the stencil's ``offsets`` around it and the Chebyshev ``nodes``."""

    fs: float
    order: int
    delay_order: int
    degree: int
    hist: int
    lead: int
    offsets: np.ndarray
    nodes: np.ndarray


def _block(
    out: np.ndarray, a: int, b: int, history: int, total: int, plan, groups: dict, ltt, st: _Stencil
) -> tuple[np.ndarray, np.ndarray]:
    """The outputs ``a:b`` of :func:`tdi_columns` into ``out``: per link group, one FIR per
    Chebyshev power for all its terms applied by FFT, the powers summed with the
    Chebyshev polynomials at the outputs; NaN where a stencil reaches before the data or
    touches a non-finite input.  Returns the block's largest work arrays (the outputs per
    Chebyshev power and their sum), for the caller to hold until the next block's are made."""
    p0, p1 = history + a, history + b  # output positions in input samples
    i0 = max(0, p0 - st.hist)  # first input sample of the block
    m = p1 - i0 + st.lead  # inputs read (stencils reach `lead` ahead)
    i1 = min(total, i0 + m)
    L = sp_fft.next_fast_len(max(p1 - i0 + st.lead + 1, st.hist + st.lead + st.order + 2), real=True)
    nb = b - a
    taps, tq = _block_taps(plan, ltt, p0, p1, st)
    j0 = p0 - i0  # block index of the first output
    spectra: dict = {}  # (c, column) -> (q, nf) spectrum of the output
    first_ok: dict = {}  # (c, column) -> outputs before it are NaN
    for key, items in groups.items():
        _add_group(spectra, first_ok, items, plan.terms[key], taps, (i0, i1, L, j0, nb), st)
    keys = list(spectra)
    y = sp_fft.irfft(np.stack([spectra[k] for k in keys]), L, axis=-1)[..., j0 + st.lead : j0 + st.lead + nb]
    res = np.einsum("jqn,qn->jn", y, tq)
    for r, k in enumerate(keys):
        if first_ok[k] > 0:
            res[r, : min(first_ok[k], nb)] = np.nan
        if (k, "mask") in first_ok:
            res[r, first_ok[(k, "mask")]] = np.nan
        out[k[0], k[1], a:b] = res[r]
    return y, res


def _block_taps(plan, ltt, p0: int, p1: int, st: _Stencil) -> tuple[dict, np.ndarray]:
    """Per delay chain, the integer shift and the Chebyshev coefficients of the Lagrange
    weights over the block of output positions ``p0:p1`` [input samples] (all chains at
    once, from the nested delays at the Chebyshev nodes), and the Chebyshev polynomials at
    the outputs ``(q, nb)``."""
    # Chebyshev nodes of the block (positions in input samples) and nested delays there
    centre, halfw = (p0 + p1 - 1) / 2, max((p1 - 1 - p0) / 2, 0.5)
    pos = centre + halfw * st.nodes
    delays = _nested_delays(plan.chains, ltt, pos, st.fs, st.delay_order)
    u = (np.arange(p0, p1) - centre) / halfw
    tq = np.polynomial.chebyshev.chebvander(u, st.degree).T  # (q, nb)
    # per chain: integer shift and Chebyshev coefficients of the weights (all chains at once)
    delayed = [chain for chain in plan.chains if chain]
    shifts = -np.stack([delays[chain] for chain in delayed]) * st.fs  # (chains, nodes): read at pos + shift
    s_ints = np.floor(shifts.mean(axis=1)).astype(np.int64)
    w = lagrange_weights((shifts - s_ints[:, None]).ravel(), st.order)  # (order + 1, chains * nodes)
    w = w.reshape(st.order + 1, len(delayed), st.degree + 1).transpose(2, 1, 0)  # (nodes, chains, order + 1)
    A = _chebyshev_coefficients(w, st.degree)  # (q, chains, order + 1)
    return {chain: (int(s_ints[i]), A[:, i]) for i, chain in enumerate(delayed)}, tq


def _add_group(spectra: dict, first_ok: dict, items: list, terms, taps: dict, span: tuple, st: _Stencil) -> None:
    """The contributions of one link group's columns ``items`` to the outputs' spectra, and
    where their outputs are NaN (``first_ok``, with a ``(key, "mask")`` entry where a
    stencil touches a non-finite input); ``span`` is the block's ``(i0, i1, L, j0, nb)``."""
    i0, i1, L, j0, nb = span
    rows = np.stack([s[i0:i1] for _, s in items])
    finite = np.isfinite(rows)
    counts = None  # per row, the non-finite inputs before each block index (once per row, not per term)
    if not finite.all():
        rows = np.where(finite, rows, 0.0)
        counts = np.zeros((rows.shape[0], rows.shape[1] + 1), dtype=np.int64)
        np.cumsum(~finite, axis=1, out=counts[:, 1:])
    Xg = sp_fft.rfft(rows, L, axis=-1)
    for c, poly in terms:
        H, reach, read_shifts = _group_filter(poly, taps, L, st)
        for r, (col, _) in enumerate(items):
            k = (c, col)
            contrib = H * Xg[r]
            spectra[k] = contrib if k not in spectra else spectra[k] + contrib
            first_ok[k] = max(first_ok.get(k, 0), reach - j0)
            if counts is not None and counts[r, -1]:
                nan_at = _non_finite_reads(counts[r], read_shifts, st.offsets, j0, nb)
                if nan_at is not None:
                    first_ok[(k, "mask")] = nan_at | first_ok.get((k, "mask"), False)


def _group_filter(poly, taps: dict, L: int, st: _Stencil) -> tuple[np.ndarray, int, list]:
    """One FIR per Chebyshev power for all terms ``poly`` (factor, delay chain) of a link
    (output ``j`` reads ``x[j + lead - d]``), as spectra of length ``L``; with the reach of
    its stencils before the read position [samples] and their integer shifts (0: undelayed)."""
    h = np.zeros((st.degree + 1, L))
    reach, read_shifts = 0, []
    for f, chain in poly:
        if not chain:
            h[0, st.lead] += f
            read_shifts.append(0)
            continue
        s_int, A = taps[chain]
        h[:, st.lead - s_int - st.offsets] += f * A
        reach = max(reach, -(s_int + st.offsets[0]))
        read_shifts.append(s_int)
    return sp_fft.rfft(h, L, axis=-1), reach, read_shifts


def _non_finite_reads(counts, shifts, offsets, j0, nb):
    """Outputs (``nb`` from block index ``j0``) whose stencils at integer shifts ``shifts``
    (0: the undelayed read) touch a non-finite input; ``counts[i]``: the non-finite inputs
    before block input index ``i`` (a running count, ``size + 1`` long).  None when no
    stencil reaches one (a stream's tail holds the few NaN a delayed input starts with, far
    before the reads of its outputs)."""
    size = counts.size - 1
    lo_read = j0 + min(shifts) + min(offsets[0], 0)  # the earliest input any output reads
    hi_read = j0 + nb + max(shifts) + max(offsets[-1], 0)  # one past the latest
    if counts[min(max(hi_read, 0), size)] == counts[min(max(lo_read, 0), size)]:
        return None
    j = np.arange(j0, j0 + nb)
    hit = np.zeros(nb, dtype=bool)
    for s in shifts:
        lo, hi = (j + s, j + s + 1) if s == 0 else (j + s + offsets[0], j + s + offsets[-1] + 1)
        hit |= counts[np.clip(hi, 0, size)] > counts[np.clip(lo, 0, size)]
    return hit

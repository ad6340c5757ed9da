"""Witness search: which series built from the telemetry explain the fit residual?

(docs/diagnostics.md), in the spirit of LIGO's brute-force coherence tool.  A
generic library of candidate witnesses (:func:`witness_library`) is built from the DWS
readouts, ``w = -DWS / c`` for each of the 12 channels (6 MOSAs x phi, eta):

- ``dws``: each channel placed on each of the six links, undelayed and delayed by one and
  two light travel times of that link;
- ``derivative``: the time derivative of each channel on each link, undelayed and delayed
  by one light travel time;
- ``product``: ``d/dt (a b)`` for the angle pairs of each MOSA (phi phi, eta eta, phi eta,
  angles integrated from the DWS), on the MOSA's rx and tx placements;
- ``time``: ``(t - t_mid) / T w`` on the rx and tx placements (a drift);
- ``step``: ``H(t - t_s) w`` on the rx and tx placements, ``t_s`` at the segment
  boundaries and midpoints (a step).

Each witness goes through TDI with the static-arm frequency response of its link
(:func:`ttlcore.tdi.combinations.link_responses`, with the extra delay as a phase factor) - exact for
static arms and good to ``2 pi f dtau ~ 1e-3`` over a segment for Keplerian ones, ample for
ranking - and is compared with the *whitened* fit residual ``L^H r`` (the same noise model
as the adequacy test).  Per band ``g`` and witness ``x`` with whitened TDI spectrum ``u``:

    b_g = sum_{s, f in g} u^H r,   n_g = sum |u|^2,   rr_g = sum |r|^2,
    delta_chi2_g = 2 (Re b_g)^2 / n_g,      coherence_g = |b_g|^2 / (n_g rr_g),

the drop in chi^2 when the witness is added alone with one real coefficient per band,
and the band-averaged coherence (any phase).  The search needs no noise level: the
coherence is scale-free.
"""

from __future__ import annotations

import re

import numpy as np

from ..conventions import ANGLES, LINKS, MOSAS, C, reverse
from ..effects.drift import Drift
from ..effects.registry import make_effects, parse_effect_spec
from ..effects.step import Step
from ..effects.witness import WitnessEffect
from ..estimate.spectra import segment_fft, window
from ..tdi.combinations import AET_MATRIX, MICHELSON, link_responses


def _responses(f, ltt_mean) -> np.ndarray:
    """A, E, T response to a unit signal on each link: (m, 3, 6)."""
    h = np.stack([link_responses(c, f, ltt_mean) for c in MICHELSON])  # (3, 6, m)
    return np.einsum("ia,alm->mil", AET_MATRIX, h)


def witness_library(tm, dg) -> tuple[list[dict], dict]:
    """The witness descriptions and the raw segment spectra they are built from.

    Parameters
    ----------
    tm : Telemetry
    dg : :class:`ttlcore.diagnose.whitened.WhitenedData`
        Gives the segments (times, length, window, bins) of the residual spectra.

    Returns
    -------
    list of dict
        ``{"name", "family", "series", "link", "delay" [s], "derivative"}``.
    dict
        ``series key -> spectra (S, m)`` (4-Hz telemetry over the residual's segments).
    """
    grid = dg.grid
    fs = tm.fs
    t = tm.t0 + np.arange(tm.size) / fs
    spectra = _spectra_on_segments(tm, dg, t)
    ltt = dict(zip(LINKS, dg.tdi.ltt_mean))
    raw: dict = {}
    lib: list[dict] = []
    # DWS gaps (NaN) at zero: the angles, integrated from the DWS, hold still over a gap
    vel = {"phi": np.nan_to_num(np.asarray(tm.dws_phi)), "eta": np.nan_to_num(np.asarray(tm.dws_eta))}
    angles = {a: np.cumsum(vel[a], axis=1) / fs for a in ANGLES}
    t_mid = 0.5 * (t[0] + t[-1])
    T = max(t[-1] - t[0], 1.0)
    boundaries = list(grid.seg_t0[1:]) + [t0 + grid.seg_duration / 2 for t0 in grid.seg_t0]
    for m in MOSAS:
        k = MOSAS.index(m)
        sides = (("rx", m, 0.0), ("tx", reverse(m), ltt[reverse(m)]))
        for a in ANGLES:
            key = f"{m}.{a}"
            w = -vel[a][k] / C
            raw[key] = spectra(w)
            for link in LINKS:
                lib += _dws_witnesses(key, link, ltt[link])
            raw[f"time {key}"] = spectra((t - t_mid) / T * w)
            for side, link, dl in sides:
                lib.append(
                    {
                        "name": f"t x dws {key} ({side})",
                        "family": "time",
                        "series": f"time {key}",
                        "link": link,
                        "delay": dl,
                        "derivative": False,
                        "spec": Drift(mosas=m, angles=a, sides=side).spec(),
                    }
                )
                for ts in boundaries:
                    skey = f"step {ts:.0f} {key}"
                    if skey not in raw:
                        on = t >= ts
                        raw[skey] = spectra(on * w, like=(raw[key], on))
                    lib.append(_step_witness(key, (m, a, side), link, dl, ts, tm.t0))
        for pair in ("phiphi", "etaeta", "phieta"):
            a, b = pair[:3], pair[3:]
            x = -(vel[a][k] * angles[b][k] + angles[a][k] * vel[b][k]) / C
            key = f"{m}.{pair}"
            raw[key] = spectra(x)
            for side, link, dl in sides:
                lib.append(
                    {
                        "name": f"d/dt({a} {b}) {m} ({side})",
                        "family": "product",
                        "series": key,
                        "link": link,
                        "delay": dl,
                        "derivative": False,
                        "spec": witness_spec(key, link, 0 if side == "rx" else 1),
                    }
                )
    return lib, raw


def _spectra_on_segments(tm, dg, t: np.ndarray):
    """``spectra(x) -> (S, m)``: a telemetry-rate series ``x`` on the residual's segments,
    windowed as the data (its valid samples: its gaps, grown by the TDI's reach), at the
    residual's frequencies (interpolated).  ``spectra(on * w, like=(spectra(w), on))`` for a
    series switched by the boolean ``on`` (a step witness): only the segments where ``on``
    changes are transformed (the others are ``w``'s spectra or zero; a day's 84 step
    witnesses took two thirds of the library's transforms).

    A witness is windowed exactly as the data it is compared with, or a gap in the data
    would leave the witness' power there unmatched (and a NaN in it would blank the search).
    """
    grid = dg.grid
    fs = tm.fs
    L = int(round(grid.seg_duration * fs))
    win = window(dg.context.settings.window, L)
    k_dec = np.clip(np.round((t - grid.t0) * grid.fs).astype(int), 0, grid.mask.size - 1)
    valid = grid.mask[k_dec]

    def spectra(x, like=None):
        out = np.zeros((len(grid.seg_t0), grid.f.size), dtype=complex)
        x = np.where(valid, np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
        for i, t0 in enumerate(grid.seg_t0):
            i0 = int(round((t0 - tm.t0) * fs))
            a, b = max(i0, 0), min(i0 + L, tm.size)
            if like is not None and b > a:
                # x = on * w: a segment where ``on`` holds throughout is w's own segment (the
                # same samples, the same spectrum), one where it never holds is zero
                on = like[1][a:b]
                if on.all():
                    out[i] = like[0][i]
                    continue
                if not on.any():
                    continue
            seg = np.zeros(L)
            if b > a:
                seg[a - i0 : b - i0] = x[a:b]
            f, X = segment_fft(seg, fs, win, workers=None)
            out[i] = np.interp(grid.f, f, X.real) + 1j * np.interp(grid.f, f, X.imag)
        return out

    return spectra


def _dws_witnesses(key: str, link: str, ltt: float) -> list[dict]:
    """The DWS series ``key`` placed on ``link`` (light travel time ``ltt`` [s]): as is,
    delayed one or two light travel times, and its derivative, as is or delayed once."""
    lib = []
    for n_delay in (0, 1, 2):
        lib.append(
            {
                "name": f"dws {key} on {link}" + (f" delayed {n_delay}L" if n_delay else ""),
                "family": "dws",
                "series": key,
                "link": link,
                "delay": n_delay * ltt,
                "derivative": False,
                "spec": witness_spec(key, link, n_delay),
            }
        )
    for n_delay in (0, 1):
        lib.append(
            {
                "name": f"d/dt dws {key} on {link}" + (" delayed 1L" if n_delay else ""),
                "family": "derivative",
                "series": key,
                "link": link,
                "delay": n_delay * ltt,
                "derivative": True,
                "spec": witness_spec(key, link, n_delay, derivative=True),
            }
        )
    return lib


def _step_witness(key: str, place: tuple, link: str, dl: float, ts: float, t0: float) -> dict:
    """The step witness of DWS series ``key`` at time ``ts`` [s] (``t0``: the telemetry's
    start [s]) on one side ``place = (mosa, angle, side)``, read on ``link`` delayed ``dl`` [s]."""
    m, a, side = place
    return {
        "name": f"H(t - {(ts - t0) / 3600:.1f} h) x dws {key} ({side})",
        "family": "step",
        "series": f"step {ts:.0f} {key}",
        "link": link,
        "delay": dl,
        "derivative": False,
        "t_step": float(ts),
        "spec": Step(mosas=m, angles=a, sides=side, t_step=float(round(ts))).spec(),
    }


def witness_search(tm, dg, model, top: int = 5, coherence_of: int = 4) -> dict:
    """Rank the witness library against ``model``'s whitened residual, per band.

    Returns
    -------
    dict
        ``{"n_witnesses", "bands": [{"f_lo", "f_hi", "top": [{"name", "family",
        "delta_chi2", "coherence"}]}], "overall": [...], "coherence_spectra": {...}}``;
        each ``overall`` entry holds ``peak_frequency`` [Hz] and ``peak_coherence``, the
        maximum of its coherence with the residual smoothed over ~2 % of ``f`` (30 log bins
        per decade);
        ``overall`` ranks by the sum of the per-band delta chi^2 (divided by the segments'
        variance factor, so that a witness unrelated to the residual gives about one per
        band).
    """
    lib, raw = witness_library(tm, dg)
    H = _responses(dg.grid.f, dg.tdi.ltt_mean)  # (m, 3, 6)
    hw = np.matmul(dg.noise.Lh, H)  # whitened responses (m, 3, 6)
    r = model.residual_w  # (S, m, 3)
    g_link = np.einsum("mil,smi->sml", hw.conj(), r)  # (S, m, 6)
    n_link = np.sum(np.abs(hw) ** 2, axis=1)  # (m, 6)
    G = dg.grid.G
    bidx = dg.grid.band_index
    onehot = np.zeros((dg.grid.f.size, G))
    onehot[np.arange(dg.grid.f.size), bidx] = 1.0
    rr = np.einsum("smi,mg->g", np.abs(r) ** 2, onehot)
    omega = 2 * np.pi * dg.grid.f
    dchi2 = np.zeros((len(lib), G))
    coh = np.zeros((len(lib), G))
    per_series = _SeriesProducts(raw, g_link)
    for i, w in enumerate(lib):
        b, n = _witness_products(w, per_series, n_link, omega)
        bsum = b @ onehot
        nsum = n @ onehot
        with np.errstate(invalid="ignore", divide="ignore"):
            dchi2[i] = np.where(nsum > 0, 2 * bsum.real**2 / nsum, 0.0) / dg.grid.kappa
            coh[i] = np.where(nsum > 0, np.abs(bsum) ** 2 / (nsum * rr), 0.0)
    bands = _band_tops(lib, dchi2, coh, dg.grid.edges, top)
    total = dchi2.sum(axis=1)
    order = np.argsort(-total)[:top]
    overall = [
        {
            "name": lib[i]["name"],
            "family": lib[i]["family"],
            "spec": lib[i]["spec"],
            "delta_chi2": float(total[i]),
            "best_band": [
                float(dg.grid.edges[int(np.argmax(dchi2[i]))]),
                float(dg.grid.edges[int(np.argmax(dchi2[i])) + 1]),
            ],
            "coherence_max": float(coh[i].max()),
        }
        for i in order
    ]
    # coherence spectra of the top witnesses (running mean over ~2 % of f): the frequency of
    # each one's peak, and the curves of the first ``coherence_of`` for the figure
    rrf = (np.abs(r) ** 2).sum(axis=(0, 2))
    spectra = {}
    for k, i in enumerate(order):
        w = lib[i]
        b, n = _witness_products(w, per_series, n_link, omega)
        curve = _smoothed_coherence(dg.grid.f, b, n, rrf)
        overall[k].update(_coherence_peak(dg.grid.f, curve))
        if k < coherence_of:
            spectra[w["name"]] = curve
    return {
        "n_witnesses": len(lib),
        "families": sorted({w["family"] for w in lib}),
        "bands": bands,
        "overall": overall,
        "coherence_spectra": {"f": _log_grid(dg.grid.f).tolist(), "curves": spectra},
    }


class _SeriesProducts:
    """``products[key]``: the sums over segments of the raw series ``key`` with the residual
    on each link and its power, ``(B (m, 6), P (m,))``, computed when asked for and kept for
    the last few keys only (the witnesses of one series follow each other in the library;
    all 126 of a day's would hold ~200 MB through the search)."""

    KEEP = 4

    def __init__(self, raw: dict, g_link: np.ndarray):
        self.raw, self.g_link = raw, g_link
        self._kept: dict = {}

    def __getitem__(self, key: str) -> tuple:
        hit = self._kept.get(key)
        if hit is None:
            X = self.raw[key]
            hit = (np.einsum("sm,sml->ml", np.conj(X), self.g_link), np.sum(np.abs(X) ** 2, axis=0))
            if len(self._kept) >= self.KEEP:
                self._kept.pop(next(iter(self._kept)))
            self._kept[key] = hit
        return hit


def _witness_products(w: dict, per_series, n_link: np.ndarray, omega: np.ndarray) -> tuple:
    """Per frequency bin, the products of witness ``w`` (placed on its link, derived and
    delayed as it says) with the whitened residual, summed over segments, and its norm."""
    B, P = per_series[w["series"]]
    li = LINKS.index(w["link"])
    b = B[:, li]
    n = P * n_link[:, li]
    if w["derivative"]:  # conj(i omega X) = -i omega conj(X)
        b = b * (-1j * omega)
        n = n * omega**2
    if w["delay"]:  # conj(X exp(-i omega delay)) = conj(X) exp(+i omega delay)
        b = b * np.exp(1j * omega * w["delay"])
    return b, n


def _band_tops(lib: list[dict], dchi2: np.ndarray, coh: np.ndarray, edges, top: int) -> list[dict]:
    """Per band (``edges`` [Hz]), the ``top`` witnesses by delta chi^2 and their coherence."""
    bands = []
    for g in range(dchi2.shape[1]):
        order = np.argsort(-dchi2[:, g])[:top]
        bands.append(
            {
                "f_lo": float(edges[g]),
                "f_hi": float(edges[g + 1]),
                "top": [
                    {
                        "name": lib[i]["name"],
                        "family": lib[i]["family"],
                        "spec": lib[i]["spec"],
                        "delta_chi2": float(dchi2[i, g]),
                        "coherence": float(coh[i, g]),
                    }
                    for i in order
                ],
            }
        )
    return bands


def _coherence_peak(f: np.ndarray, curve: list) -> dict:
    """The frequency [Hz] (on the log grid of ``f``) and value of the peak of a smoothed
    coherence ``curve`` (None where undefined)."""
    vals = np.array([-1.0 if v is None else v for v in curve])
    return {"peak_frequency": float(_log_grid(f)[int(np.argmax(vals))]), "peak_coherence": float(vals.max())}


def witness_spec(source: str, link: str, n_delay: int = 0, derivative: bool = False) -> str:
    """The spec of a library witness as an effect (:class:`ttlcore.effects.witness.WitnessEffect`):
    ``witness:source=12.phi,link=23,delay=1``."""
    opts: dict = {"source": source}
    if link != source.split(".")[0]:
        opts["link"] = link
    if n_delay:
        opts["delay"] = n_delay
    if derivative:
        opts["derivative"] = 1
    return WitnessEffect(**opts).spec()


def witness_candidates(report: dict, top: int = 3, modules=()) -> list:
    """Effects to try from a witness search (:func:`witness_search`).

    The overall ranking's first ``top`` witnesses as witness effects (time and step
    witnesses as ``drift`` and ``step`` restricted to their channel and side); for the
    DWS channel and link of the best DWS witness, frequency-dependent couplings with a
    searched pole pair and with a searched real pole, each placed undelayed and after one
    and two light travel times (a coupling's phase and a delay look alike over a band, and
    the library ranks the delays of a path whose constant part the linear TTL model already
    absorbs - its own TTL placement - below the others: the evidence decides); for the
    second DWS channel and link in the ranking, the pole pair at its delay."""

    specs: list = []
    placements: list = []
    for w in report.get("overall", []):
        spec = w.get("spec")
        if spec and w["family"] == "step":
            # the library's step times are a coarse grid (a pointer to where the step is):
            # the candidate's time is searched (step_time_search) on its channel and side
            name, _, opts = spec.partition(":")
            spec = name + ":" + ";".join(o for o in re.split(r"[;,]", opts) if not o.startswith("t_step="))
        if spec and len(specs) < top and spec not in specs:
            specs.append(spec)
        if w["family"] in ("dws", "derivative") and spec:
            opts = parse_effect_spec(spec, modules)[0].options
            key = (opts["source"], opts.get("link") or opts["source"].split(".")[0])
            if key not in [p[:2] for p in placements]:
                placements.append((*key, int(opts.get("delay") or 0)))
    for i, (src, link, n) in enumerate(placements[:2]):
        where = f"source={src}" + (f",link={link}" if link != src.split(".")[0] else "")
        for d in (0, 1, 2) if i == 0 else (n,):
            specs.append(f"fd-coupling:{where}" + (f",delay={d}" if d else ""))
        if i == 0:
            specs += [f"fd-coupling:{where}" + (f",delay={d}" if d else "") + ",filter=pole1" for d in (0, 1, 2)]
            # a coupling that changes in time (composition with a drift)
            specs.append(f"witness:{where}" + (f",delay={n}" if n else "") + ",vary=drift")
    return make_effects(list(dict.fromkeys(specs)), modules)


def _log_grid(f, per_decade: int = 30):
    return np.geomspace(f[0], f[-1], int(np.log10(f[-1] / f[0]) * per_decade) + 1)


def _smoothed_coherence(f, b, n, rr, per_decade: int = 30) -> list:
    grid = _log_grid(f, per_decade)
    idx = np.clip(np.searchsorted(grid, f), 0, grid.size - 1)
    out: list = []
    for k in range(grid.size):
        sel = idx == k
        if not sel.any():
            out.append(None)
            continue
        den = n[sel].sum() * rr[sel].sum()
        out.append(float(np.abs(b[sel].sum()) ** 2 / den) if den > 0 else None)
    return out

"""Helpers shared by the diagnosis tests: injected level against the noise model, the advice
followed as printed."""

from __future__ import annotations

import shlex

import numpy as np

from ttlcore.diagnose.diagnoser import diagnose
from ttlcore.effects import split_effects
from ttlcore.estimate.fit import default_band_edges
from ttlcore.estimate.noise_psd import tdi_noise_csd
from ttlcore.estimate.spectra import welch_asd
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.data import compute_tdi


def injected_asd_ratio(tm, injected: np.ndarray, band=(3e-3, 0.8), n_bands: int = 8) -> np.ndarray:
    """Per band, the largest over A, E, T of the band-averaged ASD ratio of the injected
    signal's TDI (Welch, 1 h Hann segments) to the analytic secondary noise (independent of
    the diagnosis code: its own TDI call, Welch estimate and the analytic CSD)."""
    only = Telemetry(t0=tm.t0, fs=tm.fs, eta=injected, dws_phi=tm.dws_phi, dws_eta=tm.dws_eta, ltt=tm.ltt)
    td = compute_tdi(only, names=()).to_aet()
    ok = np.isfinite(td.data).all(axis=0)
    f, asd = welch_asd(td.data[:, ok], td.fs, nperseg=int(3600 * td.fs))
    edges = default_band_edges(band, n_bands)
    sel = (f >= band[0]) & (f <= band[1])
    model = np.real(np.einsum("mii->mi", tdi_noise_csd(f[sel], td.ltt_mean)))
    ratio = asd[:, sel] ** 2 / model.T
    out = np.zeros(n_bands)
    for g in range(n_bands):
        b = (f[sel] >= edges[g]) & (f[sel] < edges[g + 1])
        out[g] = np.sqrt(np.max(np.mean(ratio[:, b], axis=1))) if b.any() else 0.0
    return out


def follow(tm, C, max_steps: int = 3, witnesses: bool = False) -> list[dict]:
    """``diagnose`` of ``tm`` (true coefficients ``C``) and its printed ``--effects`` option
    (split as the command line does), at most ``max_steps`` times: the reports (JSON)."""
    effects, reports = ["linear-ttl"], []
    for _ in range(max_steps):
        rep = diagnose(tm, effects, truth_coefficients=C, witnesses=witnesses).to_json()
        reports.append(rep)
        opt = (rep["recommendation"] or {}).get("option")
        if not opt:
            break
        effects = split_effects(shlex.split(opt)[1])
    return reports

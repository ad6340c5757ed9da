"""Figure of the transient finder (``ttl diagnose --out``): the time-frequency map of the
whitened residual per channel (docs/diagnostics.md, "Signals, glitches, gaps and changing
noise")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .batch import _save


def plot_time_frequency(tf, transients: dict, path) -> Path:
    """One panel per channel (A, E, T): chi2/dof of each tile and band over the noise model
    (log colour, 1 = noise), tiles at their centre [h], bands at their edges [Hz]; each
    event outlined and labelled with its class, missing data shaded.

    Parameters
    ----------
    tf : ttlcore.diagnose.transients.TimeFrequencyMap
    transients : dict
        The report's ``transients`` part (events, gaps).
    path : path-like
    """
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure

    ratio = tf.chi2 / tf.dof[None, None, :]
    t_edges = np.concatenate([tf.t_mid - 0.5 * tf.hop, [tf.t_mid[-1] + 0.5 * tf.hop]]) / 3600.0
    vmax = max(10.0, float(np.nanpercentile(ratio, 99.9)))
    fig = Figure(figsize=(10, 8), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    for c, (ax, name) in enumerate(zip(axes, ("A", "E", "T"))):
        m = ax.pcolormesh(t_edges, tf.edges, ratio[c].T, norm=LogNorm(0.3, vmax), cmap="magma", shading="flat")
        ax.set_yscale("log")
        ax.set_ylabel(f"{name}  f [Hz]")
        for e in transients.get("events", []):
            ax.axvspan(e["t_start"] / 3600, e["t_stop"] / 3600, fill=False, ec="cyan", lw=1.2)
            if c == 0:
                ax.text(e["t_start"] / 3600, tf.edges[-1], e["class"], color="cyan", fontsize=8, va="top")
            tr = np.asarray(e["track"])
            if tr.size:
                ax.plot(tr[:, 0] / 3600, tr[:, 2], "c.", ms=4)
        for a, b in transients.get("gaps", []):
            ax.axvspan(a / 3600, b / 3600, color="0.5", alpha=0.5)
    axes[-1].set_xlabel("time [h]")
    fig.colorbar(m, ax=axes, label="chi2/dof of the whitened residual (1: noise model)")
    fig.suptitle(f"whitened residual, {tf.duration:.0f}-s Hann tiles (hop {tf.hop:.0f} s)")
    return _save(fig, Path(path))

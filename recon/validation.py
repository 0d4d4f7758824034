"""Validation figures: NRMSE of simulated vs measured response, PNG overlays."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def nrmse(y_sim, y_meas) -> float:
    """rms(y_sim - y_meas) / rms(y_meas - mean(y_meas)); inf if the simulation diverged."""
    y_sim = np.asarray(y_sim, float)
    y_meas = np.asarray(y_meas, float)
    if not np.all(np.isfinite(y_sim)):
        return float("inf")
    den = np.sqrt(np.mean((y_meas - y_meas.mean()) ** 2))
    return float(np.sqrt(np.mean((y_sim - y_meas) ** 2)) / den) if den > 0 else float("inf")


def plot_overlay(path, t, y_meas, y_sim, z_meas=None, z_sim=None, title=""):
    """Time history (measured vs simulated y) and hysteresis loop (z vs y) to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    axes[0].plot(t, 1e3 * y_meas, lw=0.8, label="measured")
    axes[0].plot(t, 1e3 * y_sim, lw=0.8, ls="--", label="simulated")
    axes[0].set_xlabel("t [s]")
    axes[0].set_ylabel("y [mm]")
    axes[0].legend(loc="upper right")
    if z_meas is not None:
        axes[1].plot(1e3 * y_meas, z_meas, lw=0.6, label="from measurement")
    if z_sim is not None:
        axes[1].plot(1e3 * y_sim, z_sim, lw=0.6, ls="--", label="simulated")
    axes[1].set_xlabel("y [mm]")
    axes[1].set_ylabel("z/m [m/s^2]")
    axes[1].legend(loc="upper left")
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path

"""Figures (PNG, matplotlib with the Agg backend): the one place the application draws static plots."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a window: before pyplot is imported
import matplotlib.pyplot as plt  # noqa: E402

from recon.validation import hysteretic_force_from_data  # noqa: E402
from shakerlab.output_files import atomic_output, inside  # noqa: E402


def savefig(fig, path, dpi: int = 90) -> Path:
    """Save ``fig`` as ``path`` through a temporary file (an existing file is replaced only by a
    complete one) and close it."""
    path = Path(path)
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)
    return path


def save(fig, path, title: str = "", dpi: int = 90) -> Path:
    """Title, lay out and save ``fig`` as ``path`` (its directory made if missing)."""
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return savefig(fig, path, dpi=dpi)


def plot_overlay(path, t, y_meas, y_sim, z_meas=None, z_sim=None, title=""):
    """Time history (measured vs simulated y) and hysteresis loop (z vs y) to a PNG."""
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
    return save(fig, path, title)


def write_validation_plots(result, run, outdir):
    """PNG overlays of measured vs simulated response on every validation stage (the fitted
    stage when there is none) and the fitted stage's hysteresis loop; returns the paths."""
    outdir = Path(outdir)
    paths = []
    names = [n for n in run.stages if n.startswith("validation")] or [result.settings.nonlinear_stage]
    tuning = result.settings.tuning       # the input and the start as the validation made them
    for name in names:
        st = run.stage(name)
        u = result.model.stage_input(st, tuning=tuning)
        ysim, _, zsim = result.model.simulate(st.t - st.t[0], u, initial=result.model.stage_start(st, u, tuning=tuning))
        paths.append(plot_overlay(inside(outdir, name, ".png"), st.t, st.y, ysim, z_sim=zsim,
                                  title=f"{name}: measured vs reconstructed (NRMSE {result.validation['per_stage'].get(name, float('nan')):.3g})"))
    sig = result.signals
    z_meas = hysteretic_force_from_data(result.model, sig["y"], sig["dy"], sig["ddy"], sig["u"])
    st = run.stage(result.settings.nonlinear_stage)
    u = result.model.stage_input(st, tuning=tuning)
    ysim, _, zsim = result.model.simulate(st.t - st.t[0], u, initial=result.model.stage_start(st, u, tuning=tuning))
    half = (st.t.size - sig["t"].size) // 2
    paths.append(plot_overlay(outdir / "nonlinear_loop.png", sig["t"], sig["y"], ysim[half:half + sig["t"].size],
                              z_meas=z_meas, z_sim=zsim[half:half + sig["t"].size],
                              title="fitted stage: z from the measurement vs simulated"))
    return paths


def plot_force_law(path, t, x, F_meas, F_pred, title=""):
    """A component test: the force's time history and the force-displacement loop, recorded
    and predicted by a constitutive law, to a PNG."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    axes[0].plot(t, F_meas, lw=0.8, label="recorded")
    axes[0].plot(t, F_pred, lw=0.8, ls="--", label="law")
    axes[0].set_xlabel("t [s]")
    axes[0].set_ylabel("F [N]")
    axes[0].legend(loc="upper right")
    axes[1].plot(1e3 * x, F_meas, lw=0.6, label="recorded")
    axes[1].plot(1e3 * x, F_pred, lw=0.6, ls="--", label="law")
    axes[1].set_xlabel("x [mm]")
    axes[1].set_ylabel("F [N]")
    axes[1].legend(loc="upper left")
    return save(fig, path, title)

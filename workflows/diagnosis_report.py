"""Figures of a diagnosis: before/after overlays, residual spectra, restoring-force residual
surfaces over (y, y'), NRMSE per stage; plus diagnosis.json."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from recon.welch import welch

from recon.diagnosis import rank
from recon.diagnosis.locate import equation_residual, stage_derivatives
from workflows.figures import plt, savefig
from shakerlab.jsonsafe import clean
from shakerlab.output_files import write_text


def write_report(diag, run, outdir: Path) -> list[Path]:


    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    data = rank.prepare(run, diag.baseline.baseline)
    before, after = diag.null.sims, diag.best_fit.sims    # simulated by the diagnosis's own fits
    paths = []
    # overlays and residual spectra, one row per stage
    fig, axes = plt.subplots(len(data), 2, figsize=(12, 3.2 * len(data)), squeeze=False)
    for i, (d, yb, ya) in enumerate(zip(data, before, after)):
        ax = axes[i, 0]
        ax.plot(d.t, 1e3 * d.y, lw=0.7, label="recorded")
        ax.plot(d.t, 1e3 * yb, lw=0.7, ls="--", label="baseline (refitted)")
        ax.plot(d.t, 1e3 * ya, lw=0.7, ls=":", label="augmented")
        ax.set_title(f"{d.name}: NRMSE {diag.null.nrmse[d.name]:.3g} -> {diag.best_fit.nrmse[d.name]:.3g}")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("y' [mm/s]" if d.order else "y [mm]")     # the recorded quantity (rank.StageData)
        ax.legend(loc="upper right", fontsize=7)
        ax = axes[i, 1]
        fs = 1.0 / d.dt
        n = min(1024, d.y.size)
        for r, lab in ((d.y, "recorded y"), (d.y - yb, "residual, baseline"), (d.y - ya, "residual, augmented")):
            if np.all(np.isfinite(r)):
                f, p = welch(r, fs=fs, nperseg=n)
                ax.semilogy(f, p, lw=0.7, label=lab)
        ax.set_xlabel("f [Hz]")
        ax.set_ylabel("PSD [(m/s)^2/Hz]" if d.order else "PSD [m^2/Hz]")
        ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    p = outdir / "overlays_and_spectra.png"
    savefig(fig, p, dpi=80)
    paths.append(p)
    # restoring-force residual surfaces over (y, y'), before and after
    derivs = stage_derivatives(run, data)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, model, title in ((axes[0], diag.null.model, "baseline (refitted)"), (axes[1], diag.best, "augmented")):
        ys, vs, es = [], [], []
        for d in data:
            y, dy, e, _, frms = equation_residual(model, derivs[d.name])
            ys.append(y)
            vs.append(dy)
            es.append(e / frms)
        y, dy, e = (np.concatenate(a) for a in (ys, vs, es))
        H, xe, ye = np.histogram2d(y, dy, bins=24, weights=e)
        N, _, _ = np.histogram2d(y, dy, bins=[xe, ye])
        with np.errstate(invalid="ignore", divide="ignore"):
            M = np.where(N > 5, H / N, np.nan)
        lim = np.nanmax(np.abs(M)) if np.any(np.isfinite(M)) else 1.0
        im = ax.pcolormesh(1e3 * xe, ye, M.T, cmap="coolwarm", vmin=-lim, vmax=lim)
        fig.colorbar(im, ax=ax, label="mean unexplained force / rms force")
        ax.set_xlabel("y [mm]")
        ax.set_ylabel("y' [m/s]")
        ax.set_title(f"restoring-force residual: {title}")
    fig.tight_layout()
    p = outdir / "restoring_force_residual.png"
    savefig(fig, p, dpi=80)
    paths.append(p)
    # NRMSE per stage
    fig, ax = plt.subplots(figsize=(6, 3.5))
    names = [d.name for d in data]
    x = np.arange(len(names))
    for k, (lab, vals) in enumerate((("baseline as given", diag.fit_before["nrmse"]),
                                     ("baseline refitted", diag.null.nrmse), ("augmented", diag.best_fit.nrmse))):
        ax.bar(x + (k - 1) * 0.27, [vals[n] for n in names], width=0.27, label=lab)
    ax.set_xticks(x, names)
    ax.set_yscale("log")
    ax.set_ylabel("NRMSE")
    ax.legend(fontsize=7)
    fig.tight_layout()
    p = outdir / "nrmse_per_stage.png"
    savefig(fig, p, dpi=80)
    paths.append(p)
    p = outdir / "diagnosis.json"
    write_text(p, json.dumps(clean(diag.to_dict()), indent=1))
    paths.append(p)
    return paths

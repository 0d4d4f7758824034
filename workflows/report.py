"""The reconstruction report of one run (``shakerlab report RUN.h5 -o DIR``).

    from workflows.report import make_report
    info = make_report("run.h5", "report/")     # writes report/index.html, report/*.png, report/result.json

DIR receives a self-contained ``index.html`` (the PNG figures are embedded as
data URIs, so the one file can be mailed; they are also written next to it),
the figures as PNG files and ``result.json`` (the ``shakerlab reconstruct
--json`` object plus ``uncertainty`` and ``report``). The report holds the
recorded stages, the differentiation settings, the identified equation and
parameters with their intervals (:mod:`recon.output_error.uncertainty`), the nonlinear
force Fn against y and the restoring-force surface coloured by kernel cluster,
validation overlays, hysteresis loops at several amplitudes of the nonlinear
stage, and the residual (measured minus simulated response) per stage.

The result is written back into the run file (a new ``entry/results/
reconstruction_NNN`` group with the settings hash of :mod:`workflows.batch`),
unless a stored reconstruction has the same settings hash already, the file
is an ``.npz``, or it was not closed cleanly (the report says which).
"""
from __future__ import annotations

import base64
import contextlib
import html
import json
import os
import secrets
import shutil
import time
from pathlib import Path

import numpy as np

from recon import ReconSettings, progress, reconstruct
from recon.estimator.adequacy import verdict_summary
from recon.library.clustering import cluster
from recon.output_error.uncertainty import (UncertaintySettings, parameter_intervals, reconstruct_capturing,
                                            term_inclusion)
from recon.signals import stage_signals
from recon.validation import nrmse
from workflows.figures import plt, savefig
from shakerlab import __version__
from shakerlab.words import duration_text, nrmse_text, parameter_name, parameter_units
from shakerlab.errors import UserFacingError
from shakerlab.runfile.reader import load_run
from shakerlab.jsonsafe import clean
from shakerlab.output_files import OutputLock, check_directory, inside, write_text
from shakerlab.runfile.results import store_result
from workflows.batch import RESULT_KIND, settings_hash
from workflows.plausibility import warnings_for

CLUSTER_COLOURS = {1: ("tab:red", "AB (h = +1)"), -1: ("tab:blue", "CD (h = -1)"), 0: ("0.6", "BC/DA (h = 0)")}


BANNER_COLOURS = {"good": ("#e6f4ea", "#1e7b34"), "warning": ("#fff4e0", "#a15c00"), "bad": ("#fde8e8", "#b3261e")}
TIMING_NAMES = {"reconstruct": "reconstruction", "term_selection": "term selection",
                "uncertainty": "parameter intervals", "figures": "figures", "validation": "validation",
                "two_stage_polish": "the two stages fitted together"}


# ---------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------

def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    return savefig(fig, path, dpi=90)


def fig_stages(run, path: Path) -> Path:
    names = list(run.stages)
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 2.2 * len(names)), squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        st = run.stages[name]
        k = max(1, st.t.size // 8000)       # enough points for the eye, fast to draw
        ax.plot(st.t[::k], 1e3 * st.y[::k], lw=0.5, label="y (relative)" if st.excitation == "base" else "x")
        if st.excitation == "base":
            ax.plot(st.t[::k], 1e3 * st.channels["x_base"][::k], lw=0.5, alpha=0.7, label="x_base")
        ax.set_ylabel("mm")
        ax.set_title(f"stage {name!r}: {st.t.size} samples at {st.fs:.6g} Hz", fontsize=9)
        ax.legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("t [s]")
    return _save(fig, path)


def nonlinear_force(result, run):
    """(y, y', Fn, h) on the nonlinear stage with the identified c_m, K_m (and 1/m)."""

    s = result.settings
    st = run.stage(s.nonlinear_stage)
    sig = stage_signals(st, deriv=2, window=s.window, order=s.sg_order)
    m = result.model
    y, dy, ddy = sig.y[:3]
    Fn = m.input_gain * sig.u[0] - ddy - m.c_m * dy - m.K_m * y
    return y, dy, Fn, cluster(y, dy), sig


def fig_restoring_force(result, run, path: Path) -> Path:
    y, dy, Fn, h, _ = nonlinear_force(result, run)
    step = max(1, y.size // 6000)
    fig = plt.figure(figsize=(11, 4.5))
    ax = fig.add_subplot(1, 2, 1)
    for k, (col, lab) in CLUSTER_COLOURS.items():
        sel = h[::step] == k
        ax.scatter(1e3 * y[::step][sel], Fn[::step][sel], s=2, c=col, label=lab)
    ax.set_xlabel("y [mm]")
    ax.set_ylabel("Fn [m/s^2] (nonlinear force per unit mass)")
    ax.set_title("Fn vs y by kernel cluster", fontsize=9)
    ax.legend(loc="best", fontsize=7, markerscale=4)
    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    for k, (col, lab) in CLUSTER_COLOURS.items():
        sel = h[::step] == k
        ax3.scatter(1e3 * y[::step][sel], dy[::step][sel], Fn[::step][sel], s=1, c=col, label=lab)
    ax3.set_xlabel("y [mm]")
    ax3.set_ylabel("y' [m/s]")
    ax3.set_zlabel("Fn [m/s^2]")
    ax3.set_title("restoring-force surface Fn(y, y')", fontsize=9)
    return _save(fig, path)


def fig_loops(result, run, path: Path, n_amplitudes: int = 4) -> Path:
    """Restoring force per unit mass (g u - y'' - c y') against y, measured and simulated,
    over a few cycles at several amplitudes of the nonlinear stage."""
    m = result.model
    s = result.settings
    st = run.stage(s.nonlinear_stage)
    _, _, _, _, sig = nonlinear_force(result, run)
    y, dy, ddy = sig.y[:3]
    r_meas = m.input_gain * sig.u[0] - ddy - m.c_m * dy
    u = m.stage_input(st, tuning=s.tuning)
    start = m.stage_start(st, u, tuning=s.tuning) if hasattr(m, "stage_start") else None   # as the validation simulates
    ys, dys, zs = m.simulate(st.t - st.t[0], u, **({"initial": start} if start is not None else {}))
    half = (st.t.size - sig.t.size) // 2
    ys, dys, zs = ys[half:half + sig.t.size], dys[half:half + sig.t.size], zs[half:half + sig.t.size]
    r_sim = m.k_m * ys + m.fn(ys, dys) + zs
    # a few cycles around each chosen time; amplitude taken from the measured envelope
    n = y.size
    f_dom = _dominant_frequency(y, st.dt)
    span = int(min(n // (2 * n_amplitudes), max(3.0 / f_dom, 0.05) / st.dt)) if f_dom > 0 else n // (2 * n_amplitudes)
    centres = np.linspace(span, n - span - 1, n_amplitudes).astype(int)
    fig, ax = plt.subplots(1, 1, figsize=(7, 5))
    cmap = plt.get_cmap("viridis")
    for i, c in enumerate(centres):
        sl = slice(max(c - span // 2, 0), min(c + span // 2, n))
        amp = 0.5 * (np.max(y[sl]) - np.min(y[sl]))
        col = cmap(i / max(n_amplitudes - 1, 1))
        ax.plot(1e3 * y[sl], r_meas[sl], lw=0.7, color=col, label=f"measured, |y| ~ {1e3 * amp:.3g} mm")
        ax.plot(1e3 * ys[sl], r_sim[sl], lw=0.9, ls="--", color=col, alpha=0.8)
    ax.set_xlabel("y [mm]")
    ax.set_ylabel("restoring force per unit mass [m/s^2]")
    ax.set_title("hysteresis loops at several amplitudes (solid measured, dashed simulated)", fontsize=9)
    ax.legend(loc="upper left", fontsize=7)
    return _save(fig, path)


def _dominant_frequency(x, dt) -> float:
    x = np.asarray(x, float) - np.mean(x)
    spec = np.abs(np.fft.rfft(x * np.hanning(x.size)))
    f = np.fft.rfftfreq(x.size, dt)
    spec[0] = 0.0
    return float(f[int(np.argmax(spec))]) if spec.size > 1 else 0.0


def simulated_stages(result, run) -> dict:
    """{stage: (t, y_meas, y_sim)} for every stage the model is compared on."""
    names = [n for n in (result.settings.linear_stage, result.settings.nonlinear_stage) if n in run.stages]
    names += [n for n in run.stages if n.startswith("validation") and n not in names]
    out = {}
    for n in names:
        st = run.stage(n)
        t, ys = result.model.simulate_stage(st, result.settings.tuning)
        out[n] = (t, st.y, ys)
    return out


def fig_validation(sims: dict, result, path: Path) -> list[Path]:
    """Measured vs simulated response on every validation stage (the fitted stage when there is none):
    the whole record and a zoom on its last second."""

    paths = []
    names = [n for n in sims if n.startswith("validation")] or [result.settings.nonlinear_stage]
    for n in names:
        t, ym, ys = sims[n]
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.6), gridspec_kw={"width_ratios": [2, 1]})
        k = max(1, t.size // 8000)
        axes[0].plot(t[::k], 1e3 * ym[::k], lw=0.6, label="measured")
        axes[0].plot(t[::k], 1e3 * ys[::k], lw=0.6, ls="--", label="simulated")
        zoom = t >= t[-1] - 1.0
        axes[1].plot(t[zoom], 1e3 * ym[zoom], lw=0.8, label="measured")
        axes[1].plot(t[zoom], 1e3 * ys[zoom], lw=0.8, ls="--", label="simulated")
        for ax in axes:
            ax.set_xlabel("t [s]")
            ax.set_ylabel("y [mm]")
        axes[0].legend(loc="upper right", fontsize=7)
        axes[1].set_title("last second", fontsize=9)
        fig.suptitle(f"{n}: measured vs simulated from rest (NRMSE {nrmse_text(nrmse(ys, ym))})", fontsize=10)
        paths.append(_save(fig, inside(path.parent, f"{path.stem}_{n}", ".png", option="-o")))
    return paths


def fig_residual(sims: dict, path: Path) -> Path:
    fig, axes = plt.subplots(len(sims), 2, figsize=(11, 2.4 * len(sims)), squeeze=False)
    for row, (n, (t, ym, ys)) in zip(axes, sims.items()):
        r = ys - ym
        k = max(1, t.size // 8000)
        row[0].plot(t[::k], 1e6 * r[::k], lw=0.5)
        row[0].set_ylabel("y_sim - y [um]")
        row[0].set_title(f"{n}: residual (rms {1e6 * np.sqrt(np.mean(r * r)):.3g} um)", fontsize=9)
        dt = float(np.median(np.diff(t)))
        f = np.fft.rfftfreq(r.size, dt)
        a = np.abs(np.fft.rfft((r - r.mean()) * np.hanning(r.size))) * 2 / r.size
        am = np.abs(np.fft.rfft((ym - ym.mean()) * np.hanning(ym.size))) * 2 / ym.size
        row[1].semilogy(f, am + 1e-30, lw=0.5, color="0.6", label="measured y")
        row[1].semilogy(f, a + 1e-30, lw=0.6, label="residual")
        row[1].set_xlim(0, min(f[-1], 200.0))
        row[1].set_ylabel("amplitude [m]")
        row[1].legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("t [s]")
    axes[-1, 1].set_xlabel("frequency [Hz]")
    return _save(fig, path)


# ---------------------------------------------------------------------------
# the report
# ---------------------------------------------------------------------------

def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.6g}"
    return html.escape(str(v))


def _param_rows(d: dict, unc: dict | None) -> list[tuple]:
    """(name, estimate, [low, high], units) for every parameter, named and with units as everywhere
    (shakerlab.words)."""
    p = d["parameters"]
    iv = (unc or {}).get("intervals", {})
    rows = []
    for k in ("c_m", "k_m", "alpha_m", "gamma", "delta", "inv_m", "input_offset", "drive_u2", "drive_hp"):
        if k in p:
            rows.append((k, p[k], (iv.get(k) or [None, None]), parameter_units(k, excitation=d.get("excitation"))))
    for term, v in p.get("fn_m", {}).items():
        rows.append((parameter_name("fn_m", term), v, (iv.get("fn_m", {}).get(term) or [None, None]),
                     parameter_units("fn_m", term)))
    return rows


def verdict_banner(adequacy: dict | None) -> str:
    """The verdict as a coloured banner (id ``verdict``), the same sentence as everywhere."""
    v = verdict_summary(adequacy)
    bg, fg = BANNER_COLOURS[v["level"]]
    return (f"<div id='verdict' class='verdict {v['level']}' style='background:{bg};border-left:6px solid {fg};"
            f"padding:0.6em 1em;margin:1em 0'><b style='color:{fg}'>Verdict: {html.escape(v['label'])}.</b> "
            f"{html.escape(v['text'])}</div>")


def timings_text(timings: dict) -> str:
    """"reconstruction 1 min 03 s, parameter intervals 12 s, figures 4.1 s" (the report's own steps;
    the reconstruction's inner steps when they are all there is)."""
    own = {k: v for k, v in timings.items() if k in ("reconstruct", "term_selection", "uncertainty", "figures")}
    use = own or timings
    return ", ".join(f"{TIMING_NAMES.get(k, k.replace('_', ' '))} {duration_text(v)}" for k, v in use.items()
                     if isinstance(v, (int, float))) + (f"; in all {duration_text(sum(own.values()))}" if own else "")


def render_html(run, d: dict, figures: dict, info: dict) -> str:
    unc = d.get("uncertainty")
    css = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
           "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:3px 8px;"
           "font-size:90%;text-align:right}th{background:#f3f3f3}td:first-child{text-align:left}"
           "pre{background:#f6f6f6;padding:0.6em;overflow-x:auto}img{max-width:100%}")
    h = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>shakerlab report: "
         f"{html.escape(Path(run.source).name)}</title><style>{css}</style></head><body>",
         f"<h1>Reconstruction report: {html.escape(Path(run.source).name)}</h1>",
         verdict_banner(d.get("adequacy")),
         f"<p>Run file <code>{html.escape(run.source)}</code>; {html.escape(d['excitation'])} excitation; "
         f"shakerlab {__version__}; made {html.escape(info['created'])}. {html.escape(info['write_back'])}</p>",
         "<h2>Recorded stages</h2><table><tr><th>stage</th><th>excitation</th><th>fs [Hz]</th><th>samples</th>"
         "<th>duration [s]</th><th>status</th></tr>"]
    for n, st in run.stages.items():
        h.append(f"<tr><td>{html.escape(n)}</td><td>{st.excitation}</td><td>{st.fs:.6g}</td><td>{st.t.size}</td>"
                 f"<td>{st.t[-1] - st.t[0]:.4g}</td><td>{html.escape(str(st.settings.get('status', '')))}</td></tr>")
    h.append("</table>")
    h.append(_img(figures, "stages"))
    h.append("<h2>Differentiation (Savitzky-Golay, chosen from the data)</h2><table><tr><th>step</th><th>window</th>"
             "<th>order</th><th>derivative</th><th>bandwidth [Hz]</th><th>noise level (channel std)</th></tr>")
    diff = d["settings"]["differentiation"]
    for step in ("linear", "nonlinear"):
        c = diff.get(step) or {}
        noise = ", ".join(f"{k} {v:.3g}" for k, v in (c.get("noise_level") or {}).items())
        h.append(f"<tr><td>{step}</td><td>{_fmt(c.get('window'))}</td><td>{_fmt(c.get('order'))}</td>"
                 f"<td>{_fmt(c.get('deriv'))}</td><td>{_fmt(c.get('bandwidth_hz'))}</td><td>{html.escape(noise)}</td></tr>")
    h.append("</table>")
    h.append(f"<h2>Identified equation (per unit mass)</h2><pre>{html.escape(d['equation'])}</pre>")
    h.append(f"<p>{html.escape(d.get('convention', ''))}</p>")
    level = f"{100 * unc['level']:.0f} %" if unc else ""
    h.append(f"<h3>Parameters{' with ' + level + ' intervals' if unc else ''}</h3><table><tr><th>parameter</th>"
             "<th>estimate</th><th>low</th><th>high</th><th>units</th></tr>")
    for k, v, (lo, hi), units in _param_rows(d, unc):
        h.append(f"<tr><td>{html.escape(k)}</td><td>{_fmt(v)}</td><td>{_fmt(lo)}</td><td>{_fmt(hi)}</td>"
                 f"<td>{html.escape(units)}</td></tr>")
    h.append("</table>")
    if unc:
        blocks = ", ".join(f"{n} stage {b} samples" for n, b in (unc.get("block_samples") or {}).items())
        h.append(f"<p>Intervals: {html.escape(unc['method'])}; {unc['n_resamples']} ensemble members"
                 + (f", resampled in blocks ({html.escape(blocks)})" if blocks else "") + "; "
                 + ("computed at the optimum of the output-error fit" if unc.get("at_optimum")
                    else "the output-error fit had not reached its optimum, so they are approximate")
                 + ". They do not include the uncertainty of which library terms were selected "
                   "(see docs/reprocessing.md).</p>")
    else:
        h.append("<p>No intervals (uncertainty skipped).</p>")
    ts = d.get("term_selection") or {}
    if ts.get("available"):
        h.append(f"<h3>Stability of the term selection</h3><p>Fraction of {ts['n_models']} selections, each on a "
                 f"random {100 * ts['keep_fraction']:.0f} % of the regression rows (in {ts['n_chunks']} contiguous "
                 f"chunks), that kept each fn term. A selected term below ~0.8, or another term near 1, means "
                 f"the choice of terms is uncertain and the intervals above (conditional on it) are too "
                 f"optimistic.</p><table><tr><th>term</th><th>inclusion</th><th>selected</th></tr>")
        for term, f in ts["inclusion"].items():
            h.append(f"<tr><td>{html.escape(term)}</td><td>{f:.2f}</td><td>{'yes' if term in ts['selected'] else ''}</td></tr>")
        h.append("</table>")
        if ts.get("note"):
            h.append(f"<p>Note: {html.escape(ts['note'])}; final terms: "
                     f"{html.escape(', '.join(ts.get('final_terms', [])))}.</p>")
    sp = d["nonlinear_step"]["sparse_regression"]
    h.append(f"<p>Sparse regression: {sp['n_terms']} library terms kept (support from {html.escape(str(sp.get('support_from')))}), "
             f"threshold {sp['threshold']:.3g}; linear step condition number "
             f"{d['linear_step'].get('condition_number', float('nan')):.3g}; output-error polish: "
             f"{html.escape(info.get('polish', ''))}.</p>")
    h.append("<h2>Nonlinear force by kernel cluster</h2>" + _img(figures, "restoring_force"))
    h.append("<h2>Validation</h2><table><tr><th>stage</th><th>NRMSE</th></tr>")
    for n, v in (d["validation"].get("per_stage") or {}).items():
        h.append(f"<tr><td>{html.escape(n)}</td><td>{nrmse_text(v)}</td></tr>")
    h.append("</table>")
    if d["validation"].get("fitted_on_validation_stage"):
        h.append("<p><b>No validation stage was recorded: the NRMSE is on the fitted stage.</b></p>")
    for key in sorted(k for k in figures if k.startswith("validation")):
        h.append(_img(figures, key))
    h.append("<h2>Hysteresis loops at several amplitudes</h2>" + _img(figures, "loops"))
    h.append("<h2>Residual</h2>" + _img(figures, "residual"))
    h += info.get("sections", [])
    h.append(f"<h2>Timings</h2><p>{html.escape(timings_text(info['timings_s']))}.</p>")
    h.append("<p>The full result is in <code>result.json</code> next to this file.</p></body></html>")
    return "\n".join(h)


def _polish_text(prov: dict) -> str:
    p = prov.get("output_error_polish") or {}
    if not p.get("applied"):
        return "not applied" + (f" (NRMSE {nrmse_text(p['nrmse_before'])} not improved)" if "nrmse_before" in p else "")
    return (f"applied, fitting-stage NRMSE {nrmse_text(p['nrmse_before'])} -> {nrmse_text(p['nrmse_after'])} "
            f"({p.get('nfev')} simulations)")


def _img(figures: dict, key: str) -> str:
    p = figures.get(key)
    return "" if p is None else img_html(p, key)


def img_html(path, alt: str) -> str:
    """A PNG embedded in the page (a data URI: the report is one self-contained file)."""
    data = base64.b64encode(Path(path).read_bytes()).decode()
    return f"<p><img alt='{html.escape(alt)}' src='data:image/png;base64,{data}'></p>"


def make_report(run_path, outdir, settings=None, uncertainty: bool = True, uncertainty_settings=None,
                write_back: bool = True, term_models: int = 0, overwrite: bool = False, result=None,
                sections: list[str] | None = None, stored: str | None = None) -> dict:
    """Reconstruct ``run_path`` and write the report into ``outdir``; returns the result JSON
    (with ``uncertainty`` and ``report``: the files written and where the result went).

    The report is built in a temporary directory next to ``outdir`` and moved into place when
    complete (a new ``outdir`` is renamed into place whole; into an existing one, with
    ``overwrite``, each report file replaces its namesake). Only then is the result written back
    into the run file; if that cannot be done (the file is being written by another process, was
    not closed cleanly, ...) the report says so and stays complete. ``result``: a reconstruction of
    the run already made with ``settings`` (not repeated); ``sections``: HTML sections added before the
    timings (the demo's comparison with the simulator's truth); ``stored``: where the caller wrote the result
    itself (said in the report instead of the write-back note). Its steps are reported through
    :mod:`recon.progress` (``workflows.progress_line`` shows them)."""
    run_path = Path(run_path)
    outdir = check_directory(outdir, option="-o")
    if outdir.is_dir() and any(outdir.iterdir()) and not overwrite:
        raise UserFacingError(f"-o {outdir}: the directory exists and is not empty (an earlier report?); "
                              f"--force replaces its report files (other files are kept), or choose another -o")
    settings = settings or ReconSettings()
    timings = {}
    run = load_run(run_path)
    try:
        outdir.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserFacingError(f"-o {outdir}: cannot create the report directory ({exc})") from None
    t = time.perf_counter()
    problem = None
    shares = {"reconstruct": 0.5, "terms": 0.1 if term_models > 0 else 0.0, "intervals": 0.35 if uncertainty else 0.0}
    progress.step(f"reconstructing {run_path.name}", share=shares["reconstruct"] / (sum(shares.values()) + 0.1))
    if term_models > 0:
        result, problem = reconstruct_capturing(run, settings)
    elif result is None:
        result = reconstruct(run, settings)
    timings["reconstruct"] = time.perf_counter() - t
    d = result.to_dict()
    d["warnings"] = warnings_for(run, result)
    if term_models > 0:

        t = time.perf_counter()
        progress.step(f"term selection on {term_models} row subsamples", share=0.1 / (sum(shares.values()) + 0.1))
        d["term_selection"] = term_inclusion(problem, n_models=term_models)
        timings["term_selection"] = time.perf_counter() - t
    if uncertainty:

        t = time.perf_counter()
        progress.step("parameter intervals", share=0.35 / (sum(shares.values()) + 0.1))
        d["uncertainty"] = parameter_intervals(result.model, run, uncertainty_settings or UncertaintySettings())
        timings["uncertainty"] = time.perf_counter() - t
    staging = outdir.with_name(f".{outdir.name}.{secrets.token_hex(4)}.tmp")
    try:
        staging.mkdir()
    except OSError as exc:
        raise UserFacingError(f"-o {outdir}: cannot create a directory next to it ({exc})") from None
    try:
        t = time.perf_counter()
        figures = {}
        progress.step("figures", share=1.0)
        figures["stages"] = fig_stages(run, staging / "stages.png")
        figures["restoring_force"] = fig_restoring_force(result, run, staging / "restoring_force.png")
        sims = simulated_stages(result, run)
        for p in fig_validation(sims, result, staging / "validation.png"):
            figures[p.stem] = p
        figures["loops"] = fig_loops(result, run, staging / "loops.png")
        figures["residual"] = fig_residual(sims, staging / "residual.png")
        timings["figures"] = time.perf_counter() - t
        job = {"recon": settings.to_dict(), "uncertainty": uncertainty,
               "uncertainty_settings": (uncertainty_settings.to_dict() if uncertainty_settings else {}),
               "term_models": int(term_models)}
        digest = settings_hash(job)
        d["reprocess"] = {"settings_hash": digest, "settings": job, "software": f"shakerlab {__version__}"}
        info = {"created": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
                "timings_s": {**result.timings, **timings}, "polish": _polish_text(result.model.provenance),
                "sections": list(sections or [])}
        pending = (stored if stored else "Result not written into the run file (--no-write-back)." if not write_back else
                   "Result not yet written into the run file (the report is written first).")
        _write_report_files(staging, run, d, figures, info, outdir, None, pending)
        with OutputLock(outdir):
            _publish(staging, outdir)
        figures = {k: outdir / Path(v).name for k, v in figures.items()}
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    if not write_back:
        return clean(d)
    written, note = store_result(run_path, RESULT_KIND, clean(d), text=str(result.model), settings_hash=digest)
    out = _write_report_files(outdir, run, d, figures, info, outdir, written, f"Result {note}.")
    if written is None and "no space left" in note:
        # a full disk is a failure of the command, not a remark in the report: one line, exit 2
        raise UserFacingError(f"{note.removeprefix('not written back: ')}; the report in {outdir} was written, "
                              f"the run file is unchanged")
    return out


def _write_report_files(where: Path, run, d: dict, figures: dict, info: dict, outdir: Path, written, note: str) -> dict:
    """index.html and result.json into ``where`` (each through a temporary file); returns the result JSON."""
    info = {**info, "write_back": note}
    d["report"] = {"directory": str(outdir), "html": str(outdir / "index.html"),
                   "figures": {k: str(outdir / Path(v).name) for k, v in figures.items()}, "result_group": written,
                   "note": note}
    write_text(where / "index.html", render_html(run, clean(d), figures, info))
    write_text(where / "result.json", json.dumps(clean(d), indent=2))
    return clean(d)


def _publish(staging: Path, outdir: Path) -> None:
    """Move the complete report from ``staging`` into ``outdir``: the whole directory when ``outdir``
    does not exist, else file by file (each ``os.replace`` atomic; other files of ``outdir`` stay)."""
    if not outdir.exists():
        with contextlib.suppress(OSError):
            os.rename(staging, outdir)
            return
    outdir.mkdir(exist_ok=True)
    for f in sorted(staging.iterdir()):
        os.replace(f, outdir / f.name)


def interval_lines(d: dict) -> list[str]:
    """Plain-text lines 'name = estimate  [low, high]' for every parameter with an interval."""
    unc = d.get("uncertainty") or {}
    out = [f"{100 * unc.get('level', 0.95):.0f} % intervals ({unc.get('n_resamples')} ensemble members):"]
    for k, v, (lo, hi), units in _param_rows(d, unc):
        out.append(f"  {k:<14s} {v:>13.6g}  [{_num(lo)}, {_num(hi)}]  {units}")
    return out


def _num(v) -> str:
    return "-" if v is None else f"{v:.6g}"

"""``shakerlab demo``: the whole experiment on an embedded simulated rig.

Starts the simulated rig (as fast as possible, or in real time), runs the
protocol through the same runner and recorder as ``shakerlab acquire``,
reconstructs the governing equation from the run file (recon.estimator.pipeline),
prints it with the validation error and the simulator's true parameters,
writes the result back into the run file and the HTML report (index.html, as
``shakerlab report`` writes it, with the comparison against the simulator's
truth) into the output directory. An existing output directory is replaced
only with ``--force``.
"""
from __future__ import annotations

import html
import json
import math
import time
from pathlib import Path

import numpy as np

from recon import ReconSettings, reconstruct
from rig.session import EXIT_CODES
from rig.console import ConsoleProgress, print_summary, sigint_aborts
from rig.protocol import load_protocol
from rig.session import acquire, simulated_rig
from workflows.figures import plt, savefig
from workflows.progress_line import progress_line
from workflows.report import img_html, make_report
from shakerlab.errors import UserFacingError
from shakerlab.words import duration_text, nrmse_text, parameter_units
from shakerlab.runfile.reader import load_run, read_info
from shakerlab.jsonsafe import clean
from shakerlab.output_files import check_directory, write_text
from shakerlab.runfile.results import store_result
from sim_backend.config import DEFAULT_CONFIG_PATH

PARAMS = ("c_m", "k_m", "alpha_m", "gamma", "delta")
RECON_FORM = "weak"


def compare(identified: dict, truth: dict) -> list[dict]:
    """Rows (name, identified, true, relative error) for the linear, Bouc-Wen and fn_m parameters."""
    rows = []
    for name in PARAMS:
        rows.append({"name": name, "identified": float(identified[name]), "true": float(truth[name])})
    fn_id, fn_true = identified.get("fn_m", {}), truth.get("fn_m", {})
    for name in sorted(set(fn_id) | set(fn_true)):
        rows.append({"name": f"fn_m[{name}]", "identified": float(fn_id.get(name, 0.0)),
                     "true": float(fn_true.get(name, 0.0))})
    for r in rows:
        r["relative_error"] = (r["identified"] / r["true"] - 1.0) if r["true"] != 0 else (
            0.0 if r["identified"] == 0 else math.inf)
    return rows


def _err_text(row: dict) -> str:
    if row["true"] == 0:
        return "not in the simulator" if row["identified"] != 0 else "-"
    if row["identified"] == 0:
        return "missed"
    return f"{row['relative_error'] * 100:+.2f} %"


def _plots(outdir: Path, info: dict) -> list[str]:
    """The protocol's own figures (the report draws the stages, the fit and the validation)."""
    files = []
    search = info["stages"].get("resonance_search", {}).get("summary", {})
    if search.get("frequencies_hz"):
        f = np.array(search["frequencies_hz"])
        tr = np.array(search["transmissibility"])
        o = np.argsort(f)
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.semilogy(f[o], tr[o], "o-", ms=3)
        ax.axvline(search["resonance_hz"], color="k", ls="--", lw=0.8, label=f"{search['resonance_hz']:.3f} Hz")
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel("|X_tip| / |X_base|")
        ax.legend()
        ax.set_title("resonance search (stepped sine)")
        fig.tight_layout()
        savefig(fig, outdir / "resonance.png", dpi=80)
        files.append("resonance.png")

    levels = info["stages"].get("nonlinear", {}).get("summary", {}).get("levels", [])
    if levels:
        y = [1e3 * lv["relative_amplitude"] for lv in levels]
        fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
        ax[0].plot(y, [lv["gain"] for lv in levels], "o-")
        ax[0].set_xlabel("relative amplitude [mm]")
        ax[0].set_ylabel("|Y| / |X_base|")
        ax[1].plot(y, [lv["loss_factor"] for lv in levels], "o-")
        ax[1].set_xlabel("relative amplitude [mm]")
        ax[1].set_ylabel("loop loss factor")
        fig.suptitle("nonlinear stage: response per amplitude level")
        fig.tight_layout()
        savefig(fig, outdir / "levels.png", dpi=80)
        files.append("levels.png")
    return files


def run_demo(outdir: Path, *, realtime: bool = False, protocol_path=None, seed: int = 0, quiet: bool = False,
             force: bool = False) -> int:

    t0 = time.monotonic()
    outdir = check_directory(outdir, option="-o")
    if outdir.is_dir() and any(outdir.iterdir()) and not force:
        raise UserFacingError(f"-o {outdir}: the folder exists and is not empty (an earlier demo?); --force "
                              f"replaces its files, or choose another -o")
    outdir.mkdir(parents=True, exist_ok=True)
    path = outdir / "run.h5"
    protocol = load_protocol(protocol_path)
    speed = 1.0 if realtime else None
    print(f"shakerlab demo: simulated TMP-origami shaker rig (seed {seed}, "
          f"{'real time' if realtime else 'as fast as possible'}), report in {outdir}/")
    with simulated_rig(speed=speed, seed=seed) as (sim, config), sigint_aborts() as hook:

        outcome = acquire(config, protocol, path, lockstep=not realtime, overwrite=True,
                          observers=[ConsoleProgress(quiet=quiet)], on_runner=hook,
                          attrs={"simulated": True, "seed": seed},
                          texts={"simulator_toml": DEFAULT_CONFIG_PATH.read_text()})
        truth = sim.world.truth()
        truth["mass"] = sim.world.specimen_mass
    print_summary(outcome)
    if outcome.status != "complete":
        return EXIT_CODES.get(outcome.status, 1)

    print("\nreconstructing the governing equation from", path)
    t_rec = time.monotonic()

    run = load_run(path)
    # The weak (integral) form: the rig's sensor noise makes the pointwise form's third derivative
    # of the displacement unreliable; integrating against test functions avoids it.
    settings = ReconSettings(form=RECON_FORM)
    with progress_line(quiet=quiet):
        result = reconstruct(run, settings)
    t_rec = time.monotonic() - t_rec
    d = result.to_dict()
    print()
    print(str(result.model))
    val = d["validation"]
    print(f"\nvalidation on stage {val['stage']!r}: NRMSE {nrmse_text(val['nrmse'])}")
    print(f"verdict: {d['verdict_text']}")
    rows = compare(d["parameters"], truth)
    print("\nparameter      identified        true   error")
    for r in rows:
        print(f"{r['name']:<14s} {r['identified']:>11.5g} {r['true']:>11.5g} {_err_text(r)}")
    group, note = store_result(path, "reconstruction", clean({**d, "truth": truth, "comparison": rows}),
                               text=str(result.model))
    info = read_info(path)
    figs = _plots(outdir, info)
    with progress_line(quiet=quiet):
        make_report(path, outdir, settings=settings, uncertainty=False, write_back=False, overwrite=True,
                    result=result, sections=[_demo_section(outdir, outcome, info, rows, figs, t_rec)],
                    stored=f"Result {note}, with the simulator's truth and the comparison.")
    # the demo's result.json holds the truth and the comparison beside the reconstruction
    write_text(outdir / "result.json", json.dumps(clean({"reconstruction": d, "truth": truth, "comparison": rows}), indent=2))
    print(f"\nreport: {outdir / 'index.html'} (run file {path}); total {duration_text(time.monotonic() - t0)}")
    return 0


def _demo_section(outdir, outcome, info, rows, figs, t_rec) -> str:
    """The demo's part of the HTML report: the protocol's stages and the identified against the true."""
    h = ["<h2>The simulated rig's protocol</h2>",
         f"<p>Simulated TMP-origami shaker rig; run file <code>run.h5</code> (status {html.escape(outcome.status)}, "
         f"{duration_text(outcome.run_time_s)} of rig time in {duration_text(outcome.wall_time_s)}; samples lost "
         f"{outcome.samples_lost}); reconstruction {duration_text(t_rec)}.</p>",
         "<table><tr><th>stage</th><th>status</th><th>duration [s]</th><th>notes</th></tr>"]
    for name, st in info["stages"].items():
        s = st["summary"]
        note = ""
        if "resonance_hz" in s:
            note = f"resonance {s['resonance_hz']:.3f} Hz"
        elif "stop_reason" in s and "final_vpp" in s:
            note = f"{len(s.get('levels', []))} levels, final {s['final_vpp']:.3f} Vpp: {s['stop_reason']}"
        elif "response" in s:
            note = f"relative amplitude {s['response']['relative_amplitude'] * 1e3:.3f} mm at {s['response']['frequency_hz']:.3f} Hz"
        h.append(f"<tr><td>{html.escape(name)}</td><td>{html.escape(st['status'])}</td>"
                 f"<td>{st['n_samples'] / st['fs']:.2f}</td><td>{html.escape(note)}</td></tr>")
    h.append("</table>")
    h += [img_html(outdir / f, f) for f in figs]
    h.append("<h2>Identified against true (the simulator's specimen)</h2><table><tr><th>parameter</th>"
             "<th>identified</th><th>true</th><th>error</th><th>units</th></tr>")
    for r in rows:
        key, _, term = r["name"].partition("[")
        units = parameter_units(key, term.rstrip("]") or None)
        h.append(f"<tr><td>{html.escape(r['name'])}</td><td>{r['identified']:.5g}</td><td>{r['true']:.5g}</td>"
                 f"<td>{html.escape(_err_text(r))}</td><td>{html.escape(units)}</td></tr>")
    h.append("</table>")
    return "\n".join(h)

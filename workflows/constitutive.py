"""Constitutive mode in the application: reconstruct and report of a component test's run file.

``shakerlab reconstruct`` and ``shakerlab report`` come here when the run file's mode is
``constitutive`` (shakerlab.modes); the law comes from recon.constitutive.estimator. The
report is one self-contained ``index.html`` (figures embedded), ``result.json`` and the PNG
figures, each written through a temporary file (shakerlab.output_files).
"""
from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from recon.constitutive.diagnosis import diagnose_law
from recon.constitutive.estimator import ConstitutiveSettings, predict, reconstruct_constitutive
from recon.constitutive.law import ConstitutiveLaw
from recon.constitutive.output_error import intervals
from recon.constitutive.signals import component_signals
from shakerlab import __version__
from shakerlab.errors import UserFacingError
from shakerlab.jsonsafe import clean
from shakerlab.output_files import check_directory, inside, write_text
from shakerlab.runfile.results import store_result
from workflows.figures import plot_force_law


def settings_from(args) -> ConstitutiveSettings:
    order = getattr(args, "library_order", 5)
    if order < 2 or order > 8:
        raise UserFacingError(f"--library-order must be between 2 and 8, got {order}")
    inertia = getattr(args, "inertia", "none")
    if inertia not in ("none", "fit"):
        try:
            inertia = float(inertia)
        except ValueError:
            raise UserFacingError(f"--inertia {inertia!r}: expected none, fit or a mass in kg") from None
    return ConstitutiveSettings(library_order=order, polish=not getattr(args, "no_polish", False), inertia=inertia)


def law_plots(result, run, outdir) -> list[Path]:
    """Force history and force-displacement loop, recorded vs law, for the validation stages and
    the fitted stage."""
    outdir = Path(outdir)
    names = [n for n in run.stages if n.startswith("validation")]
    names += [result.settings.fit_stage]
    paths = []
    for name in names:
        t, F, Fp, x = predict(result.law, run.stage(name), result.settings)
        nr = result.validation.get("per_stage", {}).get(name)
        what = "fitted" if name == result.settings.fit_stage else "held out"
        paths.append(plot_force_law(inside(outdir, f"{name}_force", ".png"), t, x, F, Fp,
                                    title=f"{name} ({what}): recorded vs law"
                                    + (f" (NRMSE {nr:.3g})" if nr is not None else "")))
    return paths


def law_intervals(result, run) -> dict:
    """95 % intervals of the law's parameters on the fitted stage (recon.constitutive.output_error.intervals)."""
    sig = component_signals(run.stage(result.settings.fit_stage), result.settings.window, result.settings.sg_order)
    return intervals(result.law, [sig], fit_rate=result.settings.fit_rate)


def reconstruct_command(args, run) -> int:
    result = reconstruct_constitutive(run, settings_from(args))
    out = result.to_dict()
    out["warnings"] = []
    if getattr(args, "form", "joint") != "joint":
        out["warnings"].append(f"--form {args.form}: a component test's law uses the joint pointwise form; ignored")
    if getattr(args, "uncertainty", False):
        out["uncertainty"] = law_intervals(result, run)
    if args.plots:
        out["plots"] = [str(p) for p in law_plots(result, run, Path(args.plots))]
    if args.save_model:
        write_text(args.save_model, json.dumps(clean(result.law.to_dict()), indent=1),
                   overwrite=getattr(args, "force", False), never_hdf5=True)
    if args.json:
        print(json.dumps(clean(out)))
        return 0
    print(f"{run.source}: component test (constitutive mode), force law in SI units")
    print(result.law.equation())
    for w in out["warnings"]:
        print(f"warning: {w}")
    v = result.validation
    print(f"validation NRMSE of the force on stage {v['stage']!r}: {v['nrmse']:.4g}"
          + (" (no validation stage: fitted stage)" if v.get("fitted_on_validation_stage") else ""))
    a = result.adequacy
    print(f"admissible: {'yes' if a['admissible'] else 'NO'}; adequacy: {a['verdict']}"
          + (f" ({'; '.join(a['reasons'])})" if a["reasons"] else ""))
    d = result.differentiation
    print(f"Savitzky-Golay: window {d['window']}, order {d['order']}; sparse regression: "
          f"{result.sparse['n_terms']} library terms")
    for name, q in out.get("uncertainty", {}).get("parameters", {}).items():
        print(f"  {name:12s} {q['value']:.6g}  [{q['low']:.6g}, {q['high']:.6g}]")
    for p in out.get("plots", []):
        print(f"plot: {p}")
    return 0


def _img(path: Path) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f"<p><img alt='{html.escape(path.stem)}' src='data:image/png;base64,{data}'></p>"


def make_report(run, outdir, settings: ConstitutiveSettings | None = None, overwrite: bool = False,
                write_back: bool = True) -> dict:
    """Reconstruct the law of ``run`` and write the report into ``outdir``; returns the result JSON
    with ``report`` (the files written and where the result went). With ``write_back`` the result
    is stored in the run file (entry/results/reconstruction_NNN) once the report is complete."""
    outdir = check_directory(outdir, option="-o")
    if outdir.is_dir() and any(outdir.iterdir()) and not overwrite:
        raise UserFacingError(f"-o {outdir}: the directory exists and is not empty (an earlier report?); "
                              f"--force replaces its report files, or choose another -o")
    result = reconstruct_constitutive(run, settings)
    d = result.to_dict()
    d["uncertainty"] = law_intervals(result, run)
    d = clean(d)
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserFacingError(f"-o {outdir}: cannot create the report directory ({exc})") from None
    figures = law_plots(result, run, outdir)
    p = d["parameters"]
    iv = d["uncertainty"].get("parameters", {})

    def interval(key):
        q = iv.get(key)
        return f"[{q['low']:.6g}, {q['high']:.6g}]" if q else ""

    rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{v:.6g}</td><td>{interval(k)}</td>"
                   f"<td>{html.escape(str(d['units'].get(k, '')))}</td></tr>"
                   for k, v in p.items() if isinstance(v, (int, float)))
    rows += "".join(f"<tr><td>fn {html.escape(k)}</td><td>{v:.6g}</td><td>{interval('fn:' + k)}</td>"
                    f"<td>N/(m^p (m/s)^r)</td></tr>" for k, v in p.get("fn", {}).items())
    v = d["validation"]
    stages = "".join(f"<tr><td>{html.escape(n)}</td><td>{st.fs:.6g}</td><td>{st.t.size}</td>"
                     f"<td>{st.t[-1] - st.t[0]:.4g}</td><td>{html.escape(', '.join(st.channels))}</td></tr>"
                     for n, st in run.stages.items())
    a = d["adequacy"]
    doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>shakerlab report: "
           f"{html.escape(Path(run.source).name)}</title></head><body>"
           f"<h1>Constitutive law: {html.escape(Path(run.source).name)}</h1>"
           f"<p>Run file <code>{html.escape(run.source)}</code>; component test (displacement imposed, force "
           f"measured); shakerlab {__version__}.</p>"
           f"<h2>Stages</h2><table border=1><tr><th>stage</th><th>fs [Hz]</th><th>samples</th><th>duration [s]</th>"
           f"<th>channels</th></tr>{stages}</table>"
           f"<h2>Identified law</h2><pre>{html.escape(d['equation'])}</pre>"
           f"<table border=1><tr><th>parameter</th><th>value</th><th>95 % interval</th><th>units</th></tr>{rows}</table>"
           f"<p>Intervals: {html.escape(str(d['uncertainty'].get('method', '')))}.</p>"
           f"<h2>Validation</h2><p>NRMSE of the predicted force on stage {html.escape(str(v['stage']))}: "
           f"{v['nrmse']:.4g}{' (the fitted stage: no validation stage)' if v.get('fitted_on_validation_stage') else ''}"
           f". Verdict: {html.escape(a['verdict'])}{': ' + html.escape('; '.join(a['reasons'])) if a['reasons'] else ''}.</p>"
           + "".join(_img(f) for f in figures)
           + f"<h2>Timings</h2><p>{html.escape(json.dumps({k: round(t, 3) for k, t in d['timings_s'].items()}))} s</p>"
           "<p>The full result is in <code>result.json</code> next to this file; the method in "
           "docs/constitutive.md.</p></body></html>")
    written = [write_text(outdir / "index.html", doc), write_text(outdir / "result.json", json.dumps(d, indent=1))]
    note = "not written back (--no-write-back)"
    if write_back:
        group, note = store_result(run.source, "reconstruction", d, text=str(result.law))
        if group is not None:
            note = f"result written back into {run.source} (entry/results/{group})"
    d["report"] = {"html": str(outdir / "index.html"), "files": [str(f) for f in written + figures], "note": note}
    return d


def report_command(args, run) -> int:
    d = make_report(run, args.output, settings_from(args), overwrite=args.force,
                    write_back=not getattr(args, "no_write_back", False))
    if args.json:
        print(json.dumps(d))
        return 0
    print(d["equation"])
    v = d["validation"]
    print(f"validation NRMSE of the force on stage {v['stage']!r}: {v['nrmse']:.4g}")
    print(d["report"]["note"])
    print(f"report: {d['report']['html']}")
    return 0



def diagnose_command(args, run) -> int:
    """``shakerlab diagnose`` of a component test: the candidates the law lacks (recon.constitutive.diagnosis)."""
    if getattr(args, "report", None) or getattr(args, "save_model", None):
        raise UserFacingError(f"{args.run}: a component test: --report and --save-model are not available for its "
                              f"diagnosis yet (use --json)")
    baseline = getattr(args, "baseline", "paper")
    if baseline in (None, "paper"):
        law = None
    elif baseline == "linear":
        raise UserFacingError("--baseline linear: a component test's diagnosis starts from its law ('paper', the "
                              "default) or a saved law JSON")
    else:
        law = ConstitutiveLaw.load(baseline)
    d = diagnose_law(run, law, settings_from(args) if hasattr(args, "library_order") else None)
    out = d.to_dict()
    if args.json:
        print(json.dumps(clean(out)))
        return 0
    print(f"{run.source}: component test, baseline law ({d.baseline_kind}, refitted on the fitted stage)")
    print(out["baseline"])
    print(f"  held-out force NRMSE ({', '.join(d.held_out)}): {d.fit_before['held_out_nrmse']:.4g}")
    for c in d.candidates:
        shape = ", ".join(f"{k} = {v:.4g}" for k, v in (c["shape"] or {}).items())
        print(f"  {c['id']:18s} {c['coefficient']:.4g} {c['unit']}{' (' + shape + ')' if shape else ''}: held-out "
              f"{c['held_out_nrmse']:.4g} ({100 * c['gain']:+.1f} %)")
    print(out["result"])
    return 0

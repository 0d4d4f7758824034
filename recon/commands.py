"""Sub-commands contributed by ``recon`` (see shakerlab.cli). Import-light: heavy imports in handlers."""
from __future__ import annotations


def register(subparsers) -> None:
    """Add this package's sub-commands to the ``shakerlab`` parser."""
    p = subparsers.add_parser(
        "reconstruct",
        help="identify the hysteretic governing equation from a run file",
        description="Reconstruct y'' + c y' + k y + fn(y, y') + z = u with Bouc-Wen z from a run "
                    "(.h5 or .npz with stages 'linear', 'nonlinear', optionally 'validation'). "
                    "Everything is per unit mass.",
    )
    p.add_argument("run", metavar="RUN", help="run file (.h5 or .npz)")
    p.add_argument("--json", action="store_true", help="print one JSON object (machine-readable)")
    p.add_argument("--plots", metavar="DIR", help="write PNG overlays (time history, hysteresis loop) to DIR")
    p.add_argument("--library-order", metavar="Q", type=int, default=5,
                   help="highest monomial degree of fn (default 5)")
    p.add_argument("--save-model", metavar="PATH", help="write the identified model as JSON to PATH")
    p.add_argument("--no-polish", action="store_true", help="skip the output-error polish (equation-error estimate only)")
    p.add_argument("--form", choices=("joint", "weak", "ab"), default="joint",
                   help="nonlinear step: pointwise agent model on AB and CD (joint, default), the weak form "
                        "(needs no third derivative; holds to 40 dB SNR, see docs/method.md) or the paper's AB-only form")
    p.add_argument("--uncertainty", action="store_true",
                   help="add 95%% intervals of every parameter (key 'uncertainty'; see docs/reprocessing.md)")
    p.set_defaults(handler=_reconstruct)
    register_reprocessing(subparsers)
    register_diagnosis(subparsers)


def _clean(obj):
    """JSON-safe copy: numpy scalars to float, NaN/inf to None."""
    import math

    import numpy as np

    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def _reconstruct(args) -> int:
    import json
    from pathlib import Path

    from shakerlab.errors import UserFacingError
    from shakerlab.run_data import load_run
    from recon.pipeline import ReconSettings, reconstruct
    from recon.validation import write_validation_plots

    if args.library_order < 2 or args.library_order > 8:
        raise UserFacingError(f"--library-order must be between 2 and 8, got {args.library_order}")
    run = load_run(args.run)
    result = reconstruct(run, ReconSettings(library_order=args.library_order, polish=not args.no_polish,
                                            form=getattr(args, "form", "joint")))
    out = result.to_dict()
    if getattr(args, "uncertainty", False):
        from recon.uncertainty import parameter_intervals

        out["uncertainty"] = parameter_intervals(result.model, run)
    if args.plots:
        out["plots"] = [str(p) for p in write_validation_plots(result, run, Path(args.plots))]
    if args.save_model:
        result.model.save(args.save_model)
    if args.json:
        print(json.dumps(_clean(out)))
        return 0
    print(f"{run.source}: {result.model.excitation} excitation, per unit mass")
    print(result.model.equation())
    v = result.validation
    print(f"validation NRMSE on stage {v['stage']!r}: {v['nrmse']:.4g}"
          + (" (no validation stage: fitted stage)" if v.get("fitted_on_validation_stage") else ""))
    d = result.differentiation["nonlinear"]
    print(f"Savitzky-Golay (nonlinear stage): window {d['window']}, order {d['order']}, "
          f"noise level {', '.join(f'{k} {v:.3g}' for k, v in d['noise_level'].items())}")
    print(f"sparse regression: {result.sparse['n_terms']} library terms, threshold {result.sparse['threshold']:.3g}; "
          f"linear step condition number {result.linear.condition_number:.3g}")
    if "uncertainty" in out:
        from recon.report import interval_lines

        print(*interval_lines(out), sep="\n")
    for p in out.get("plots", []):
        print(f"plot: {p}")
    return 0


# --- offline reprocessing: `report` and `reprocess` (recon/report.py, recon/batch.py) ---------------

def register_reprocessing(subparsers) -> None:
    p = subparsers.add_parser(
        "report",
        help="reconstruct a run and write an HTML report (PNG figures, JSON, intervals)",
        description="Reconstruct RUN, compute parameter intervals, and write DIR/index.html (self-contained, "
                    "figures embedded), the figures as PNG and DIR/result.json. The result is written back "
                    "into the run file (entry/results/reconstruction_NNN) unless the same settings are stored.",
    )
    p.add_argument("run", metavar="RUN", help="run file (.h5; .npz works but holds no results)")
    p.add_argument("-o", "--output", metavar="DIR", required=True, help="report directory (created)")
    _common_recon_options(p)
    p.add_argument("--no-write-back", action="store_true", help="do not write the result into the run file")
    p.add_argument("--term-models", metavar="N", type=int, default=0,
                   help="term-selection ensemble size (row-subsampled reselections, ~1 s each; default 0: off)")
    p.add_argument("--json", action="store_true", help="print the result JSON instead of a summary")
    p.set_defaults(handler=_report)

    p = subparsers.add_parser(
        "reprocess",
        help="reconstruct many run files in parallel on Dask (summary table, results written back)",
        description="Reconstruct every run matching the patterns (quote them: 'runs/*.h5') on a local Dask "
                    "cluster or an existing scheduler. Runs already processed with the same settings are "
                    "skipped; a bad run is reported with its reason and the batch goes on. Prints a summary "
                    "table and writes it as CSV.",
    )
    p.add_argument("patterns", metavar="RUNS", nargs="+", help="run files or glob patterns")
    p.add_argument("--scheduler", metavar="ADDRESS", help="address of a running Dask scheduler (tcp://host:port)")
    p.add_argument("--workers", metavar="N", type=int, default=2, help="local cluster worker processes (default 2)")
    p.add_argument("--threads", action="store_true", help="local cluster with threads instead of processes")
    p.add_argument("--serial", action="store_true", help="a plain loop in this process (no Dask)")
    p.add_argument("--csv", metavar="PATH", default="reprocess_summary.csv",
                   help="summary table as CSV (default reprocess_summary.csv)")
    p.add_argument("--diagnose", action="store_true", help="also run the mismatch diagnosis on each run")
    p.add_argument("--force", action="store_true", help="reprocess runs already processed with the same settings")
    p.add_argument("--no-write-back", action="store_true", help="do not write results into the run files")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--term-models", metavar="N", type=int, default=0,
                   help="term-selection ensemble size per run (row-subsampled reselections; default 0: off)")
    _common_recon_options(p)
    p.set_defaults(handler=_reprocess)


def _common_recon_options(p) -> None:
    p.add_argument("--library-order", metavar="Q", type=int, default=5, help="highest monomial degree of fn (default 5)")
    p.add_argument("--no-polish", action="store_true", help="skip the output-error polish")
    p.add_argument("--no-uncertainty", action="store_true", help="skip the parameter intervals")
    p.add_argument("--resamples", metavar="B", type=int, default=200,
                   help="ensemble members for the intervals (default 200)")


def _recon_settings(args) -> dict:
    from shakerlab.errors import UserFacingError

    if args.library_order < 2 or args.library_order > 8:
        raise UserFacingError(f"--library-order must be between 2 and 8, got {args.library_order}")
    if args.resamples < 50:
        raise UserFacingError(f"--resamples must be at least 50, got {args.resamples}")
    return {"library_order": args.library_order, "polish": not args.no_polish}


def _term_models(args) -> int:
    from shakerlab.errors import UserFacingError

    if args.term_models < 0 or 0 < args.term_models < 5:
        raise UserFacingError(f"--term-models must be 0 (off) or at least 5, got {args.term_models}")
    return args.term_models


def _report(args) -> int:
    import json

    from recon.pipeline import ReconSettings
    from recon.report import StepProgress, interval_lines, make_report
    from recon.uncertainty import UncertaintySettings

    rs = _recon_settings(args)
    d = make_report(args.run, args.output, settings=ReconSettings(**rs), uncertainty=not args.no_uncertainty,
                    uncertainty_settings=UncertaintySettings(n_resamples=args.resamples),
                    write_back=not args.no_write_back, progress=StepProgress(enabled=not args.json),
                    term_models=_term_models(args))
    if args.json:
        print(json.dumps(d))
        return 0
    print(d["equation"])
    v = d["validation"]
    print(f"validation NRMSE on stage {v['stage']!r}: {v['nrmse']:.4g}" if v.get("nrmse") is not None
          else "validation: simulation diverged")
    if "uncertainty" in d:
        print(*interval_lines(d), sep="\n")
    ts = d.get("term_selection") or {}
    if ts.get("available"):
        print(f"term selection over {ts['n_models']} row subsamples: "
              + ", ".join(f"{t} {f:.2f}" + ("*" if t in ts["selected"] else "") for t, f in ts["inclusion"].items())
              + "  (* selected)")
    print(d["report"]["note"])
    print(f"report: {d['report']['html']}")
    return 0


def _reprocess(args) -> int:
    import sys

    from recon.batch import BatchSettings, TextProgress, diagnosis_available, expand, format_table, run_batch, run_loop, write_csv

    rs = _recon_settings(args)
    paths = expand(args.patterns)
    if args.diagnose and not diagnosis_available():
        print("shakerlab reprocess: --diagnose: diagnosis unavailable (recon.diagnosis is not installed); "
              "reconstructing only", file=sys.stderr)
    s = BatchSettings(recon=rs, uncertainty=not args.no_uncertainty,
                      uncertainty_settings={"n_resamples": args.resamples} if args.resamples != 200 else {},
                      diagnose=args.diagnose and diagnosis_available(), write_back=not args.no_write_back,
                      force=args.force, workers=args.workers, scheduler=args.scheduler, processes=not args.threads,
                      term_models=_term_models(args))
    where = ("a plain loop" if args.serial else f"scheduler {args.scheduler}" if args.scheduler
             else f"a local Dask cluster ({args.workers} {'threads' if args.threads else 'processes'})")
    print(f"reprocessing {len(paths)} run(s) on {where}", file=sys.stderr)
    progress = TextProgress(len(paths), enabled=not args.quiet)
    rows = run_loop(paths, s, progress) if args.serial else run_batch(paths, s, progress)
    print(format_table(rows))
    print(f"summary: {write_csv(rows, args.csv)}")
    n_bad = sum(r["status"] == "failed" for r in rows)
    return 1 if n_bad else 0


# --- mismatch diagnosis: `diagnose` (recon/diagnosis/, docs/diagnosis.md) -----------------------------

def register_diagnosis(subparsers) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="locate where a model and a recording disagree, name the missing physics, show the fit improve",
        description="Compare a model's simulation with RUN, locate the mismatch (time, frequency, state plane, "
                    "channel), fit every candidate from the physics catalog as an augmented model and rank them "
                    "on held-out data (validation stage, else the last 30 % of each stage).",
    )
    p.add_argument("run", metavar="RUN", help="run file (.h5 or .npz)")
    p.add_argument("--baseline", default="paper", metavar="paper|linear|MODEL.json",
                   help="model to test: 'paper' (reconstructed from RUN, default), 'linear', or a saved model JSON")
    p.add_argument("--json", action="store_true", help="print one JSON object (machine-readable)")
    p.add_argument("--report", metavar="DIR", help="write PNG figures and diagnosis.json to DIR")
    p.add_argument("--save-model", metavar="PATH", help="write the augmented model as JSON to PATH")
    p.set_defaults(handler=_diagnose_cmd)


def _diagnose_cmd(args) -> int:
    import json
    from pathlib import Path

    from shakerlab.run_data import load_run
    from recon.diagnosis.diagnose import diagnose

    run = load_run(args.run)
    d = diagnose(run, baseline=args.baseline)
    out = d.to_dict()
    if args.report:
        from recon.diagnosis.report import write_report

        out["report"] = [str(p) for p in write_report(d, run, Path(args.report))]
    if args.save_model:
        d.best.save(args.save_model)
    if args.json:
        print(json.dumps(_clean(out)))
        return 0
    print(f"{run.source}: baseline ({d.baseline_kind})")
    print(out["baseline"])
    fb, fa = out["fit_before"]["nrmse"], out["fit_after"]["nrmse"]
    for stage in fb:
        print(f"  NRMSE {stage:12s} before {fb[stage]:.4g}  refit {out['fit_before']['refit_nrmse'][stage]:.4g}"
              f"  after {fa[stage]:.4g}")
    for f in out["mismatch"][:8]:
        print(f"  mismatch: {f['kind']} in {f['stage']} {f['region']} size {f['size']:.3g}")
    print(out["result"])
    for m in out["missing_physics"]:
        ps = ", ".join(f"{k} = {v['value']:.4g}" for k, v in m["parameters"].items())
        print(f"  {m['id']}: {m['explanation']} ({ps}); held-out NRMSE "
              f"{m['evidence']['held_out_nrmse_before']:.4g} -> {m['evidence']['held_out_nrmse_after']:.4g}")
    if out["missing_physics"]:
        print("augmented model:\n" + out["fit_after"]["model"])
    for p in out.get("report", []):
        print(f"report: {p}")
    return 0

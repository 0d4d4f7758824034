"""The handlers of the recon sub-commands (parsers: workflows.commands): reconstruct, report,
reprocess, diagnose, demo."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from recon import ReconSettings, diagnose, reconstruct
from recon import progress
from recon.diagnosis.wording import diagnosis_text, finding_text, friction_text, loop_reading
from recon.estimator.adequacy import verdict_text
from recon.output_error.uncertainty import UncertaintySettings, parameter_intervals
from shakerlab.errors import UserFacingError
from shakerlab.jsonsafe import clean
from shakerlab.output_files import check_directory, check_output, is_hdf5
from shakerlab.modes import CONSTITUTIVE, run_mode
from shakerlab.runfile.reader import load_run, read_info
from workflows.batch import (BatchSettings, TextProgress, diagnosis_available, expand, format_table,
                             refuse_drive_for_component_test, run_batch, run_loop, write_csv)
from workflows.plausibility import warnings_for
from workflows.progress_line import progress_line
from shakerlab.words import nrmse_text


def loop_as_friction(result, run) -> dict | None:
    """The reconstructed Bouc-Wen loop read as a friction law (recon.diagnosis.wording.friction_reading)
    over the nonlinear stage's travel (its displacement's peak-to-peak), None when it does not slide
    within it. A sharp loop is how a reconstruction holds a dry friction: the reading gives its
    sliding force."""
    stage = getattr(result.settings, "nonlinear_stage", None)
    return loop_reading(result.model, float(np.ptp(run.stage(stage).y))) if stage in run.stages else None


def reconstruct_command(args) -> int:

    if args.library_order < 2 or args.library_order > 8:
        raise UserFacingError(f"--library-order must be between 2 and 8, got {args.library_order}")
    check_outputs(args)
    run = load_run(args.run)
    if run_mode(run) == CONSTITUTIVE:       # a component test: the force law (docs/constitutive.md)
        refuse_drive_for_component_test(getattr(args, "drive", False), args.run)
        from workflows import constitutive  # heavy: matplotlib, for component tests only
        return constitutive.reconstruct_command(args, run)
    if getattr(args, "inertia", "none") != "none":
        raise UserFacingError(f"--inertia is for component tests (constitutive mode); {args.run} is a structure's run")
    with progress_line(quiet=getattr(args, "quiet", False)):
        intervals, plots = getattr(args, "uncertainty", False), bool(args.plots)
        rest = 0.25 * intervals + 0.1 * plots
        progress.step("reconstructing", share=1.0 - rest)
        result = reconstruct(run, ReconSettings(library_order=args.library_order, polish=not args.no_polish,
                                                form=getattr(args, "form", "joint"),
                                                drive=bool(getattr(args, "drive", False))))
        out = result.to_dict()
        out["warnings"] = warnings_for(run, result)
        out["loop_as_friction"] = loop_as_friction(result, run)
        if intervals:
            progress.step("parameter intervals", share=0.25)
            out["uncertainty"] = parameter_intervals(result.model, run)
        if plots:
            progress.step("figures", share=0.1)
            from workflows.figures import write_validation_plots  # heavy: matplotlib, with -o only
            out["plots"] = [str(p) for p in write_validation_plots(result, run, Path(args.plots))]
    if args.save_model:
        result.model.save(args.save_model, overwrite=getattr(args, "force", False))
    if args.json:
        print(json.dumps(clean(out)))
        return 0
    print(f"{run.source}: {result.model.excitation} excitation, per unit mass")
    print(result.model.equation())
    if out["loop_as_friction"]:
        print(f"  {friction_text(out['loop_as_friction'])}")
    for w in out["warnings"]:
        print(f"warning: {w}")
    v = result.validation
    print(f"validation NRMSE on stage {v['stage']!r}: {nrmse_text(v['nrmse'])}"
          + (" (no validation stage: fitted stage)" if v.get("fitted_on_validation_stage") else ""))
    if result.adequacy:
        print(f"verdict: {verdict_text(result.adequacy)}")
        fb = result.adequacy.get("fallback") or {}
        if fb.get("used"):
            estimate = "replaced" if fb.get("trigger") == "inadequate" else "inadmissible"
            print(f"  the simpler model was chosen by {fb['chosen_by']}; the {estimate} estimate is in the "
                  f"JSON (adequacy.fallback)")
    drive = result.model.provenance.get("drive_fit")
    if drive:
        print("exciter (--drive): " + (
            f"distortion u2 {drive['drive_u2']:.4g}, roll-off {drive['drive_hp_hz']:.3g} Hz; held-out NRMSE "
            f"{nrmse_text(drive['held_out_nrmse_without'])} -> {nrmse_text(drive['held_out_nrmse_with'])}"
            if drive.get("applied")
            else f"not kept ({drive.get('reason') or drive.get('failed')})"))
    rule = result.model.provenance.get("input_offset_rule") or {}
    if rule.get("on"):
        print(f"input offset fitted ({result.model.input_offset:.4g}): {rule['reason']}")
    d = result.differentiation.get("nonlinear")
    if d:
        print(f"Savitzky-Golay (nonlinear stage): window {d['window']}, order {d['order']}, "
              f"noise level {', '.join(f'{k} {v:.3g}' for k, v in d['noise_level'].items())}")
    if result.sparse.get("threshold") is not None:
        print(f"sparse regression: {result.sparse['n_terms']} library terms, threshold "
              f"{result.sparse['threshold']:.3g}; linear step condition number {result.linear.condition_number:.3g}")
    if "uncertainty" in out:
        from workflows.report import interval_lines  # heavy: matplotlib, with --uncertainty only
        print(*interval_lines(out), sep="\n")
    for p in out.get("plots", []):
        print(f"plot: {p}")
    return 0


def check_outputs(args) -> None:
    """The output paths of reconstruct and diagnose, checked before anything is computed."""
    force = getattr(args, "force", False)
    if getattr(args, "save_model", None):
        check_output(args.save_model, overwrite=force, option="--save-model", never_hdf5=True, what="model JSON")
    for option in ("plots", "report"):
        value = getattr(args, option, None)
        if isinstance(value, (str, Path)) and value:
            check_directory(value, option="-o")


def _recon_settings(args) -> dict:

    if args.library_order < 2 or args.library_order > 8:
        raise UserFacingError(f"--library-order must be between 2 and 8, got {args.library_order}")
    if args.resamples < 50:
        raise UserFacingError(f"--resamples must be at least 50, got {args.resamples}")
    return {"library_order": args.library_order, "polish": not args.no_polish,
            **({"form": args.form} if getattr(args, "form", "joint") != "joint" else {}),
            **({"drive": True} if getattr(args, "drive", False) else {})}


def _term_models(args) -> int:

    if args.term_models < 0 or 0 < args.term_models < 5:
        raise UserFacingError(f"--term-models must be 0 (off) or at least 5, got {args.term_models}")
    return args.term_models


def report_command(args) -> int:

    rs = _recon_settings(args)
    if is_hdf5(args.run) and read_info(args.run)["mode"] == CONSTITUTIVE:
        refuse_drive_for_component_test(rs.get("drive", False), args.run)
        from workflows import constitutive  # heavy: matplotlib, for component tests only
        return constitutive.report_command(args, load_run(args.run))
    if getattr(args, "inertia", "none") != "none":
        raise UserFacingError(f"--inertia is for component tests (constitutive mode); {args.run} is a structure's run")
    from workflows.report import interval_lines, make_report  # heavy: matplotlib, the report's figures

    with progress_line(quiet=getattr(args, "quiet", False)):
        d = make_report(args.run, args.output, settings=ReconSettings(**rs), uncertainty=not args.no_uncertainty,
                        uncertainty_settings=UncertaintySettings(n_resamples=args.resamples),
                        write_back=not args.no_write_back, term_models=_term_models(args), overwrite=args.force)
    if args.json:
        print(json.dumps(d))
        return 0
    print(d["equation"])
    for w in d.get("warnings", []):
        print(f"warning: {w}")
    v = d["validation"]
    print(f"validation NRMSE on stage {v['stage']!r}: {nrmse_text(v['nrmse'])}" if v.get("nrmse") is not None
          else "validation: simulation diverged")
    if d.get("verdict_text"):
        print(f"verdict: {d['verdict_text']}")
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


def reprocess_command(args) -> int:

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
    with progress_line(quiet=args.quiet, done=None) as line:
        if line is None:
            print(f"reprocessing {len(paths)} run(s) on {where}", file=sys.stderr)
        else:
            line.note(f"reprocessing {len(paths)} run(s) on {where}")
        progress = TextProgress(len(paths), enabled=not args.quiet, line=line)
        rows = run_loop(paths, s, progress) if args.serial else run_batch(paths, s, progress)
    print(format_table(rows))
    print(f"summary: {write_csv(rows, args.csv)}")
    n_bad = sum(r["status"] == "failed" for r in rows)
    return 1 if n_bad else 0


def diagnose_command(args) -> int:

    check_outputs(args)
    candidates = getattr(args, "candidates", None)      # an unknown id: recon's diagnose refuses it first
    run = load_run(args.run)
    if run_mode(run) == CONSTITUTIVE:       # a component test: what its force law leaves out
        if candidates:
            raise UserFacingError("--candidates: a component test's diagnosis has its own catalog of force-law "
                                  "terms (docs/constitutive.md) and always fits all of them; drop the option")
        from workflows import constitutive  # heavy: matplotlib, for component tests only
        return constitutive.diagnose_command(args, run)
    with progress_line(quiet=getattr(args, "quiet", False)):
        progress.step("diagnosing", share=0.95 if args.report else 1.0)
        d = diagnose(run, baseline=args.baseline, candidates=candidates)
        out = d.to_dict()
        out["warnings"] = warnings_for(run) + out.get("baseline_warnings", [])
        out["result_text"] = diagnosis_text(out)
        if args.report:
            progress.step("figures", share=0.05)
            from workflows.diagnosis_report import write_report  # heavy: matplotlib, with -o only
            out["report"] = [str(p) for p in write_report(d, run, Path(args.report))]
    if args.save_model:
        d.best.save(args.save_model, overwrite=getattr(args, "force", False))
    if args.json:
        print(json.dumps(clean(out)))
        return 0
    print(f"{run.source}: baseline ({d.baseline_kind})")
    print(out["baseline"])
    if out.get("baseline_loop_as_friction"):
        print(f"  {friction_text(out['baseline_loop_as_friction'])}")
    for w in out["warnings"] + ([out["baseline_note"]] if out.get("baseline_note") else []):
        print(f"warning: {w}")
    fb, fa = out["fit_before"]["nrmse"], out["fit_after"]["nrmse"]
    print("NRMSE per stage: the baseline as given, refitted, and with what was found")
    for stage in fb:
        print(f"  {stage:16s} before {nrmse_text(fb[stage]):>10s}  refit "
              f"{nrmse_text(out['fit_before']['refit_nrmse'][stage]):>10s}  after {nrmse_text(fa[stage]):>10s}")
    if out["mismatch"]:
        print("where the baseline and the record disagree (largest first):")
        for f in out["mismatch"][:8]:
            print(f"  {finding_text(f)}")
    print(f"result: {out['result_text']}")
    for m in out["missing_physics"]:
        ps = ", ".join(f"{k} = {v['value']:.4g}" for k, v in m["parameters"].items())
        print(f"  {m['id']}: {m['explanation']} ({ps}); held-out NRMSE "
              f"{nrmse_text(m['evidence']['held_out_nrmse_before'])} -> "
              f"{nrmse_text(m['evidence']['held_out_nrmse_after'])}")
    if out["missing_physics"]:
        print("augmented model:\n" + out["fit_after"]["model"])
    else:
        # what "nothing found" covers: the size at which each candidate would show on this record (an estimate)
        lims = [(c["id"], c["detection_limit"]) for c in out["candidates_tested"]
                if (c.get("detection_limit") or {}).get("value") is not None]
        if lims:
            print("not seen above (detection limits on this record): "
                  + ", ".join(f"{cid} {d['parameter']} {d['value']:.3g}" for cid, d in lims))
    for p in out.get("report", []):
        print(f"report: {p}")
    return 0


def demo_command(args) -> int:
    from workflows.demo import run_demo  # heavy: the simulated rig and matplotlib
    return run_demo(args.output, realtime=args.realtime, protocol_path=args.protocol, seed=args.seed,
                    quiet=args.quiet, force=args.force)

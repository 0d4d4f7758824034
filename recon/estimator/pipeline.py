"""The estimator: one entry point that runs a form, compares fallback passes and revises the terms.

    from recon import reconstruct, ReconSettings
    result = reconstruct(run)            # run: shakerlab.run_data.Run
    result.model.print(); result.to_dict()
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from recon import progress
from recon.determinism import single_thread_blas
from recon.estimator.adequacy import assess
from recon.estimator.drive import fit_drive
from recon.estimator.fallback import (HYSTERETIC_KINDS, NUMERICAL_ERRORS, admissible, figures,
                                      fitted_stages, held_out_stages, score, simpler_models)
from recon.estimator.finish import validate
from recon.estimator.two_stage import two_stage_polish
from recon.estimator.input_offset import resolve_input_offset
from recon.estimator.pointwise import reconstruct_pointwise
from recon.estimator.result import ReconResult, ReconSettings
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.estimator.weak_form import reconstruct_weak
from recon.model import HystereticModel
from recon.output_error.polish import polish
from recon.output_error.problem import parameter_keys
from recon.output_error.term_selection import select_terms, stage_data
from recon.steps.bouc_wen import hysteretic_share, term_contributions
from shakerlab.errors import EstimateRefused, UserFacingError
from shakerlab.run_data import FORCE, Run

# the forms of the nonlinear step, each a function (run, settings, validate_model) -> ReconResult
FORMS = {"joint": reconstruct_pointwise, "ab": reconstruct_pointwise, "weak": reconstruct_weak}


@progress.task("reconstruct")
@single_thread_blas
def reconstruct(run: Run, settings: ReconSettings | None = None, validate_model: bool = True) -> ReconResult:
    """Identify the model.

    A pass is trusted when its equation-error estimate and its polished model are physically
    admissible. Otherwise the other passes run and the one whose simulation fits the
    nonlinear stage best is kept: with ``linear_correction="auto"`` a pass with the
    linear-correction columns (e.g. the linear stage was large enough for the hysteresis to
    bias c and K), and with ``fallback_form`` that form (the weak form's path rows hold where
    the pointwise regression is noise: at 60 dB, 2 of 50 noise seeds gave a negative alpha
    there, and the polish then ran to gamma, delta of 1e5).

    A pass that fails numerically (a singular matrix, an SVD that does not converge, overflow)
    counts as failed and the next one runs. When no pass gives an admissible model, the answer
    is the best admissible simpler model (:mod:`recon.estimator.fallback`), and the result's
    ``adequacy`` says so; the inadmissible estimate stays there for inspection. Input errors
    (a missing stage, a bad setting) still raise UserFacingError.

    ``input_offset="auto"`` (the default) is decided from the data first
    (:mod:`recon.estimator.input_offset`); the result's settings hold the decision and its
    model's provenance the figures (``input_offset_rule``)."""
    s, rule = resolve_input_offset(run, settings or ReconSettings())
    if s.drive and run.excitation != FORCE:
        raise UserFacingError(f"--drive needs force excitation ({run.source or 'the run'} is {run.excitation} "
                              f"excitation): it models the exciter between a recorded drive and the force")
    progress.step("the first estimate (equation error, then output-error polish)", share=0.45)
    result = _reconstruct_passes(run, s, validate_model)
    if s.drive:
        progress.step("fitting the exciter (--drive)", share=0.1)
        result = fit_drive(result, run, s)
    if rule is not None:
        result.model.provenance["input_offset_rule"] = rule
    return result


@dataclass(frozen=True)
class Pass:
    """One way to make the first estimate: a name, when it runs, and the settings it runs with."""
    name: Callable[[ReconSettings], str]
    runs: Callable[[ReconSettings], bool]
    settings: Callable[[ReconSettings], ReconSettings]


# The estimator's passes, in the order they run. The first is the answer when it is trusted
# (:func:`_trusted`); otherwise every pass that runs is made, and the one :func:`_preference` ranks
# first is concluded (its terms revised, the two stages fitted together, the simpler models
# compared when it is inadequate: :func:`_conclude`). When no pass is usable (admissible, with a
# finite validation), the answer is the best simpler model (:func:`_simpler`).
PASSES = (
    # the settings as given; with linear_correction "auto", first without the correction columns
    Pass(lambda s: "first", lambda s: True,
         lambda s: replace(s, linear_correction=False) if s.linear_correction == "auto" else s),
    # the columns that absorb the linear step's c/K error (the hysteresis of a large linear stage
    # biases them)
    Pass(lambda s: "linear_correction", lambda s: s.linear_correction == "auto",
         lambda s: replace(s, linear_correction=True)),
    # the other form (the weak form's path rows hold where the pointwise regression is noise)
    Pass(lambda s: f"form={s.fallback_form}", lambda s: bool(s.fallback_form and s.fallback_form != s.form),
         lambda s: replace(s, form=s.fallback_form, linear_correction=False)),
)


def _preference(r: ReconResult) -> tuple:
    """The one criterion passes are chosen by (lower first): trusted before untrusted, then the
    output-error cost of the polished model on the nonlinear stage."""
    info = r.model.provenance.get("output_error_polish", {})
    e = info.get("nrmse_after" if info.get("applied") else "nrmse_before", np.inf)
    return (not _trusted(r), e if np.isfinite(e) else np.inf)


def _usable(r: ReconResult, validate_model: bool) -> bool:
    return bool(admissible(r.model, r.settings.tuning)
                and (not validate_model or np.isfinite(r.validation.get("nrmse", 0.0))))


def _reconstruct_passes(run: Run, s: ReconSettings, validate_model: bool) -> ReconResult:
    """The PASSES as their module comment says."""
    failures = {}
    made = []           # (name, result) of every pass that gave a result
    for k, p in enumerate(pass_ for pass_ in PASSES if pass_.runs(s)):
        name = p.name(s)
        if k:
            progress.step(f"another pass ({name}): the first was not admissible", share=0.1)
        r = _attempt(name, run, p.settings(s), validate_model, failures)
        if r is None:
            continue
        r.settings = s
        if k:
            r.hysteresis_info["pass"] = name
        elif _trusted(r):
            return _conclude(r, run, s, validate_model, failures)
        made.append((name, r))
    usable = [(name, r) for name, r in made if _usable(r, validate_model)]
    if not usable:
        return _simpler(run, s, [r for _, r in made], failures, validate_model)
    _, best = min(usable, key=lambda nr: _preference(nr[1]))
    best.hysteresis_info["passes_compared"] = [name for name, _ in made]
    best.hysteresis_info.setdefault("pass", "first")
    best.hysteresis_info["linear_correction_pass"] = best.hysteresis_info["pass"] == "linear_correction"
    return _conclude(best, run, s, validate_model, failures)


def _attempt(name: str, run: Run, s: ReconSettings, validate_model: bool, failures: dict):
    """One pass; None (and the reason in ``failures``) when it fails numerically or refuses."""
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return _reconstruct(run, s, validate_model)
    except UserFacingError as e:
        # an input error reaches the user as it is; a part of the estimate the recording does not
        # determine (EstimateRefused: for example a nonlinear stage that never has y' and z of
        # opposite signs) is recorded, and the other passes and the simpler models follow
        if name == "first" and not isinstance(e, EstimateRefused):
            raise
        failures[name] = str(e)
    except NUMERICAL_ERRORS as e:
        failures[name] = f"{type(e).__name__}: {e}"
    return None


def _finish(result: ReconResult, run: Run, failures: dict, fallback: dict | None = None) -> ReconResult:
    if failures:
        result.hysteresis_info["failed_passes"] = dict(failures)
    result.adequacy = assess(result.model, result.validation, run, fallback,
                              getattr(result.settings, "tuning", DEFAULT_TUNING))
    return result


def _conclude(result: ReconResult, run: Run, s: ReconSettings, validate_model: bool, failures: dict) -> ReconResult:
    """An admissible result's end: its terms revised, both stages polished together, then checked
    against the simpler models."""
    progress.step("revising the fn terms", share=0.15)
    result = _revise_terms(result, run, s, validate_model, failures)
    progress.step("fitting the two stages together", share=0.25)
    result = _two_stage(result, run, s, validate_model)
    return _prefer_simpler(result, run, s, validate_model, failures)




def _prefer_simpler(result: ReconResult, run: Run, s: ReconSettings, validate_model: bool,
                    failures: dict) -> ReconResult:
    """The full model when it is adequate; when it is not (its validation NRMSE above the adequacy
    limit), the simpler models of fallback.py are fitted too, and one that predicts the held-out
    (validation) stages in at most ``s.tuning.simpler_gain`` of the full model's error is the answer. The
    estimator's structure can be wrong without being inadmissible: on a system without hysteresis
    the estimate can carry a Bouc-Wen law and validate far above the noise floor, while a simpler
    model's output-error fit reaches the floor. Needs a validation stage (the held-out data decide).

    Only simpler models that fit the nonlinear stage within ``s.tuning.simpler_fit_slack`` of the
    full model's error take part: a validation stage at a fraction of the nonlinear stage's
    amplitude (the rig protocol's) does not judge the terms that act at the larger one; a simpler
    model can predict such a validation stage better while fitting the nonlinear stage many times
    worse and diverging past it."""
    names, held = held_out_stages(run, (s.linear_stage, s.nonlinear_stage))
    first = _finish(result, run, failures)
    if not (validate_model and held and first.adequacy["verdict"] != "adequate"):
        return first
    v, limit = first.adequacy["validation_nrmse"], first.adequacy["nrmse_limit"]
    if not (math.isfinite(v) and v > limit):
        return first            # inadequate for another reason (its term count): no held-out case
    progress.step("comparing with the simpler models (the full model is inadequate)", share=0.1)
    full = score(result.model, run, names, s.tuning)
    try:
        fits = simpler_models(run, s, result.model, result.linear)
    except NUMERICAL_ERRORS as e:
        first.hysteresis_info["simpler_models_failed"] = f"{type(e).__name__}: {e}"
        return first
    # each simpler fit carries its own nonlinear-stage figure (fallback.simpler_models)
    full_nl = (score(result.model, run, [s.nonlinear_stage], s.tuning) if s.nonlinear_stage in run.stages
               else float("nan"))
    good = [f for f in fits if f.model is not None and np.isfinite(f.held_out_nrmse)
            and (not math.isfinite(full_nl) or f.nonlinear_stage_nrmse <= s.tuning.simpler_fit_slack * full_nl)]
    best = min(good, key=lambda f: f.held_out_nrmse) if good else None
    compared = {"full_model_held_out_nrmse": full, "gain_needed": s.tuning.simpler_gain,
                "full_model_nonlinear_stage_nrmse": full_nl, "fit_slack": s.tuning.simpler_fit_slack,
                "candidates": [f.to_dict(s.tuning) for f in fits]}
    if best is None or not best.held_out_nrmse < s.tuning.simpler_gain * full:
        first.adequacy["simpler_models_compared"] = compared
        return first
    fallback = {"used": True, "kind": best.kind, "trigger": "inadequate",
                "chosen_by": "held-out NRMSE on " + ", ".join(names)
                + f": {best.held_out_nrmse:.3g} against {full:.3g} for the inadequate full model",
                "candidates": compared["candidates"], "full_model_held_out_nrmse": full,
                "full_model_nonlinear_stage_nrmse": full_nl,
                "replaced_estimate": result.model.to_dict()["parameters"],
                "inadmissible_estimate": None, "failed_passes": dict(failures)}
    result.hysteresis_info["replaced_estimate"] = fallback["replaced_estimate"]
    return _adopt(result, best, fallback, run, s, validate_model)


def _simpler(run: Run, s: ReconSettings, candidates: list, failures: dict, validate_model: bool) -> ReconResult:
    """No admissible model from any pass: the best admissible simpler model (fallback.py)."""
    estimate = candidates[0] if candidates else None
    lin = estimate.linear if estimate is not None else None
    progress.step("fitting the simpler models (no admissible estimate)", share=0.3)
    fits = simpler_models(run, s, estimate.model if estimate is not None else None, lin)
    good = [f for f in fits if f.model is not None and np.isfinite(f.held_out_nrmse)]
    if not good:
        why = "; ".join(f"{k}: {v}" for k, v in failures.items()) or "every estimate was inadmissible"
        raise UserFacingError(f"{run.source or 'run'}: reconstruct found no admissible model. The passes gave: "
                              f"{why}. Simpler models: " + "; ".join(f"{f.kind}: {f.failed}" for f in fits)
                              + ". Check the stages (a linear stage well below resonance, a nonlinear stage "
                              "near it, the sensors' units and sign) or try --form weak.")
    names, held = held_out_stages(run, (s.linear_stage, s.nonlinear_stage))
    law = [f for f in good if f.kind in HYSTERETIC_KINDS]
    if law and s.polish:
        # the kinds are compared as each would answer: the best Bouc-Wen fit with its terms revised and
        # its two stages fitted together (what _adopt does to it), not the fit of the terms the
        # inadmissible estimate happened to offer
        lead = min(law, key=lambda f: f.held_out_nrmse)
        _finish_law(estimate, lead, run, s)
        lead.held_out_nrmse, lead.fitted_nrmse, lead.nonlinear_stage_nrmse = figures(
            lead.model, run, names, fitted_stages(run, s), s.nonlinear_stage, s.tuning)
    best = min(good, key=lambda f: f.held_out_nrmse)
    fallback = {"used": True, "kind": best.kind, "trigger": "inadmissible",
                "chosen_by": "held-out NRMSE on " + ", ".join(names)
                + ("" if held else " (no validation stage: the fitted nonlinear stage)"),
                "candidates": [f.to_dict(s.tuning) for f in fits],
                "inadmissible_estimate": (estimate.model.to_dict()["parameters"] if estimate is not None else None),
                "failed_passes": dict(failures)}
    if estimate is not None:
        estimate.hysteresis_info = dict(estimate.hysteresis_info,
                                        inadmissible_estimate=fallback["inadmissible_estimate"])
    return _adopt(estimate, best, fallback, run, s, validate_model)


def _finish_law(result: ReconResult | None, fit, run: Run, s: ReconSettings) -> None:
    """A simpler fit of the Bouc-Wen kinds (``fit``, a fallback.SimplerFit) made into the answer it would
    be, in place and once (``fit.finished``): its fn terms revised by output error and its two stages
    fitted together, as the full model's are. Other kinds are left as they are."""
    if fit.finished:
        return
    fit.model.provenance = {"simpler_model": fit.kind, "settings": {"linear_stage": s.linear_stage,
                                                                    "nonlinear_stage": s.nonlinear_stage}}
    if fit.kind not in HYSTERETIC_KINDS:
        return
    fit.finished = True
    if s.polish and admissible(fit.model, s.tuning):
        # a Bouc-Wen law fitted by output error from a generic start is the full model's form, and
        # its fn terms are only those the inadmissible estimate offered: the output error revises
        # them as it revises the full model's (a weak true term the equation error missed is added)
        holder = result if result is not None else ReconResult.of_model(fit.model, {}, s)
        holder.model = fit.model
        fit.model = _revise_terms(holder, run, s, validate_model=False).model
    if s.polish and s.two_stage_polish and admissible(fit.model, s.tuning):
        # a Bouc-Wen law fitted on the nonlinear stage: the two stages decide its terms as for the full
        # model (at low SNR a law fitted on one stage can carry a spurious term beside the true one)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            fit.model = two_stage_polish(fit.model, run, s)


def _adopt(result: ReconResult | None, best, fallback: dict, run: Run, s: ReconSettings,
           validate_model: bool) -> ReconResult:
    """``result`` (or a new result when there is none) answering with the simpler model ``best``."""
    _finish_law(result, best, run, s)
    val = validate(best.model, run, tuning=s.tuning) if validate_model else {"nrmse": float("nan"), "stage": None}
    if result is None:
        result = ReconResult.of_model(best.model, val, s)
    result.model = best.model
    result.validation = val
    result.settings = s
    result.hysteresis_info["simpler_model"] = best.kind
    return _finish(result, run, {}, fallback)


def _trusted(r: ReconResult) -> bool:
    """Admissible from its equation-error estimate on, and its validation is finite and better than
    predicting zero (NRMSE below 1)."""
    v = r.validation.get("nrmse", 0.0)
    return bool(admissible(r.model, r.settings.tuning) and r.hysteresis_info.get("equation_error_admissible", True)
                and np.isfinite(v) and not v >= 1.0)


def _two_stage(result: ReconResult, run: Run, s: ReconSettings, validate_model: bool) -> ReconResult:
    """The linear and nonlinear stages polished together (recon.estimator.two_stage.two_stage_polish),
    re-validated when the joint fit is kept."""
    if not (s.polish and s.two_stage_polish and admissible(result.model, s.tuning)):
        return result
    t0 = time.perf_counter()
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        model = two_stage_polish(result.model, run, s)
    result.timings["two_stage_polish"] = time.perf_counter() - t0
    kept = model is not result.model
    result.model = model
    if kept and validate_model:
        result.validation = validate(model, run, tuning=s.tuning)
    return result


def _revise_terms(result: ReconResult, run: Run, s: ReconSettings, validate_model: bool,
                  failures: dict | None = None) -> ReconResult:
    """:func:`_revise_model_terms`; a numerical failure there keeps the unrevised result."""
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return _revise_model_terms(result, run, s, validate_model)
    except NUMERICAL_ERRORS as e:
        if failures is not None:
            failures["term_revision"] = f"{type(e).__name__}: {e}"
        return result


def _revise_model_terms(result: ReconResult, run: Run, s: ReconSettings, validate_model: bool) -> ReconResult:
    """Revise the fn terms of the polished model on the nonlinear stage (needs ``s.polish``):

    1. term selection by output error (recon/term_selection.py, with ``s.term_selection``),
       then a polish of the selected structure on the whole (decimated) stage;
    2. drop the terms the output error left negligible (rms below ``s.tuning.negligible`` of the
       elastic force, as in chains) and polish once more. At 60 dB the term selection kept a y^4*dy
       of 0.04 % in 13 of 50 noise seeds (its held-out gain was within the information
       criterion's margin).
    A revised model replaces the result's only if it stays admissible; it is re-validated."""
    t = s.tuning
    if not s.polish or not admissible(result.model, t):
        return result
    stage = run.stage(s.nonlinear_stage)
    data, q, _ = stage_data(result.model, stage, t)
    changed = False
    if s.term_selection:
        tp = time.perf_counter()
        model, info = select_terms(result.model, stage, data=(data, q), tuning=t)
        if info["applied"]:
            model, pinfo = polish(model, [data], max_nfev=30, tuning=t)
            info["final_polish"] = pinfo
            if not admissible(model, t):
                model = _without_vanished_hysteresis(model, data, info, t)
            model.provenance = dict(result.model.provenance)
            model.provenance["term_selection"] = info
            if admissible(model, t):
                result.model, changed = model, True
        else:
            result.model.provenance["term_selection"] = info
        result.timings["term_selection"] = time.perf_counter() - tp
    m = result.model
    y, dy = result.signals.get("y"), result.signals.get("dy")
    if m.fn_m and y is not None and dy is not None:
        share = term_contributions(m.fn_m, m.K_m, y, dy)
        small = sorted(k for k, v in share.items() if v < t.negligible)
        if small:
            trial = HystereticModel.from_dict(m.to_dict())
            for k in small:
                del trial.fn_m[k]
            trial, pinfo = polish(trial, [data], max_nfev=30, tuning=t)
            if admissible(trial, t):
                trial.provenance = dict(m.provenance)
                trial.provenance["pruned"] = {"terms": small, "threshold": t.negligible, "polish": pinfo,
                                              "share_of_elastic_force": {k: share[k] for k in small}}
                result.model, changed = trial, True
    if changed:
        t2 = time.perf_counter()
        if validate_model:
            result.validation = validate(result.model, run, tuning=t)
        result.timings["validation"] = time.perf_counter() - t2
    return result


def _without_vanished_hysteresis(model: HystereticModel, data: tuple, info: dict,
                                 tuning: EstimatorTuning) -> HystereticModel:
    """``model`` without its Bouc-Wen law, polished on ``data``, when the law's force has vanished
    (rms z below ``tuning.negligible`` of the elastic force on the stage) and only it made ``model``
    inadmissible; else ``model`` as it is. ``info`` (the term selection's) gets the figures.

    A law the equation-error step put in for a term it missed can fall to nothing once the term
    selection adds that term, with an alpha of either sign: on a system with y^2 and no hysteresis,
    a large alpha beside a spurious term can become, once y^2 is added, a tiny negative alpha
    beside the true y^2 and k, a z of a fraction of a per cent of the elastic force. That
    model is inadmissible for its alpha alone: without this step the revision would be thrown away
    and the diagnosis would later name the y^2 the baseline lacks."""
    share = hysteretic_share(model, data[0], data[1])
    record = {"hysteretic_share": share, "threshold": tuning.negligible, "applied": False}
    info["vanished_hysteresis"] = record
    if not share < tuning.negligible:
        return model
    trial = HystereticModel.from_dict(model.to_dict())
    trial.k_m = model.K_m
    trial.alpha_m = trial.gamma = trial.delta = 0.0
    free = [k for k in parameter_keys(trial) if k not in ("alpha_m", "gamma", "delta")]
    trial, pinfo = polish(trial, [data], max_nfev=30, free=free, tuning=tuning)
    record["polish"] = pinfo
    if not admissible(trial, tuning):
        return model
    record["applied"] = True
    return trial


def _reconstruct(run: Run, s: ReconSettings, validate_model: bool = True) -> ReconResult:
    return FORMS[s.form](run, s, validate_model)

"""Is the reconstructed model adequate? A verdict with the figures that decide it.

The verdict is ``adequate`` when the model is admissible, its validation NRMSE is within
``noise_factor`` times the noise floor of the validation recording (or below
``nrmse_floor``, whichever is larger) and it has no more fn terms than ``max_fn_terms``
(recon.estimator.tuning);
otherwise ``inadequate``, with the reasons. A fallback to a simpler model without hysteresis
(equivalent-linear, linear) is always inadequate; a fallback of the law's own (Bouc-Wen) form,
fitted by output error from a generic start, is judged by the same figures as any estimate. The noise floor is the NRMSE a perfect model
would score: the validation record's noise (from its spectrum's flat tail) over its rms, both in
the quantity the response was recorded in (a velocity record's velocity: validation compares the
simulated y' with it, recon.estimator.finish.validate). The noise is the fits' own unit
(recon.signals.target_noise_std): for an acceleration record, integrated once to the velocity the
fits compare, it counts the integral's random walk as well as the velocity's white floor.
An inadequate model points to ``shakerlab diagnose``.
"""
from __future__ import annotations

import math

import numpy as np

from recon.estimator.fallback import HYSTERETIC_KINDS, admissible
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.signals import compared_response, target_noise_std
from shakerlab.run_data import Run
from shakerlab.words import nrmse_text



def noise_floor(run: Run, stage: str | None) -> float | None:
    if stage is None or stage not in run.stages:
        return None
    st = run.stage(stage)
    x = compared_response(st)      # the record in its own quantity, as validation judges it
    y = x - np.mean(x)
    rms = float(np.sqrt(np.mean(y ** 2)))
    if rms <= 0:
        return None
    return target_noise_std(st) / rms       # the fits' noise unit, as a share of the record


def verdict(ok: bool, v: float, floor: float | None, n_fn: int, fitted_on_validation: bool,
            subject: str = "model", simpler: str | None = None, tuning: EstimatorTuning = DEFAULT_TUNING) -> dict:
    """The verdict from its figures: admissibility ``ok``, validation NRMSE ``v``, the record's noise
    floor, the number of fn terms; ``simpler`` names a fallback kind without hysteresis (always
    inadequate). The keys every adequacy in the JSON has."""
    v = float(v) if v is not None else float("nan")
    factor, lowest, most = tuning.noise_factor, tuning.nrmse_floor, tuning.max_fn_terms
    limit = max(factor * floor, lowest) if floor is not None else lowest
    reasons = []
    if not ok:
        reasons.append(f"the {subject} is not physically admissible")
    if not math.isfinite(v):
        reasons.append("its validation simulation diverges or was not run")
    elif v > limit:
        reasons.append(f"validation NRMSE {v:.3g} is above {limit:.3g} "
                       f"(max of {factor:g} x the noise floor and {lowest:g})")
    if n_fn > most:
        reasons.append(f"{n_fn} fn terms, more than the {most} a TMP-like law needs")
    if fitted_on_validation:
        reasons.append("no validation stage: the NRMSE is on the fitted stage")
    if simpler:
        reasons.append(f"the full model was not admissible; this is the simpler {simpler} model")
    good = ok and math.isfinite(v) and v <= limit and n_fn <= most and not simpler
    return {"verdict": "adequate" if good else "inadequate", "admissible": ok, "validation_nrmse": v,
            "noise_floor_nrmse": floor, "nrmse_limit": limit, "fn_terms": n_fn, "max_fn_terms": most,
            "reasons": reasons}


def assess(model, validation: dict, run: Run, fallback: dict | None = None,
           tuning: EstimatorTuning = DEFAULT_TUNING) -> dict:
    """The adequacy verdict of ``model`` (JSON-ready)."""
    # a simpler kind without hysteresis standing in for an inadmissible estimate is always
    # inadequate; one chosen over an inadequate full model on the held-out data is judged by its figures
    simpler = fallback["kind"] if (fallback and fallback.get("used") and fallback.get("trigger") != "inadequate"
                                    and fallback.get("kind") not in HYSTERETIC_KINDS) else None
    out = verdict(admissible(model, tuning), validation.get("nrmse"), noise_floor(run, validation.get("stage")),
                  len(model.fn_m), bool(validation.get("fitted_on_validation_stage")), "model", simpler, tuning)
    if out["verdict"] != "adequate":
        out["advice"] = "run `shakerlab diagnose` on this run to locate and name what the model leaves out"
    if fallback:
        out["fallback"] = fallback
    return out


def one_line(adequacy: dict) -> str:
    """``reconstruct``'s text line: admissibility and adequacy together."""
    v, floor = adequacy["validation_nrmse"], adequacy.get("noise_floor_nrmse")
    figs = f"validation NRMSE {v:.3g}" + (f", noise floor {floor:.2g}" if floor is not None else "") \
        + f", {adequacy['fn_terms']} fn term(s)"
    line = f"admissible: {'yes' if adequacy['admissible'] else 'NO'}; adequacy: {adequacy['verdict']} ({figs})"
    if adequacy["verdict"] != "adequate":
        line += f": {'; '.join(adequacy['reasons'])}; run `shakerlab diagnose`"
    return line


# the one sentence a person reads about a model, everywhere it is shown (command line, JSON key
# ``verdict_text``, HTML report banner, demo, reprocess table, operator window); ``level`` picks
# the banner colour: "good" (adequate), "warning" (adequate, but a simpler model stands in for the
# full one), "bad" (inadequate)
FALLBACK_WHY = {"inadmissible": "the full model was not physically admissible",
                "inadequate": "the full model was admissible but predicted the held-out data worse"}


def verdict_summary(adequacy: dict | None) -> dict:
    """{"level", "label", "text"} of a model's adequacy (the ``adequacy`` of a reconstruction's JSON).

    The text names, in this order and never contradicting itself: which model is the answer (the
    full model, or the simpler model standing in for it and why), whether it is admissible,
    whether it is adequate with the figures that decide it, and what to do next."""
    if not adequacy:
        return {"level": "warning", "label": "no verdict", "text": "No verdict: the model was not validated."}
    good = adequacy.get("verdict") == "adequate"
    fb = adequacy.get("fallback") or {}
    v, limit = adequacy.get("validation_nrmse"), adequacy.get("nrmse_limit")
    problems = []
    if not adequacy.get("admissible", True):
        problems.append("it is not physically admissible")
    if v is None or not math.isfinite(float(v)):
        problems.append("its validation simulation diverged")
    elif limit is not None and float(v) > float(limit):
        problems.append(f"its validation NRMSE {nrmse_text(v)} is above the {nrmse_text(limit)} limit")
    most = adequacy.get("max_fn_terms", DEFAULT_TUNING.max_fn_terms)
    if adequacy.get("fn_terms", 0) > most:
        problems.append(f"it has {adequacy['fn_terms']} fn terms (more than {most})")
    if fb.get("used") and fb.get("kind") not in HYSTERETIC_KINDS:
        problems.append("a model without hysteresis cannot stand for the specimen")
    if any("no validation stage" in r for r in adequacy.get("reasons", [])):
        problems.append("there is no validation stage (its NRMSE is on the fitted stage)")
    if fb.get("used"):
        why = FALLBACK_WHY.get(fb.get("trigger"), "the full model was set aside")
        subject = f"Fallback: {why}, so the answer is the simpler {fb.get('kind')} model; it"
    else:
        subject = "The model"
    figs = f"validation NRMSE {nrmse_text(v)}" + (f", limit {nrmse_text(limit)}" if limit is not None else "")
    if good:
        text = f"{subject} is admissible and adequate ({figs})."
        label = "adequate (simpler model)" if fb.get("used") else "adequate"
        level = "warning" if fb.get("used") else "good"
    else:
        if adequacy.get("admissible", True):
            text = f"{subject} is admissible but inadequate: {'; '.join(problems) or 'see adequacy.reasons'}."
        else:
            text = f"{subject} is inadequate: {'; '.join(problems)}."
        text += " Run `shakerlab diagnose` to locate and name what it leaves out."
        label, level = ("inadequate fallback" if fb.get("used") else "inadequate"), "bad"
    return {"level": level, "label": label, "text": text[0].upper() + text[1:]}


def verdict_text(adequacy: dict | None) -> str:
    """The one sentence of :func:`verdict_summary`."""
    return verdict_summary(adequacy)["text"]

"""The end every form shares: admissibility (recon.estimator.fallback.admissible), output-error polish,
validation."""
from __future__ import annotations

import time

import numpy as np

from recon.estimator.adequacy import noise_floor
from recon.estimator.fallback import NUMERICAL_ERRORS, admissible, with_term_scales
from recon.estimator.result import ReconSettings
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.model import HystereticModel
from recon.output_error.polish import decimate, item_cost, polish
from recon.validation import nrmse
from shakerlab.run_data import Run


def validate(model: HystereticModel, run: Run, skip: tuple = (), tuning: EstimatorTuning = DEFAULT_TUNING) -> dict:
    names = [n for n in run.stages if n.startswith("validation")]
    if not names:
        names = [n for n in ("nonlinear",) if n in run.stages]
    out = {}
    for n in names:      # in the quantity the response was recorded in (HystereticModel.simulate_measured)
        out[n] = nrmse(*model.simulate_measured(run.stage(n), tuning))
    main = names[0] if names else None
    return {"nrmse": out.get(main, float("nan")), "stage": main, "per_stage": out,
            "fitted_on_validation_stage": main == "nonlinear"}


def restart_fn_terms(model: HystereticModel, item: tuple, polish_info: dict,
                     tuning: EstimatorTuning = DEFAULT_TUNING):
    """Polish the estimate again from restarted fn terms when the estimate itself does not
    simulate the stage; the term selection by output error (recon.output_error.term_selection)
    then decides the fn terms from a model that simulates.

    The fn terms are the least-determined part of the equation-error estimate; the terms in y
    alone are the best determined of them (y is the least noisy column). Two restarts, the
    better admissible polish kept: (a) no fn terms; (b) the stiffness terms y^2 and y^3 (started
    at 1 % of the elastic force, or at the estimate's value when it has them). A usable restart
    simulates the stage better than ``tuning.start_nrmse_limit`` (1: better than predicting zero;
    a start that diverges or does worse leaves the trust region no finite neighbourhood).
    Why both: on one tone, the harmonic identity y y'^2 = w^2 (A^2 y - y^3) makes y y'^2 and y'^5
    nearly collinear with y^3, and an estimate can swap the true term for them and diverge; from
    (a) the term selection finds the true term again. Where the truth has hardening terms, (b) is
    needed: without them the Bouc-Wen law imitates the hardening with gamma + delta < 0."""
    restarts = {}
    stiff = {k: model.fn_m.get(k, 0.0) for k in ("y^2", "y^3")}
    for name, fn in (("without_fn", {}), ("stiffness_terms", stiff)):
        trial = HystereticModel.from_dict(model.to_dict())
        trial.fn_m = dict(fn)
        trial = with_term_scales(trial, [item])
        new, info = polish(trial, [item], tuning=tuning)
        ok = bool(info["applied"] and admissible(new, tuning) and info["nrmse_after"] < tuning.start_nrmse_limit)
        restarts[name] = {"fn_terms": sorted(fn), "admissible": admissible(new, tuning), **info,
                          "model": new if ok else None}
    good = [(r["nrmse_after"], name) for name, r in restarts.items() if r["model"] is not None]
    record = {"start_nrmse": polish_info["nrmse_before"], "dropped_terms": sorted(model.fn_m),
              **{name: {k: v for k, v in r.items() if k != "model"} for name, r in restarts.items()}}
    if not good:
        return model, {**polish_info, "restart": record}
    _, name = min(good)
    record["kept"] = name
    info = {k: v for k, v in restarts[name].items() if k not in ("model", "fn_terms", "admissible")}
    return restarts[name]["model"], {**info, "restart": record}


# A polished fit whose cost on the nonlinear stage, past its start's transient (:func:`settled_cost`),
# is above ``tuning.floor_factor`` times the stage's noise floor (recon.estimator.adequacy.noise_floor)
# may not have found the record's optimum: the polish restarts from generic Bouc-Wen starts
# (:func:`generic_restarts`), and keeps a restart only where it fits better. The transient of a start
# no fit observes whole holds even the truth's cost over the whole stage above the floor; past it the
# truth is at the floor. Filter and model errors can still hold a fit above it at a high SNR: there
# the restarts run and change nothing, which costs time, not answers.


def settled_cost(model: HystereticModel, item: tuple, tuning: EstimatorTuning = DEFAULT_TUNING) -> float:
    """``model``'s output-error cost (NRMSE, as the polish takes it) on ``item`` past the transient of
    its start: the first ``tuning.start_decays`` decay times of the model's mode (2 / c each) are
    left out, unless less than half of the stage would remain. No fit observes a stage's start
    state whole: a stage recorded in motion leaves the hysteresis state z unobserved, and one taken
    as recorded from rest may still ring at a few noise stds from the stage before; the error of
    even the true model's start decays only with the mode. What the restart's floor test compares
    with the noise floor (:func:`polish_and_validate`): a fit in a wrong basin errs over the whole
    stage, a start's transient only at its beginning."""
    d, _ = decimate(item, tuning.polish_fs)       # item_cost's own decimation then leaves it as it is
    t = np.asarray(d[0], float)
    mask = None
    if model.c_m > 0 and tuning.start_decays > 0:
        cut = t >= t[0] + tuning.start_decays * 2.0 / model.c_m
        mask = cut if 2 * np.count_nonzero(cut) >= t.size else None
    return item_cost(model, d, tuning, mask)[0]


def generic_starts(model: HystereticModel, data: list, tuning: EstimatorTuning = DEFAULT_TUNING):
    """The generic Bouc-Wen starts (share, knee, model) of :func:`generic_restarts` on ``data`` (the
    last item is the nonlinear stage, whose amplitude sets the knee)."""
    amp = float(np.sqrt(2.0) * np.std(data[-1][2])) or 1.0
    K = model.K_m
    stiff = {k: model.fn_m.get(k, 0.0) for k in ("y^2", "y^3")}
    for share in tuning.alpha_shares:
        for knee in tuning.knees:
            trial = HystereticModel.from_dict(model.to_dict())
            trial.k_m, trial.alpha_m = (1.0 - share) * K, share * K
            trial.gamma = trial.delta = 0.5 * knee / amp
            trial.fn_m = dict(stiff)
            yield share, knee, with_term_scales(trial, data)


def generic_restarts(model: HystereticModel, item: tuple, polish_info: dict, floor: float,
                     tuning: EstimatorTuning = DEFAULT_TUNING):
    """Polish again from generic starts when the polished model does not fit the nonlinear stage
    to its noise floor: the equation-error estimate put the polish in another basin.

    Starts: the small-amplitude stiffness K of the polished model split into alpha = s K,
    k = (1 - s) K for s in ``tuning.alpha_shares``, the knee at lambda Y in ``tuning.knees``
    (gamma = delta), the polished model's y^2 and y^3 (or 1 % of the elastic force). Each is
    polished briefly (``tuning.screen_nfev``); the best is polished to the end and kept when it is
    admissible and fits better than the model it replaces. An equation-error estimate whose loop
    is far too wide or too narrow (lambda a hundred times off) polishes into a basin with k < 0 at
    ten times the noise floor; a generic start near the true share and knee reaches the floor."""
    screened = []
    for share, knee, trial in generic_starts(model, [item], tuning):
        try:
            new, info = polish(trial, [item], max_nfev=tuning.screen_nfev, tuning=tuning)
        except NUMERICAL_ERRORS:
            continue
        if np.isfinite(info["nrmse_after"]):
            screened.append((info["nrmse_after"], share, knee, new))
    record = {"cost_before": polished_cost(polish_info),
              "noise_floor": floor, "screened": [{"alpha_share": s, "knee": k, "cost": c} for c, s, k, _ in screened]}
    if not screened:
        return model, {**polish_info, "generic_restart": record}
    _, share, knee, best = min(screened, key=lambda r: r[0])
    try:
        new, info = polish(best, [item], tuning=tuning)
    except NUMERICAL_ERRORS:
        return model, {**polish_info, "generic_restart": record}
    cost = info["nrmse_after"] if info["applied"] else info["nrmse_before"]
    record.update(kept_start={"alpha_share": share, "knee": knee}, cost_after=cost)
    if admissible(new, tuning) and cost < record["cost_before"]:
        record["applied"] = True
        return new, {**polish_info, "nrmse_after": cost, "generic_restart": record}
    record["applied"] = False
    return model, {**polish_info, "generic_restart": record}


def polished_cost(polish_info: dict) -> float:
    """The output-error cost (NRMSE) of the model a polish returned."""
    v = polish_info.get("nrmse_after") if polish_info.get("applied") else polish_info.get("nrmse_before")
    return float(v) if v is not None else float("inf")


def continue_polish(model: HystereticModel, item: tuple, polish_info: dict,
                    tuning: EstimatorTuning = DEFAULT_TUNING):
    """Polish again from where a polish stopped at its evaluation budget (``tuning.polish_nfev``; at
    most ``tuning.continue_rounds`` more rounds, while the cost falls).

    A polish started far from the optimum (an equation-error k a hundred times too small) spends
    its budget on the way and stops short of the optimum with parameters several per cent off.
    Returns (model, polish_info); ``polish_info["continued"]`` records the rounds."""
    rounds = []
    info = polish_info
    while info.get("applied") and info.get("nfev", 0) >= tuning.polish_nfev and len(rounds) < tuning.continue_rounds:
        try:
            new, info = polish(model, [item], tuning=tuning)
        except NUMERICAL_ERRORS as exc:
            rounds.append({"failed": f"{type(exc).__name__}: {exc}"})
            break
        before, after = polished_cost(polish_info), polished_cost(info)
        rounds.append({"cost_before": before, "cost_after": after, "nfev": info.get("nfev")})
        if not (info["applied"] and admissible(new, tuning) and after < before):
            break
        model = new
        polish_info = {**polish_info, "nrmse_after": after}
    if rounds:
        polish_info = {**polish_info, "continued": rounds}
    return model, polish_info


def refine_start(model: HystereticModel, stage, item: tuple, polish_info: dict,
                 tuning: EstimatorTuning = DEFAULT_TUNING):
    """Re-estimate the start state of a stage that starts in motion with the polished model, and
    polish again from it (at most ``tuning.start_rounds`` times, while the cost falls).

    The start of such a stage is fitted to its first seconds with the model at hand
    (recon.simulation.start_state); the polish then keeps it fixed. Fitted with the equation-error
    estimate, it carries that estimate's errors into the polish: a start velocity many times the
    true one holds the polish, and even a fit started at the truth, at ten times the noise floor
    with the loop's shape off. Returns
    (model, item, polish_info); ``polish_info["start_refined"]`` records the rounds."""
    rounds = []
    for _ in range(tuning.start_rounds):
        if model.stage_start(stage, fit=False, tuning=tuning) == (0.0, 0.0, 0.0):
            break                                   # recorded from rest: no start to refine
        try:
            item2 = model.fit_item(stage, tuning=tuning)
            if np.allclose(item2[3], item[3], rtol=1e-6, atol=0.0):
                break
            new, info = polish(model, [item2], tuning=tuning)
        except NUMERICAL_ERRORS as exc:
            rounds.append({"failed": f"{type(exc).__name__}: {exc}"})
            break
        before, after = polished_cost(polish_info), polished_cost(info)
        rounds.append({"start": [float(v) for v in item2[3]], "cost_before": before, "cost_after": after})
        if not (admissible(new, tuning) and after < before):
            break
        model, item = new, item2
        polish_info = {**polish_info, "applied": True, "nrmse_after": after}
    if rounds:
        polish_info = {**polish_info, "start_refined": polish_info.get("start_refined", []) + rounds}
    return model, item, polish_info


def polish_and_validate(model: HystereticModel, run: Run, s: ReconSettings, info: dict, timings: dict,
                        validate_model: bool):
    """The common end of every form: mark whether the equation-error estimate is admissible
    (``info``), polish it by output error on the nonlinear stage (``s.polish``), record both in
    the provenance and validate. Returns (model, validation)."""
    t = s.tuning
    info["equation_error_admissible"] = admissible(model, t)
    equation_error_model = model
    polish_info = {"applied": False}
    if s.polish and info["equation_error_admissible"]:
        if s.input_offset is True and model.input_offset is None:
            model.input_offset = 0.0       # a parameter of the polish from here on (ReconSettings)
        tp = time.perf_counter()
        stage = run.stage(s.nonlinear_stage)
        item = model.fit_item(stage, tuning=t)
        model, polish_info = polish(model, [item], tuning=t)
        model, polish_info = continue_polish(model, item, polish_info, t)
        if model.fn_m and not polish_info["applied"] and not polish_info["nrmse_before"] < t.start_nrmse_limit:
            model, polish_info = restart_fn_terms(model, item, polish_info, t)
        model, item, polish_info = refine_start(model, stage, item, polish_info, t)
        floor = noise_floor(run, s.nonlinear_stage)
        if floor and model.alpha_m > 0:
            # the floor test: is the fit at the noise floor where its start no longer matters?
            settled = settled_cost(model, item, t)
            polish_info["floor_test"] = {"noise_floor": floor, "cost": polished_cost(polish_info),
                                         "settled_cost": settled, "limit": t.floor_factor * floor,
                                         "restart": bool(settled > t.floor_factor * floor)}
            if polish_info["floor_test"]["restart"]:
                model, polish_info = generic_restarts(model, item, polish_info, floor, t)
                if polish_info["generic_restart"].get("applied"):
                    model, item, polish_info = refine_start(model, stage, item, polish_info, t)
        timings["polish"] = time.perf_counter() - tp
    elif s.polish:
        # no polish from an inadmissible start: an estimate whose Bouc-Wen split cancels (k and alpha
        # huge and opposite) can take minutes to polish without reaching an admissible model; the
        # pipeline's other passes run instead
        polish_info = {"applied": False, "skipped": "the equation-error estimate is not admissible"}
    model.provenance["equation_error_estimate"] = equation_error_model.to_dict()["parameters"]
    model.provenance["output_error_polish"] = polish_info
    t2 = time.perf_counter()
    val = validate(model, run, tuning=t) if validate_model else {"nrmse": float("nan"), "stage": None}
    timings["validation"] = time.perf_counter() - t2
    return model, val

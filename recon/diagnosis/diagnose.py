"""Mismatch diagnosis: locate, name the missing physics, model it, show the fit improve.

    from recon.diagnosis.diagnose import diagnose
    d = diagnose(run, baseline="paper")       # or "linear", a model JSON path, a HystereticModel,
                                              # a component test's law JSON (recon.constitutive.bridge)
    d.to_dict()                               # the JSON contract of ``shakerlab diagnose --json``

The diagnosis is a sequence of named steps, each a function of this module reading a
:class:`~recon.diagnosis.context.DiagnosisContext`:

1. :func:`reference_step`: the baseline, refitted by output error (the *null* model), and the
   reference every candidate must beat: the better of the null model and the baseline as given
   (:mod:`.references`).
2. :func:`locate_step`: where the reference misses (:mod:`.locate`).
3. :func:`.references.candidate_origins`: where candidate fits start, and the null models found
   on the way.
4. :func:`score_candidates`: each catalog candidate (:mod:`.catalog`) fitted from each origin
   (:mod:`.candidate_fit`), refitted without the baseline terms that absorbed it and scored on the
   held-out samples against its reference and its nested null (:func:`score_candidate`,
   :mod:`.refits`, :mod:`.rank`).
5. :func:`rescore_against_best_null`, :func:`hold_to_every_stage`: every candidate must beat the best
   null model found anywhere, and be no worse on any held-out stage (:mod:`.stagewise`).
6. :func:`revision_step`: when none is significant, the one that explains most refitted with the
   baseline's fn terms chosen again under it (:mod:`.term_revision`); :func:`pair_search`,
   :func:`forward_step`: two candidates together when none is significant alone; a runner-up only
   if it adds on top of the best one.
7. :func:`missing_entries`, :func:`assemble`: the named physics, ranked by the share of the
   held-out mismatch each removes, and the :class:`Diagnosis`.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.constitutive.bridge import KIND, shaker_baseline
from recon.constitutive.law import ConstitutiveLaw, is_law_file
from recon import progress
from recon.determinism import single_thread_blas
from recon.diagnosis import rank
from recon.diagnosis.settings import DEFAULTS, DiagnosisSettings
from recon.diagnosis.ambiguity import ambiguous_pair, separating_stage
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.candidate_fit import (CANDIDATE_FAILURES, CandidateFit, fit_candidate, implausible,
                                           interval95)
from recon.diagnosis.catalog import CATALOG, SIGNATURES
from recon.diagnosis.context import DiagnosisContext
from recon.diagnosis.locate import locate, stage_derivatives
from recon.diagnosis.references import (GIVEN_FREE, Origins, References, candidate_origins, check_null,
                                        even_stiffness_terms, reference_fits, references_of,
                                        without_terms)
from recon.diagnosis.refits import (combined_fit, drop_sets, friction_from_loop, joint_pair, nested_null,
                                    prune_absorbed, refit_on)
from recon.diagnosis.sensitivity import detection_limits
from recon.diagnosis.stagewise import held_stage_figures, worse_stages
from recon.diagnosis.term_revision import revise_terms
from recon.diagnosis.wording import friction_reading, loop_reading
from recon.estimator.tuning import DEFAULT_TUNING
from recon.estimator.linear_start import linear_step
from recon.estimator.pipeline import reconstruct
from recon.model import HystereticModel
from recon.output_error.problem import get_parameter
from shakerlab.errors import UserFacingError
from shakerlab.run_data import BASE, Run

# the steps' parts other modules and tests reach through this module
__all__ = ["Diagnosis", "diagnose", "resolve_baseline", "linear_baseline", "baseline_note", "partly_entry",
           "partly_result", "unexplained_mismatch", "implausible", "CandidateFit", "CANDIDATE_FAILURES",
           "GIVEN_FREE", "drop_sets", "even_stiffness_terms", "joint_pair", "nested_null", "prune_absorbed",
           "without_terms", "SCORE_KEYS"]


def linear_baseline(run: Run) -> HystereticModel:
    """y'' + c y' + k y = g u from the linear step of recon (first stage named 'linear', else the first)."""

    name = "linear" if "linear" in run.stages else next(iter(run.stages))
    st = run.stage(name)
    # a linear stage too noisy for c and K: the least noisy fitted stage (recon.estimator.linear_start)
    lf, _, used = linear_step(run, name, "nonlinear" if "nonlinear" in run.stages else None)
    return HystereticModel(excitation=st.excitation, c_m=lf.c_m, k_m=lf.K_m, alpha_m=0.0, gamma=0.0, delta=0.0,
                           inv_m=None if st.excitation == BASE else lf.inv_m,
                           provenance={"method": "linear step of recon (diagnosis baseline 'linear')",
                                       **({"linear_step_stage": used, "warnings": list(lf.warnings)}
                                          if used != name else {})})


def resolve_baseline(run: Run, baseline, whole: bool = False,
                     settings: DiagnosisSettings = DEFAULTS) -> tuple[AugmentedModel, str]:
    """The baseline as an augmented model and its kind. ``paper`` and ``linear`` are reconstructed
    from :func:`rank.fitting_part` of ``run`` (from all of it when ``whole``)."""
    if isinstance(baseline, AugmentedModel):
        return baseline.copy(), "model"
    if isinstance(baseline, HystereticModel):
        return AugmentedModel(HystereticModel.from_dict(baseline.to_dict())), "model"
    if baseline in (None, "paper"):
        # reconstructed from the fitting samples only (rank.fitting_part: a stage the validation
        # stages do not cover has its end held out), so the baseline's held-out score is out of sample
        res = reconstruct(run if whole else rank.fitting_part(run, settings))
        model = res.model
        if res.linear is not None and res.linear.warnings:
            model.provenance["warnings"] = list(res.linear.warnings)
        fb = res.adequacy.get("fallback") or {}
        if fb.get("used"):
            # reconstruct answered with a simpler model: kept with the baseline, so the diagnosis can
            # say that what it names may stand for a term that model lacks (baseline_note)
            model.provenance["reconstruct_fallback"] = {k: fb.get(k) for k in ("kind", "trigger", "chosen_by")}
        if model.input_offset is not None and (model.provenance.get("input_offset_rule") or {}).get("on"):
            # the paper's model has no constant term: an offset reconstruct fitted on its own
            # (recon.estimator.input_offset) is taken out of the baseline, so that the catalog's
            # `offset` names it and measures it against the model without it
            model.provenance["input_offset_left_to_diagnosis"] = model.input_offset
            model.input_offset = None
        return AugmentedModel(model), "paper"
    if baseline == "linear":
        return AugmentedModel(linear_baseline(run if whole else rank.fitting_part(run, settings))), "linear"
    path = Path(str(baseline))
    if path.suffix != ".json" and not path.exists():
        raise UserFacingError(f"--baseline must be 'paper', 'linear' or a model JSON file, got {baseline!r}")
    if is_law_file(path):      # a component test's law: its mass and support are fitted on this run
        model, _ = shaker_baseline(ConstitutiveLaw.load(path), run)
        return AugmentedModel(model), f"{path} ({KIND})"
    return AugmentedModel.load(path), str(path)


@dataclass
class Diagnosis:
    baseline: AugmentedModel
    baseline_kind: str
    fit_before: dict
    null: rank.FitResult
    mismatch: list
    candidates: list                 # every tested candidate with its score
    missing: list                    # significant ones, ranked
    best: AugmentedModel
    best_fit: rank.FitResult
    context: dict = field(default_factory=dict)
    seconds: float = 0.0
    reference: rank.FitResult | None = None   # the better of the baseline as given and the null model
    ambiguity: dict | None = None             # two candidates the held-out data cannot tell apart
    unexplained: dict | None = None           # the held-out mismatch the final model still leaves, if large
    partly: dict | None = None                # a candidate better as a whole but worse on a held-out stage
    # the baseline's own Bouc-Wen loop read as a friction law when it slides within the record's travel
    # (wording.friction_reading): a reconstruction can hold a dry friction as a sharp loop
    baseline_as_friction: dict | None = None

    def to_dict(self) -> dict:
        def clean_ctx(c):
            return {k: v for k, v in c.items() if k != "billings_voon"}

        return {
            "baseline": self.baseline.equation(),
            "baseline_kind": self.baseline_kind,
            "fit_before": self.fit_before,
            "fit_after": {"nrmse": self.best_fit.nrmse, "held_out_nrmse": self.best_fit.nrmse_held,
                          "model": self.best.equation()},
            "mismatch": self.mismatch,
            "missing_physics": self.missing,
            "result": (f"missing physics: {', '.join(m['id'] for m in self.missing)}" if self.missing
                       else partly_result(self.partly) if self.partly
                       else "nothing found: no candidate explains the held-out mismatch beyond noise"),
            "partly_explained": self.partly,
            "candidates_tested": self.candidates,
            "correlation_tests": self.context.get("billings_voon", {}),
            "context": clean_ctx(self.context),
            "augmented_model": self.best.to_dict(),
            "ambiguous": list(self.ambiguity["ids"]) if self.ambiguity else [],
            "separating_stage": self.ambiguity,
            "unexplained_mismatch": self.unexplained,
            "baseline_note": baseline_note(self.baseline.baseline),
            "baseline_loop_as_friction": self.baseline_as_friction,
            # what the baseline's own fit had to say (a linear stage too noisy for c and K)
            "baseline_warnings": list(self.baseline.baseline.provenance.get("warnings", [])),
            "seconds": self.seconds,
        }



def partly_result(p: dict) -> str:
    """The one-line answer when the best candidate is better on the held-out samples as a whole but
    worse than the baseline as given on a held-out stage beyond its noise band (stagewise.py)."""
    return (f"partly explained: {' + '.join(p['ids'])} predicts the held-out samples better as a whole but "
            f"is worse than the baseline as given on stage {', '.join(p['worse_on_stages'])} beyond its noise band")


def partly_entry(ids: list, figures: dict, after: "rank.FitResult", given: "rank.FitResult") -> dict:
    """``Diagnosis.partly``: the ids, the stages where the model fails, every held-out stage's figures."""
    return {"ids": list(ids), "worse_on_stages": worse_stages(figures), "held_out_stages": figures,
            "held_out_nrmse_before": given.nrmse_held, "held_out_nrmse_after": after.nrmse_held}


def baseline_note(model: HystereticModel) -> str | None:
    """A warning when the baseline is one of reconstruct's simpler models (recon.estimator.fallback:
    the full model was inadmissible, or predicted the held-out stages worse), else None. Against
    such a baseline a catalog name can stand for a term the baseline lacks as well as for the
    effect (a linear fallback that lacks the true model's polynomial and hysteresis terms can have
    a damping candidate named for what those terms do)."""
    kind = model.provenance.get("simpler_model")
    if not isinstance(kind, str):
        return None
    fb = model.provenance.get("reconstruct_fallback") or {}
    why = {"inadmissible": "was not admissible",
           "inadequate": "predicted the held-out stages worse"}.get(fb.get("trigger"), "was set aside")
    return (f"the baseline is reconstruct's simpler {kind} model (its full model {why}): a name found "
            f"against it may stand for a term the baseline lacks as well as for an effect the record holds")


def unexplained_mismatch(fr: rank.FitResult, noise_mse: float, named: list[str]) -> dict | None:
    """The held-out mismatch the final model (``fr``: the baseline, or the baseline with what was
    named) still leaves, when it is above reconstruct's adequacy limit (max of noise_factor x the
    held-out noise floor and nrmse_floor, recon.estimator.tuning's defaults): physics outside the catalog,
    an effect this excitation cannot bring out, or a baseline too far off for a local fit to
    recover. None when the final model is within the limit."""
    if not (math.isfinite(fr.mse_held) and fr.mse_held > 0 and math.isfinite(fr.nrmse_held)):
        return None
    noise = math.sqrt(max(noise_mse, 0.0)) * fr.nrmse_held / math.sqrt(fr.mse_held)
    factor, lowest = DEFAULT_TUNING.noise_factor, DEFAULT_TUNING.nrmse_floor
    limit = max(factor * noise, lowest)
    if fr.nrmse_held <= limit:
        return None
    after = f"with {', '.join(named)} added" if named else "no catalog candidate is significant"
    return {"held_out_nrmse": fr.nrmse_held, "noise_nrmse": noise, "nrmse_limit": limit, "named": list(named),
            "note": f"the held-out NRMSE {fr.nrmse_held:.3g} is above {limit:.3g} (max of {factor:g} x the "
                    f"held-out noise floor {noise:.2g} and {lowest:g}); {after}: something the catalog does "
                    f"not hold, an effect this excitation cannot separate, or a baseline too far off"}



def _params_of(fr: rank.FitResult, keys, bounds: dict | None = None) -> dict:
    """Each parameter's value, standard error and 95 % interval; and, for one that ended on a bound
    of the range it was fitted in (``bounds``), which bound: the record does not fix that value (a
    second mode driven off its resonance leaves its damping free), it only says on which side it
    lies."""
    out = {}
    for k in keys:
        v = get_parameter(fr.model, k)
        name = k.split(":", 1)[-1]
        se = fr.stderr.get(k)
        out[name] = {"value": v, "stderr": se, "interval": interval95(v, se) if k in fr.stderr else None}
        side = on_bound(v, (bounds or {}).get(k))
        if side:
            out[name]["at_bound"] = side
    return out


def on_bound(v: float, bound) -> str | None:
    """'lower' or 'upper' when ``v`` sits on that end of ``bound`` (lo, hi): within 1 % of the
    bound's own size (a bound at 0: a thousandth of the range's width); an open end holds nothing."""
    if not bound:
        return None
    lo, hi = (float(b) for b in bound)
    width = hi - lo

    def near(b: float) -> bool:
        if not math.isfinite(b):
            return False
        tol = (0.01 + 1e-12) * abs(b) if b != 0.0 else (1e-3 * width if math.isfinite(width) else 0.0)
        return abs(v - b) <= tol

    if near(lo) or v < lo:
        return "lower"
    if near(hi) or v > hi:
        return "upper"
    return None


# the figures of rank.score a candidate's entry keeps from its score before a nested null replaced
# its reference (entry "before_nested_null")
SCORE_KEYS = ("significant", "explained", "gain_over_noise", "relative_gain", "blocks_improved", "dbic")


@dataclass
class Scores:
    """The candidate step's outcome: every tested entry (its JSON row), each fitted candidate's
    CandidateFit, and what each was scored against."""
    tested: list = field(default_factory=list)        # entries in catalog order, failed ones included
    fits: dict = field(default_factory=dict)          # {id: CandidateFit}
    references: dict = field(default_factory=dict)    # {id: (reference FitResult, parameters added)}


def reference_step(run: Run, baseline, max_nfev: int, settings: DiagnosisSettings) -> References:
    """The baseline resolved and its reference fits. A baseline reconstructed without the held-out
    end of a stage (rank.fitting_part) that does not simulate that stage is reconstructed from the
    whole run instead, and its score on that end is then in sample."""
    progress.step("the baseline model", share=0.15)
    base, kind = resolve_baseline(run, baseline, settings=settings)
    if base.excitation != run.excitation:
        raise UserFacingError(f"baseline model is {base.excitation} excitation, {run.source or 'run'} is {run.excitation}")
    data, null, given = reference_fits(run, base, max_nfev, settings)
    if (kind in ("paper", "linear") and not (math.isfinite(null.mse_held) or math.isfinite(given.mse_held))
            and rank.uncovered_stages(run, settings)):
        base, kind = resolve_baseline(run, baseline, whole=True, settings=settings)
        base.baseline.provenance["fitted_on_held_out"] = "the whole run (its fitting part alone diverged)"
        data, null, given = reference_fits(run, base, max_nfev, settings)
    check_null(null if math.isfinite(null.mse_held) else given, data, run)
    return references_of(base, kind, data, null, given)


def locate_step(run: Run, refs: References, max_nfev: int, settings: DiagnosisSettings) -> tuple[list, DiagnosisContext]:
    """(where the reference misses: locate's findings, the context every later step reads)."""
    progress.step("locating the mismatch", share=0.05)
    derivs = stage_derivatives(run, refs.data)
    findings, located = locate(refs.ref.model, run, refs.data, refs.ref.sims, derivs, settings)
    dctx = DiagnosisContext(run=run, data=refs.data, derivs=derivs, located=located,
                            noise_mse=rank.held_noise_mse(refs.data), max_nfev=max_nfev, settings=settings)
    return findings, dctx


def candidate_fits(cid: str, cand, refs: References, origins: Origins, dctx: DiagnosisContext) -> CandidateFit:
    """Candidate ``cid`` fitted from each of its origins; the fit that predicts the held-out samples
    best. A fit from the baseline as given (c and k free, the reference) that takes at least
    ``1 - settings.follow_on_share`` of its start's fitting cost is also refitted with every
    baseline parameter free: with c and k alone a term the baseline's other parameters absorbed
    can stay short of significance that the full refit reaches. Raises the first failure when no
    origin gives a fit."""
    full_free = refs.full_free
    got, errs = [], []
    for origin in origins.for_candidate(cand):
        try:
            cf = fit_candidate(cid, cand, origin.fit, origin.free, origin.step_keys, dctx, origin.name)
            got.append(cf)
            if (origin.name == "as_given" and not refs.refit_better and set(full_free) - set(origin.free)
                    and cf.fit.cost_fit < dctx.settings.follow_on_share * origin.fit.cost_fit):
                fa = rank.fit(cf.fit.model, list(dict.fromkeys(full_free + cf.keys)), dctx.data, cf.scales,
                              max_nfev=max(dctx.max_nfev // 2, 5), bounds=cf.bounds)
                if math.isfinite(fa.mse_held) and fa.n_held > 0:
                    got.append(dataclasses.replace(cf, fit=fa, free=full_free, started_from="as_given_then_refit"))
        except CANDIDATE_FAILURES as exc:
            errs.append(exc)
    if not got:
        raise errs[0]
    return min(got, key=lambda g: g.fit.mse_held)


def score_candidate(cid: str, cand, refs: References, origins: Origins, dctx: DiagnosisContext,
                    pruned_refs: dict) -> tuple[dict, CandidateFit | None, rank.FitResult | None]:
    """(candidate ``cid``'s entry, its fit, the reference it was scored against). The fit
    (:func:`candidate_fits`) is refitted without the baseline terms that may have absorbed it
    (refits.prune_absorbed; not after the follow-on refit, which already refitted every term beside
    it), scored by the rule, and, when significant, scored again against its nested null if that
    does better than its reference (``origins.nulls`` gains the nested null). A candidate whose fit
    or simulation fails gets an entry with its reason and no fit."""
    ref, data, rule, noise_mse = refs.ref, dctx.data, dctx.rule, dctx.noise_mse
    tc = time.perf_counter()
    try:
        cf = candidate_fits(cid, cand, refs, origins, dctx)
        if cf.started_from == "as_given_then_refit":
            drop, against = (), ref
        else:
            cf, drop, against = prune_absorbed(cf, ref, data, dctx.max_nfev, pruned_refs, dctx.settings)
        score = rank.score(against, cf.fit, len(cf.keys), noise_mse, rule)
        before_nested = None
        if score["significant"]:
            nn = nested_null(cf, cid, ref.model, data, dctx.max_nfev)
            if nn is not None:
                origins.nulls.append(nn)
                if nn.mse_held < against.mse_held:
                    # the score that made the nested null be fitted: it decides whether this null
                    # exists, so a change of the rule can be judged on stored rows
                    before_nested = {k: score[k] for k in SCORE_KEYS if k in score}
                    against = nn
                    score = rank.score(against, cf.fit, len(cf.keys), noise_mse, rule)
    except CANDIDATE_FAILURES as exc:
        return ({"id": cid, "failed": f"{type(exc).__name__}: {exc}", "significant": False,
                 "seconds": time.perf_counter() - tc}, None, None)
    fr = cf.fit
    entry = {"id": cid, **score, "held_out_nrmse": fr.nrmse_held, "started_from": cf.started_from,
             "seconds": time.perf_counter() - tc}
    entry["compared_with_held_out_nrmse"] = against.nrmse_held
    if any(against is n for n in origins.nulls):
        entry["compared_with_nested_null"] = True
    if before_nested is not None:
        entry["before_nested_null"] = before_nested
    if drop:
        entry["baseline_terms_dropped"] = list(drop)
    if cf.started_from == "without_hysteresis":
        entry["hysteresis_dropped"] = True
    if cf.started_from == "without_even_stiffness":
        entry["baseline_terms_dropped"] = sorted(set(entry.get("baseline_terms_dropped", []))
                                                 | set(origins.even_terms))
    why = implausible(cid, fr, ref.model, data)
    if why:
        entry["implausible"] = why
        entry["significant"] = False
    return entry, cf, against


def score_candidates(ids: list, refs: References, origins: Origins, dctx: DiagnosisContext) -> Scores:
    """Every applicable candidate of ``ids`` fitted and scored (:func:`score_candidate`), then
    friction refitted from a hysteresis fit that is a friction law (refits.friction_from_loop)."""
    out = Scores()
    pruned_refs = {}        # the pruned references, shared between candidates
    for cid in ids:
        progress.step(f"candidate {cid} ({ids.index(cid) + 1} of {len(ids)})", share=0.65 / len(ids))
        cand = CATALOG[cid]
        if cid in refs.ref.model.added or not cand.applies(refs.ref.model.baseline, dctx.located):
            continue
        entry, cf, against = score_candidate(cid, cand, refs, origins, dctx, pruned_refs)
        if cf is not None:
            out.fits[cid] = cf
            out.references[cid] = (against, len(cf.keys))
        out.tested.append(entry)
    friction_from_loop(out.tested, out.fits, out.references, dctx, refs.ref.model, refs.full_free, refs.bkeys)
    return out


def rescore_against_best_null(scores: Scores, nulls: list, dctx: DiagnosisContext) -> None:
    """The best null model found anywhere (a core, or a candidate's fit with its term off and the
    baseline refitted) is the one every candidate must beat: each significant entry scored against
    a worse reference is scored again against it."""
    if not nulls:
        return
    best_null = min(nulls, key=lambda f: f.mse_held)
    for t in scores.tested:
        if t.get("significant") and t["id"] in scores.references:
            against, k_added = scores.references[t["id"]]
            if best_null.mse_held < against.mse_held:
                t.update(rank.score(best_null, scores.fits[t["id"]].fit, k_added, dctx.noise_mse, dctx.rule))
                t["compared_with_held_out_nrmse"] = best_null.nrmse_held
                t["compared_with_nested_null"] = True


def hold_to_every_stage(scores: Scores, given: rank.FitResult, dctx: DiagnosisContext) -> list:
    """Never an improvement that is worse on a held-out stage (stagewise.py): a candidate significant
    on the held-out samples together must be no worse than the baseline as given on each held-out
    stage beyond that stage's noise band. One that is loses its significance; returned are the
    ``partly_entry`` records of those (the answer is "partly explained" if nothing else is named)."""
    partly = []
    for t in scores.tested:
        if t.get("significant") and t["id"] in scores.fits:
            fr = scores.fits[t["id"]].fit
            figs = held_stage_figures(given, fr, dctx.data, dctx.rule.stage_level)
            t["held_out_stages"] = figs
            bad = worse_stages(figs)
            if bad:
                t["significant"] = False
                t["worse_on_stages"] = bad
                partly.append(partly_entry([t["id"]], figs, fr, given) | {"explained": t["explained"]})
    return partly


def add_detection_limits(scores: Scores, refs: References, dctx: DiagnosisContext) -> None:
    """Each fitted candidate's entry gains the size at which its effect, added to the record, would
    be named (an estimate; sensitivity.py), beside what the reference's own refit would take up of it
    when the reference is the refitted baseline."""
    progress.step("detection limits", share=0.1)
    limits = detection_limits(refs.ref, scores.fits, dctx.data, dctx.noise_mse, CANDIDATE_FAILURES, dctx.rule,
                              refitted=refs.full_free if refs.refit_better else ())
    for t in scores.tested:
        if t["id"] in limits:
            t["detection_limit"] = limits[t["id"]]


def revision_step(scores: Scores, refs: References, partly: list, dctx: DiagnosisContext,
                  above: float = -math.inf) -> list:
    """When no candidate is named (or, with ``above``, the share the best named one explains: among
    those that explain more than it): each candidate that is plausible and already explains the share
    of the reference's excess the rule asks of a named effect (``rule.min_explained``), while failing
    its other margins or a held-out stage, is refitted with the baseline's fn terms chosen again under
    it (term_revision.revise_terms), in order of what it explains, until one is named. (The first in
    that order is not always the effect: a candidate that stands in for it on the held-out samples
    can explain more and still fail, and then the effect's own revision is never tried.) A baseline
    reconstructed from a record that holds an effect has fitted terms to stand in for it and may
    have traded true ones away; beside those terms the effect's candidate explains a good part of
    the mismatch and still fails. (One that explains less is held back by its own size, not by the
    baseline's terms: revising under it costs a few fits and names nothing.) The revised fit is scored
    against the better of the candidate's reference and that reference revised the same way (and
    the nested null of the revised fit), so that the revision itself earns the candidate nothing.
    Named (the one-entry list returned) when it passes the rule, is plausible and is no worse on
    any held-out stage; its entry gains ``baseline_terms_revised``. Else [] and nothing changes."""
    fitted = [t for t in scores.tested if t["id"] in scores.fits and not t.get("implausible")
              and not t.get("significant") and t.get("explained", 0.0) >= dctx.rule.min_explained
              and t.get("explained", 0.0) > above]
    for t in sorted(fitted, key=lambda t: -t["explained"]):
        named = _revised(t, scores, refs, partly, dctx)
        if named:
            return named
    return []


def _revised(t: dict, scores: Scores, refs: References, partly: list, dctx: DiagnosisContext) -> list:
    """:func:`revision_step` for the tested candidate ``t``: [t] when named, else []."""
    cid, cf = t["id"], scores.fits[t["id"]]
    data, rule = dctx.data, dctx.rule
    progress.step(f"the baseline's terms chosen again under {cid}", share=0.0)
    try:
        rev, log = revise_terms(cf.fit, list(cf.free), list(cf.keys), cf.scales, cf.bounds, data, dctx.max_nfev,
                                dctx.settings)
    except CANDIDATE_FAILURES:
        return []
    if not log["moves"] or not rev.mse_held < cf.fit.mse_held:
        return []
    against, k_added = scores.references[cid]
    ref_keys = [k for k in refs.full_free if not k.startswith("fn:")]
    try:
        rref, _ = revise_terms(against, ref_keys, [], {}, {}, data, dctx.max_nfev, dctx.settings)
    except CANDIDATE_FAILURES:
        rref = against
    rev_free = list(dict.fromkeys([k for k in cf.free if not k.startswith("fn:")]
                                  + [f"fn:{x}" for x in rev.model.baseline.fn_m]))
    rcf = dataclasses.replace(cf, fit=rev, free=rev_free)
    nn = nested_null(rcf, cid, refs.ref.model, data, dctx.max_nfev)
    best_null = min([f for f in (against, rref, nn) if f is not None], key=lambda f: f.mse_held)
    k_terms = len(rev.model.baseline.fn_m) - len(best_null.model.baseline.fn_m)
    score = rank.score(best_null, rev, k_added + k_terms, dctx.noise_mse, rule)
    figs = held_stage_figures(refs.given, rev, data, rule.stage_level)
    if not score["significant"] or implausible(cid, rev, refs.ref.model, data) or worse_stages(figs):
        return []
    # the candidate's parameters as fitted beside the terms as reconstructed: a size that moves
    # beyond its interval when the terms are chosen again depends on the baseline's structure, which
    # the interval (noise alone) does not hold (rig.closed_loop sizes such an effect on a stage
    # where it shows)
    log["parameters_before"] = _params_of(cf.fit, [k for k in CATALOG[cid].parameters if k in cf.keys])
    t.update(score, held_out_nrmse=rev.nrmse_held, compared_with_held_out_nrmse=best_null.nrmse_held,
             held_out_stages=figs, baseline_terms_revised=log)
    t.pop("worse_on_stages", None)
    if best_null is not against:
        t["compared_with_nested_null"] = True
    scores.fits[cid] = rcf
    partly[:] = [p for p in partly if cid not in p.get("ids", ())]
    return [t]


def pair_search(scores: Scores, refs: References, nulls: list, partly: list,
                dctx: DiagnosisContext) -> tuple[list, rank.FitResult | None]:
    """When no candidate is significant alone: (the pair refits.joint_pair names, their joint fit),
    held to every held-out stage as a single candidate is (a pair worse on one is added to
    ``partly`` and not named), or ([], None)."""
    ref, given = refs.ref, refs.given
    refit = functools.partial(refit_on, bkeys=refs.bkeys, dctx=dctx)
    sig, combined = joint_pair(scores.tested, scores.fits, nulls + [ref], ref.model, dctx.data, dctx.noise_mse,
                               dctx.max_nfev, refit, unexplained_mismatch(ref, dctx.noise_mse, []) is not None,
                               dctx.rule)
    if combined is not None:
        figs = held_stage_figures(given, combined, dctx.data, dctx.rule.stage_level)
        if worse_stages(figs):
            partly.append(partly_entry([t["id"] for t in sig], figs, combined, given)
                          | {"explained": min(t["explained"] for t in sig)})
            for t in sig:
                t.update(significant=False, worse_on_stages=worse_stages(figs), held_out_stages=figs)
            sig, combined = [], None
    return sig, combined


def forward_step(sig: list, scores: Scores, refs: References, dctx: DiagnosisContext) -> tuple[list, rank.FitResult | None]:
    """(the named candidates, their joint fit or None): the best of the significant ``sig`` (ranked),
    and the first runner-up that still adds significantly on top of it, fitted together
    (refits.combined_fit), plausible and no worse on any held-out stage. Each runner-up's entry
    gains its score on top of the best (``on_top_of_best``)."""
    fits, data, rule, noise_mse = scores.fits, dctx.data, dctx.rule, dctx.noise_mse
    best = fits[sig[0]["id"]]
    kept, combined = [sig[0]], None
    for t in sig[1:]:
        second = fits[t["id"]]
        try:
            frc = combined_fit(best, second, t["id"], data, dctx.max_nfev)
            s2 = rank.score(best.fit, frc, len(second.keys), noise_mse, rule)
        except CANDIDATE_FAILURES as exc:
            t["on_top_of_best"] = {"failed": f"{type(exc).__name__}: {exc}", "significant": False}
            continue
        why = implausible(t["id"], frc, refs.ref.model, data) + implausible(sig[0]["id"], frc, refs.ref.model, data)
        if why:
            s2 = {**s2, "implausible": why, "significant": False}
        if s2["significant"]:
            figs = held_stage_figures(refs.given, frc, data, rule.stage_level)
            if worse_stages(figs):
                s2 = {**s2, "significant": False, "worse_on_stages": worse_stages(figs)}
        t["on_top_of_best"] = s2
        if s2["significant"]:
            kept.append(t)
            fits[t["id"]] = dataclasses.replace(second, fit=frc, free=best.free)
            combined = frc
            break
    return kept, combined


def missing_entries(sig: list, scores: Scores, refs: References, findings: list, dctx: DiagnosisContext) -> list:
    """The JSON records of the named candidates ``sig``: what each is, its fitted parameters with
    their intervals, and the evidence (held-out figures before and after, located findings)."""
    missing = []
    for t in sig:
        cf = scores.fits[t["id"]]
        fr = cf.fit
        cand = CATALOG[t["id"]]
        ev_kinds = SIGNATURES.get(t["id"], ())
        missing.append({
            "id": t["id"], "explanation": cand.explanation, "adds": cand.adds, "simulated": cand.simulated,
            "parameters": _params_of(fr, [k for k in cand.parameters if k in cf.keys or k == "x:side"], cf.bounds),
            "evidence": {"held_out_nrmse_before": refs.given.nrmse_held, "held_out_nrmse_after": fr.nrmse_held,
                         "held_out_nrmse_refit": refs.null.nrmse_held, "compared_with": refs.ref_name,
                         "explained_fraction_of_excess": t["explained"], "delta_bic_held_out": t["dbic"],
                         "effective_samples": t["n_eff"],
                         "compared_with_held_out_nrmse": t["compared_with_held_out_nrmse"],
                         "located": [f for f in findings if f["kind"] in ev_kinds][:4]},
            "fit_after": {"nrmse": fr.nrmse},
            "baseline_terms_dropped": t.get("baseline_terms_dropped", []),
            "hysteresis_dropped": bool(t.get("hysteresis_dropped", False)),
        })
        if "baseline_terms_revised" in t:
            missing[-1]["baseline_terms_revised"] = t["baseline_terms_revised"]
        if t["id"] == "hysteresis":
            # a named loop that slides within the record's travel is a friction law (wording.py)
            b = fr.model.baseline
            travel = max((float(np.ptp(d.displacement)) for d in dctx.data), default=0.0)
            missing[-1]["as_friction"] = friction_reading(b.alpha_m, b.gamma, b.delta, travel, dctx.settings)
    return missing


def loop_as_friction(model, dctx: DiagnosisContext) -> dict | None:
    """``model``'s Bouc-Wen loop read as a friction law over the record's largest travel (the
    displacement's peak-to-peak on any stage), None when it does not slide within it."""
    travel = max((float(np.ptp(d.displacement)) for d in dctx.data), default=0.0)
    return loop_reading(model, travel, dctx.settings)


def fit_before_figures(refs: References, core: rank.FitResult | None, data: list) -> dict:
    """``Diagnosis.fit_before``: the baseline as given (nrmse, held_out_nrmse), the null model's
    figures under refit_*, the noise floors and the held-out share of each stage."""
    null, given = refs.null, refs.given
    out = {"nrmse": given.nrmse, "refit_nrmse": null.nrmse, "held_out_nrmse": given.nrmse_held,
           "held_out_nrmse_as_given": given.nrmse_held, "refit_held_out_nrmse": null.nrmse_held,
           "compared_with": refs.ref_name,
           "noise_nrmse": {d.name: d.noise / d.rms for d in data},
           # the share of each stage's samples the models are compared on (a validation stage
           # whole; the end of a stage the validation stages do not reach, rank.uncovered_stages)
           "held_out_share": {d.name: float(np.mean(d.held)) for d in data if d.held.any()}}
    if core is not None:
        # candidate fits also started from the baseline's linear core (settings.linear_core_nrmse)
        out["linear_core_held_out_nrmse"] = core.nrmse_held
    return out


@single_thread_blas
@progress.task("diagnose")
def diagnose(run: Run, baseline="paper", candidates=None, max_nfev: int = 30,
             settings: DiagnosisSettings | None = None) -> Diagnosis:
    """Diagnose ``run`` against ``baseline`` ("paper", "linear", a model JSON path or a model).
    ``settings``: the significance rule, the record's split and weighting and the search's tuned
    numbers (recon.diagnosis.settings; None: the calibrated defaults)."""
    if settings is not None and not isinstance(settings, DiagnosisSettings):
        raise TypeError(f"settings must be a DiagnosisSettings, not {type(settings).__name__}")
    unknown = [c for c in candidates or () if c not in CATALOG]
    if unknown:     # refused before anything is computed
        raise UserFacingError(f"unknown candidate {', '.join(map(repr, unknown))} (catalog: {', '.join(CATALOG)})")
    return _diagnose(run, baseline, candidates, max_nfev, settings or DEFAULTS)


def _diagnose(run: Run, baseline, candidates, max_nfev: int, settings: DiagnosisSettings) -> Diagnosis:
    """The steps of the module docstring, in order."""
    t0 = time.perf_counter()
    refs = reference_step(run, baseline, max_nfev, settings)
    findings, dctx = locate_step(run, refs, max_nfev, settings)
    # the baseline's loop read as a friction law (None: it does not slide within the record's travel):
    # reported, and a start for the friction candidate (candidates/coulomb_friction.py)
    dctx.located["loop_friction"] = loop_as_friction(refs.base.baseline, dctx)
    ids = candidates or list(CATALOG)
    origins = candidate_origins(refs, ids, max_nfev, settings)
    scores = score_candidates(ids, refs, origins, dctx)
    rescore_against_best_null(scores, origins.nulls, dctx)
    partly = hold_to_every_stage(scores, refs.given, dctx)
    add_detection_limits(scores, refs, dctx)
    sig = sorted((t for t in scores.tested if t["significant"]), key=lambda t: -t["explained"])
    combined = None
    if sig:
        # a candidate that explains more than the best named one and fails only a margin or a
        # held-out stage gets the revision it would get if nothing were named, before the best is
        # accepted: beside the baseline's terms as reconstructed (chosen on a record that holds the
        # effect) the effect's own candidate can fail where a stand-in for it passes
        sig = sorted(revision_step(scores, refs, partly, dctx, above=sig[0]["explained"]) + sig,
                     key=lambda t: -t["explained"])
    else:
        sig = revision_step(scores, refs, partly, dctx)
    if not sig:
        sig, combined = pair_search(scores, refs, origins.nulls, partly, dctx)
    ranked = list(sig)
    if len(sig) > 1 and combined is None:
        sig, combined = forward_step(sig, scores, refs, dctx)
    # the candidates as each was fitted beside the baseline as reconstructed: what two of them are
    # compared on (assemble's ambiguity), before a named one's terms are revised below
    compared = {c: f.fit.mse_held for c, f in scores.fits.items()}
    ranked = [dict(t) for t in ranked]
    if len(sig) == 1 and combined is None and "baseline_terms_revised" not in sig[0]:
        # one effect named beside the baseline's terms as reconstructed: those terms were chosen on a
        # record that holds the effect and may stand in for it. They are chosen again under it, as
        # for a candidate not yet named (revision_step), and the revision kept on the same rule
        _revised(sig[0], scores, refs, partly, dctx)
    return assemble(refs, dctx, findings, scores, origins, ranked, sig, combined, partly,
                    time.perf_counter() - t0, compared)


def assemble(refs: References, dctx: DiagnosisContext, findings: list, scores: Scores, origins: Origins,
             ranked: list, sig: list, combined: rank.FitResult | None, partly: list, seconds: float,
             compared: dict) -> Diagnosis:
    """The :class:`Diagnosis`: the named candidates (``sig``; ``combined`` their joint fit, if any),
    the best model (the joint fit, the first named candidate's, or the reference), two candidates
    the held-out data cannot tell apart among ``ranked`` (on ``compared``: each candidate's held-out
    MSE as fitted beside the baseline as reconstructed), and the mismatch left unexplained."""
    ref, noise_mse = refs.ref, dctx.noise_mse
    pair = ambiguous_pair(ranked, {t["id"] for t in sig[1:]}, compared,
                          dctx.rule.bic_margin, noise_mse, dctx.settings)
    ambiguity = separating_stage(pair) if pair else None
    missing = missing_entries(sig, scores, refs, findings, dctx)
    if combined is not None:
        best_fr = combined
    elif missing:
        best_fr = scores.fits[missing[0]["id"]].fit
    else:
        best_fr = ref
    partly_explained = (None if missing or not partly
                        else {k: v for k, v in max(partly, key=lambda p: p["explained"]).items() if k != "explained"})
    return Diagnosis(baseline=refs.base, baseline_kind=refs.kind, fit_before=fit_before_figures(refs, origins.core,
                                                                                               dctx.data),
                     null=refs.null, mismatch=findings, candidates=scores.tested, missing=missing, best=best_fr.model,
                     best_fit=best_fr, context=dctx.located, seconds=seconds, reference=ref, ambiguity=ambiguity,
                     unexplained=unexplained_mismatch(best_fr, noise_mse, [m["id"] for m in missing]),
                     partly=partly_explained, baseline_as_friction=dctx.located["loop_friction"])

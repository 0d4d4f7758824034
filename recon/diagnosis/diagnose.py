"""Mismatch diagnosis: locate, name the missing physics, model it, show the fit improve.

    from recon.diagnosis.diagnose import diagnose
    d = diagnose(run, baseline="paper")       # or "linear", a model JSON path, a HystereticModel,
                                              # a component test's law JSON (recon.constitutive.bridge)
    d.to_dict()                               # the JSON contract of ``shakerlab diagnose --json``

Steps: the baseline is refitted by output error (the *null* model, so that every
candidate is compared with the best the baseline can do on the same data); the
residuals of the null model are located (:mod:`.locate`); every applicable
catalog candidate (:mod:`.catalog`) is fitted as an augmented model and scored on
held-out data (:mod:`.rank`); the significant ones are ranked by the share of the
held-out mismatch they remove.
"""
from __future__ import annotations

import itertools
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
from recon.diagnosis.settings import DEFAULT_RULE, DEFAULTS, DiagnosisSettings, SignificanceRule
from recon.diagnosis.ambiguity import ambiguous_pair, separating_stage
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.catalog import CATALOG, SIGNATURES
from recon.diagnosis.locate import locate, stage_derivatives
from recon.diagnosis.sensitivity import detection_limits
from recon.diagnosis.stagewise import held_stage_figures, worse_stages
from recon.diagnosis.wording import friction_reading
from recon.estimator.tuning import DEFAULT_TUNING
from recon.estimator.linear_start import linear_step
from recon.estimator.pipeline import reconstruct
from recon.library import monomials
from recon.model import HystereticModel
from recon.output_error.problem import get_parameter, set_parameter
from shakerlab.errors import UserFacingError
from shakerlab.run_data import BASE, Run



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
            # what the baseline's own fit had to say (a linear stage too noisy for c and K)
            "baseline_warnings": list(self.baseline.baseline.provenance.get("warnings", [])),
            "seconds": self.seconds,
        }


Z95 = 1.96


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


# the baseline's parameters a candidate fit frees when it starts from the baseline as given
GIVEN_FREE = ("c_m", "k_m")



def _interval(v: float, se) -> list | None:
    if se is None or not math.isfinite(se):
        return None
    return [v - Z95 * se, v + Z95 * se]


def _params_of(fr: rank.FitResult, keys) -> dict:
    out = {}
    for k in keys:
        v = get_parameter(fr.model, k)
        name = k.split(":", 1)[-1]
        se = fr.stderr.get(k)
        out[name] = {"value": v, "stderr": se, "interval": _interval(v, se) if k in fr.stderr else None}
    return out


def implausible(cid: str, fr: rank.FitResult, ref: AugmentedModel, data, intervals: bool = True) -> list[str]:
    """Why the fitted candidate ``cid`` is not physical, or contradicts the rest of its model ([] if
    it is plausible). Such a candidate is never reported, however well it fits. ``intervals=False``:
    the fitted values alone, not whether the first parameter's interval holds 0."""
    m = fr.model
    b, r = m.baseline, ref.baseline
    why = []
    if b.K_m <= 0 < r.K_m:
        why.append(f"linear stiffness K_m = {b.K_m:.4g} <= 0")
    if b.c_m < 0 <= r.c_m:
        why.append(f"negative viscous damping c_m = {b.c_m:.4g}")
    cand = CATALOG[cid]
    why += cand.check(m, data)       # the candidate's own physical range (its module)
    k0 = cand.parameters[0]
    if intervals and k0 in fr.stderr:
        iv = _interval(get_parameter(m, k0), fr.stderr[k0])
        if iv is not None and iv[0] <= 0.0 <= iv[1]:
            why.append(f"the 95 % interval of {k0.split(':', 1)[-1]} [{iv[0]:.4g}, {iv[1]:.4g}] holds 0")
    return why


# A reconstructed baseline absorbs missing physics into fn terms of its own (friction as y'^3 and
# y'^5, which compensate each other), and the candidate fitted next to them cannot show what it
# explains. A candidate whose fit leaves at most this share of the reference's fitting cost is
# refitted without those terms, singly, in pairs and all at once (a friction fitted beside the
# y'^3 and y'^5 that absorbed it can do worse than the baseline as given, and far better without
# them).
PRUNE_FIT_SHARE = 0.9
# short output-error fits (function evaluations) that rank starts differing in a fitted shape parameter
SHAPE_SCREEN_NFEV = 6
PRUNE_PAIRS_UP_TO = 5    # fn terms up to which pairs are tried as well
# a candidate fitted from the baseline as given (c and k free) that leaves at most this share of its
# fitting cost is fitted once more with every baseline parameter free (see _diagnose)
FOLLOW_ON_SHARE = 0.5
# a reference whose held-out NRMSE is above this explains less than half of the held-out variance:
# candidate fits also start from the baseline's linear core (its fn terms at 0, c and k refitted)
LINEAR_CORE_NRMSE = 0.7


def drop_sets(terms: list[str]) -> list[tuple]:
    """The sets of baseline fn terms a candidate is refitted without: each term, each pair (up to
    PRUNE_PAIRS_UP_TO terms), all of them, and each parity class of y' in full: the terms odd in y'
    (dissipative, where friction or nonlinear damping is absorbed) and the even ones (elastic,
    where a stiffness law is). A baseline that absorbed friction holds several dissipative terms
    next to true elastic ones (odd terms in y' such as y^2 y', y'^3, y'^5 beside y^2, y^3);
    neither the pairs nor the whole set take out just the absorbing ones."""
    out = [(t,) for t in terms]
    if len(terms) <= PRUNE_PAIRS_UP_TO:
        out += list(itertools.combinations(terms, 2))
    if len(terms) > 2:
        out.append(tuple(terms))
    for odd in (1, 0):
        cls = tuple(t for t in terms if monomials.parse(t)[1] % 2 == odd)
        if 1 < len(cls) < len(terms) and cls not in out:
            out.append(cls)
    return out


def without_terms(am: AugmentedModel, drop: tuple) -> AugmentedModel:
    m = am.copy()
    for t in drop:
        m.baseline.fn_m.pop(t, None)
    return m


def prune_absorbed(fr: rank.FitResult, keys: list, sc: dict, b: dict, free: list, ref: rank.FitResult, data,
                   max_nfev: int, cache: dict | None = None, rule: SignificanceRule = DEFAULT_RULE):
    """(fit, free keys, dropped terms, reference to score against): the candidate fit ``fr`` refitted
    without the baseline fn terms it may have made redundant, when one such refit predicts the
    held-out samples better (only for a candidate that removes at least 1 - PRUNE_FIT_SHARE of the
    reference's fitting cost, or lowers its held-out NRMSE by the rule's min_rel_gain). The reference is then the better of ``ref`` and the baseline without
    the same terms, its parameters refitted as in the candidate's fit: the candidate gets no credit
    for what dropping them and refitting the rest alone does.
    ``cache`` keeps those pruned references between candidates."""
    cache = {} if cache is None else cache
    terms = [t for t in fr.model.baseline.fn_m if f"fn:{t}" not in keys]
    # tried too for a candidate that lowers the held-out NRMSE by the rule's min_rel_gain or more: where one stage
    # misfitted by every model holds most of the fitting cost, no candidate removes a tenth of it,
    # yet the held-out error can still show that a baseline term stands in for the candidate's
    promising = (math.isfinite(fr.nrmse_held) and math.isfinite(ref.nrmse_held)
                 and fr.nrmse_held <= (1.0 - rule.min_rel_gain) * ref.nrmse_held)
    if not terms or not (fr.cost_fit < PRUNE_FIT_SHARE * ref.cost_fit or promising):
        return fr, free, (), ref
    best, best_free, best_drop = fr, free, ()
    for drop in drop_sets(terms):
        # first with the baseline's other fn terms as they are; then, from there, with them refitted
        # too: they were fitted next to the dropped ones and may compensate them (a huge y^5 beside
        # the dissipative terms that absorbed a friction). The reference below refits what the
        # kept fit refitted, so the candidate gets no credit for that
        f1 = [k for k in free if not (k.startswith("fn:") and k[3:] in drop)]
        kept = [f"fn:{t}" for t in terms if t not in drop and f"fn:{t}" not in f1]
        start = without_terms(fr.model, drop)
        for f2 in ([f1, f1 + kept] if kept else [f1]):
            try:
                frd = rank.fit(start, list(dict.fromkeys(f2 + keys)), data, sc, max_nfev=max_nfev, bounds=b)
            except CANDIDATE_FAILURES:
                break
            if math.isfinite(frd.mse_held) and frd.mse_held < best.mse_held:
                best, best_free, best_drop = frd, f2, drop
            if math.isfinite(frd.cost_fit):
                start = frd.model
    if not best_drop:
        return fr, free, (), ref
    key = (best_drop, tuple(best_free))
    if key not in cache:
        try:    # the reference frees what the candidate's fit freed of the baseline
            cache[key] = rank.fit(without_terms(ref.model, best_drop), best_free, data, max_nfev=max_nfev)
        except CANDIDATE_FAILURES:
            cache[key] = None
    pr = cache[key]
    against = pr if pr is not None and math.isfinite(pr.mse_held) and pr.mse_held < ref.mse_held else ref
    return best, best_free, best_drop, against


# the figures of rank.score a candidate's entry keeps from its score before a nested null replaced
# its reference (entry "before_nested_null")
SCORE_KEYS = ("significant", "explained", "gain_over_noise", "relative_gain", "blocks_improved", "dbic")

# numerical failures of one candidate's fit or simulation: recorded, never raised
CANDIDATE_FAILURES = (ArithmeticError, ValueError, np.linalg.LinAlgError)


def within_bound(am: AugmentedModel, key: str, bounds: dict) -> bool:
    """Whether ``am``'s parameter ``key`` lies inside its bounds (inclusive; unbounded: always)."""
    lo, hi = bounds.get(key, (-np.inf, np.inf))
    return bool(lo <= get_parameter(am, key) <= hi)


def nested_null(fr: rank.FitResult, keys: list, free: list, cid: str | tuple, ref_model: AugmentedModel, data,
                max_nfev: int) -> rank.FitResult | None:
    """The candidate's fit ``fr`` with its own terms put back to the reference's values (off), and
    the baseline parameters its fit freed refitted from there: a null model fitted from where the
    candidate's fit ended. A candidate whose gain comes from its baseline parameters landing
    somewhere better, not from its term, does no better than this (on a clean recording a
    negligible friction or an offset whose interval holds 0 can beat the null model fitted from the
    reference by refitting the baseline alone). None if the fit fails."""
    m = fr.model.copy()
    for k in keys:
        if k in free:
            continue
        if k.startswith("fn:") and k[3:] not in ref_model.baseline.fn_m:
            m.baseline.fn_m.pop(k[3:], None)
        elif k.startswith("x:") and k[2:] not in ref_model.extras:
            m.extras.pop(k[2:], None)
        else:
            set_parameter(m, k, get_parameter(ref_model, k))
    for k in ("side", "v0"):            # shape parameters of an extra that is now off
        if k not in ref_model.extras:
            m.extras.pop(k, None)
    cids = (cid,) if isinstance(cid, str) else tuple(cid)
    m.added = [a for a in m.added if a not in cids]
    try:
        out = rank.fit(m, list(free), data, max_nfev=max_nfev)
    except CANDIDATE_FAILURES:
        return None
    return out if math.isfinite(out.mse_held) else None


def combined_fit(first: tuple, second: tuple, second_id: str, data, max_nfev: int) -> rank.FitResult:
    """The fit of ``first`` (fit, keys, scales, bounds, free baseline keys) with ``second``'s new terms
    added at their fitted values, and every parameter of both fitted together."""
    fr0, keys0, sc0, b0, free0 = first
    fr1, keys1, sc1, b1, _ = second
    m = fr0.model.copy()
    for k in keys1:
        set_parameter(m, k, get_parameter(fr1.model, k))
    if second_id == "contact_stiffness":
        m.extras["side"] = fr1.model.get("side")
    m.added = list(fr0.model.added) + [second_id]
    return rank.fit(m, list(dict.fromkeys(free0 + keys0 + keys1)), data, {**sc0, **sc1}, max_nfev=max_nfev,
                    bounds={**b0, **b1})


def joint_pair(tested: list, fits: dict, nulls: list, ref_model: AugmentedModel, data, noise_mse: float,
               max_nfev: int, refit_on=None, far_from_floor: bool = False,
               rule: SignificanceRule = DEFAULT_RULE) -> tuple[list, rank.FitResult | None]:
    """When no candidate is significant alone: two fitted together. Two effects (or an effect and a
    term the baseline lacks) can each explain too little of the mismatch alone.

    First the two that lower the held-out error most (for example a contact beside a y^2 the
    baseline lacks: each alone removes part of the mismatch, neither enough). They are fitted
    together from the better one's fit with the other's terms added at their fitted values, and
    (``refit_on(id, fit)``: a candidate's whole fit, its starts included, from another's fit) each
    fitted again from the other's fit: one candidate's fit can stand in for the other term (a
    contact's gap near 0 for y^2) and hold the pair there, while fitted on top of the other term it
    reaches the truth.
    Then, when the reference is far above the noise floor (``far_from_floor``), every other candidate
    plausible alone fitted on top of the one that lowers the fitting cost most, and the pair with the
    lowest fitting cost tried (a candidate refused alone is not taken: on the real bolted beam a
    contact whose kc interval held 0 alone was named on top of the exciter's distortion). This is
    for a baseline that lacks two things at once, such as friction and a hardening spring beside a
    linear reconstruction: each alone does no better than the reference (friction's k takes the
    hardening), while the pair reaches the truth.

    A pair is named (the one that lowers the fitting cost more alone first) only if it passes the
    rule against the best null model with both terms counted, each term adds significantly on top of
    the other one's own fit, both are plausible, and the null model fitted from where the pair ended
    does not explain it. Returns (the two tested entries, updated with the joint score, their
    figures alone kept under "alone"; the joint fit), or ([], None)."""
    plausible = [t for t in tested if t["id"] in fits and not t.get("implausible")]
    lower = sorted((t for t in plausible if fits[t["id"]][0].nrmse_held < t["compared_with_held_out_nrmse"]),
                   key=lambda t: fits[t["id"]][0].mse_held)[:2]
    rounds = []
    if len(lower) == 2:
        a, b = lower
        rounds.append([(a, b, lambda a=a, b=b: combined_fit(fits[a["id"]], fits[b["id"]], b["id"], data, max_nfev))]
                      + ([(a, b, lambda a=a, b=b: refit_on(b["id"], fits[a["id"]])),
                          (a, b, lambda a=a, b=b: refit_on(a["id"], fits[b["id"]]))] if refit_on else []))
    if far_from_floor and refit_on is not None and len(plausible) > 1:
        first = min(plausible, key=lambda t: fits[t["id"]][0].cost_fit)
        rounds.append([(first, t, lambda first=first, t=t: refit_on(t["id"], fits[first["id"]]))
                       for t in plausible if t is not first and not (lower and {first["id"], t["id"]} ==
                                                                  {x["id"] for x in lower})])
    against0 = min(nulls, key=lambda f: f.mse_held)
    for tries in rounds:
        got = []
        for a, b, make in tries:
            try:
                fr = make()
            except CANDIDATE_FAILURES:
                continue
            if math.isfinite(fr.mse_held) and fr.n_held > 0 and math.isfinite(fr.cost_fit):
                got.append((fr, a, b))
        if not got:
            continue
        frc, a, b = min(got, key=lambda g: g[0].cost_fit)
        if fits[b["id"]][0].cost_fit < fits[a["id"]][0].cost_fit:
            a, b = b, a
        (fa, keys_a, _, _, free_a), (fb, keys_b, _, _, _) = fits[a["id"]], fits[b["id"]]
        k2 = len(keys_a) + len(keys_b)
        joint = rank.score(against0, frc, k2, noise_mse, rule)
        if not (joint["significant"] and rank.score(fb, frc, len(keys_a), noise_mse, rule)["significant"]
                and rank.score(fa, frc, len(keys_b), noise_mse, rule)["significant"]):
            continue
        if implausible(a["id"], frc, ref_model, data) or implausible(b["id"], frc, ref_model, data):
            continue
        against = against0
        nn = nested_null(frc, keys_a + keys_b, free_a, (a["id"], b["id"]), ref_model, data, max_nfev)
        if nn is not None and nn.mse_held < against.mse_held:
            against = nn
            joint = rank.score(against, frc, k2, noise_mse, rule)
            if not joint["significant"]:
                continue
        for t, other in ((a, b), (b, a)):
            t["alone"] = {k: t.pop(k) if k in ("implausible", "compared_with_nested_null") else t[k]
                          for k in ("explained", "dbic", "significant", "held_out_nrmse",
                                    "compared_with_held_out_nrmse", "implausible", "compared_with_nested_null")
                          if k in t}
            t.update(joint)
            t["held_out_nrmse"] = frc.nrmse_held
            t["jointly_with"] = other["id"]
            t["compared_with_held_out_nrmse"] = against.nrmse_held
            if against is nn:
                t["compared_with_nested_null"] = True
            fits[t["id"]] = (frc,) + tuple(fits[t["id"]][1:4]) + (free_a,)
        return [a, b], frc
    return [], None


def linear_core(base: AugmentedModel, data, bkeys: list, max_nfev: int) -> rank.FitResult | None:
    """The baseline with its fn terms at 0 (kept in the model, so a fit frees them) and its linear
    terms refitted by output error; None without fn terms or when the fit fails."""
    if not base.baseline.fn_m:
        return None
    m = base.copy()
    for k in m.baseline.fn_m:
        m.baseline.fn_m[k] = 0.0
    return core_fit(m, [k for k in bkeys if k in GIVEN_FREE + ("inv_m",)], data, max_nfev)


def core_fit(m: AugmentedModel, free: list, data, max_nfev: int) -> rank.FitResult | None:
    """``m`` with ``free`` refitted by output error; None when the fit fails or predicts no held-out
    sample (the cores below: a null model and a place for candidate fits to start from)."""
    try:
        fr = rank.fit(m, free, data, max_nfev=max_nfev)
    except CANDIDATE_FAILURES:
        return None
    return fr if math.isfinite(fr.mse_held) and fr.n_held > 0 else None


HYSTERESIS_KEYS = ("alpha_m", "gamma", "delta")


def hysteresis_free_core(base: AugmentedModel, data, free: list, max_nfev: int) -> rank.FitResult | None:
    """The baseline without its Bouc-Wen law: alpha folded into k (the loop's small-amplitude
    stiffness is k + alpha), alpha, gamma and delta at 0 and held there, ``free`` (keys without
    HYSTERESIS_KEYS) refitted by output error. None for a baseline without hysteresis or when the
    fit fails.

    A reconstructed Bouc-Wen law can take up a dissipation it does not hold: its |y'| z terms
    dissipate more at larger amplitude, as quadratic damping or friction does. From such a
    baseline, and from its refit, the candidate's own term stays at 0; from this core it can reach
    its true value."""
    if base.baseline.alpha_m == 0.0:
        return None
    m = base.copy()
    b = m.baseline
    b.k_m += b.alpha_m
    b.alpha_m = b.gamma = b.delta = 0.0
    return core_fit(m, free, data, max_nfev)


def even_stiffness_terms(base: AugmentedModel) -> list[str]:
    """The baseline's fn terms even in y and free of y' (y^2, y^4, ...): the asymmetric part of its
    restoring force."""
    out = []
    for t in base.baseline.fn_m:
        p, r = monomials.parse(t)
        if r == 0 and p >= 2 and p % 2 == 0:
            out.append(t)
    return out


def even_stiffness_free_core(base: AugmentedModel, drop: tuple, data, free: list,
                             max_nfev: int) -> rank.FitResult | None:
    """The baseline without its even stiffness terms ``drop`` (even_stiffness_terms), ``free`` (keys
    without theirs) refitted by output error. None for a baseline without them or when the fit fails.

    A reconstructed y^2 or y^4 can take up a one-sided contact (the even part of its force); a
    contact fitted on top of it then has nothing left to explain (the even terms can fit the
    fitting stages better than the true contact while predicting the held-out stage worse, and the
    contact fitted beside them stays far below its true stiffness)."""
    if not drop:
        return None
    return core_fit(without_terms(base, drop), free, data, max_nfev)


def every_parameter(base: AugmentedModel) -> list[str]:
    """Every free parameter of the baseline: its own (rank.baseline_keys) and its extras' (but v0 and
    side, which a candidate's fit sets)."""
    return rank.baseline_keys(base.baseline) + [f"x:{k}" for k in base.extras if k not in ("v0", "side")]


def friction_from_loop(tested: list, fits: dict, references: dict, data, ctx: dict, fit_candidate,
                       ref_model: AugmentedModel, full_free: list, bkeys: list, noise_mse: float,
                       rule: SignificanceRule = DEFAULT_RULE) -> None:
    """Friction competes with a friction-like loop from the same start. A Bouc-Wen loop that slides
    within the record's travel is a friction law with presliding (wording.friction_reading); where
    the hysteresis candidate's fit is such a loop, coulomb_friction is fitted again from that fit
    with the loop taken out (its baseline's c, k and terms as fitted beside the loop, friction's own
    starts for mu and v0), and the better of its two fits on the held-out samples is scored by the
    same rule against the same reference. ``tested`` and ``fits`` are updated in place."""
    cid = "coulomb_friction"
    entry = next((t for t in tested if t["id"] == cid and cid in fits and cid in references), None)
    if entry is None or "hysteresis" not in fits:
        return
    loop = fits["hysteresis"][0].model
    b = loop.baseline
    travel = max((float(np.ptp(d.displacement)) for d in data), default=0.0)
    if friction_reading(b.alpha_m, b.gamma, b.delta, travel) is None:
        return
    src_model = without_terms(loop, ())
    src_model.baseline.alpha_m = src_model.baseline.gamma = src_model.baseline.delta = 0.0
    src_model.added = [a for a in src_model.added if a != "hysteresis"]
    free = [k for k in full_free if k not in HYSTERESIS_KEYS]
    try:
        src = rank.fit(src_model, [], data)
        fr, keys, sc, bnd = fit_candidate(cid, CATALOG[cid], src, free, [k for k in bkeys if k not in HYSTERESIS_KEYS])
    except CANDIDATE_FAILURES:
        return
    if not (math.isfinite(fr.mse_held) and fr.mse_held < fits[cid][0].mse_held):
        return
    against, k_added = references[cid]
    fits[cid] = (fr, keys, sc, bnd, free)
    entry.update(rank.score(against, fr, k_added, noise_mse, rule))
    entry.update(held_out_nrmse=fr.nrmse_held, started_from="hysteresis_fit_without_its_loop")
    why = implausible(cid, fr, ref_model, data)
    entry.pop("implausible", None)
    if why:
        entry["implausible"] = why
        entry["significant"] = False


def _reference_fits(run: Run, base: AugmentedModel, max_nfev: int, settings: DiagnosisSettings = DEFAULTS):
    """(stage data, the null model: every baseline parameter refitted, the baseline as given scored
    the same way with no parameter moved)."""
    data = rank.prepare(run, base.baseline, settings)
    null = rank.fit(base, every_parameter(base), data, max_nfev=max_nfev)
    given = rank.fit(base, [], data)
    return data, null, given


def _check_null(null, data, run) -> None:
    """The null model (the baseline refitted) must simulate every stage and leave held-out samples."""
    if null.n_held == 0:
        raise UserFacingError(f"{run.source or 'run'}: no held-out samples to compare models on (stages "
                              f"{', '.join(d.name for d in data)}); record a validation stage or longer stages")
    if not math.isfinite(null.mse_held):
        bad = [d for d in data if not np.isfinite(null.nrmse.get(d.name, np.nan))]
        where = ", ".join(d.name for d in bad) or ", ".join(d.name for d in data)
        raise UserFacingError(f"{run.source or 'run'}: the baseline refitted by output error does not simulate "
                              f"stage(s) {where} (the simulation diverged); try --baseline linear or a saved model")


@single_thread_blas
@progress.task("diagnose")
def diagnose(run: Run, baseline="paper", candidates=None, max_nfev: int = 30,
             settings: DiagnosisSettings | None = None) -> Diagnosis:
    """Diagnose ``run`` against ``baseline`` ("paper", "linear", a model JSON path or a model).
    ``settings``: the significance rule and the record's split and weighting
    (recon.diagnosis.settings; None: the calibrated defaults)."""
    if settings is not None and not isinstance(settings, DiagnosisSettings):
        raise TypeError(f"settings must be a DiagnosisSettings, not {type(settings).__name__}")
    return _diagnose(run, baseline, candidates, max_nfev, settings or DEFAULTS)


def _diagnose(run: Run, baseline, candidates, max_nfev: int, settings: DiagnosisSettings) -> Diagnosis:
    t0 = time.perf_counter()
    rule = settings.rule
    progress.step("the baseline model", share=0.15)
    base, kind = resolve_baseline(run, baseline, settings=settings)
    if base.excitation != run.excitation:
        raise UserFacingError(f"baseline model is {base.excitation} excitation, {run.source or 'run'} is {run.excitation}")
    data, null, given = _reference_fits(run, base, max_nfev, settings)
    if (kind in ("paper", "linear") and not (math.isfinite(null.mse_held) or math.isfinite(given.mse_held))
            and rank.uncovered_stages(run, settings)):
        # reconstructed without the held-out end of a stage (rank.fitting_part), the baseline does
        # not simulate that stage: it is reconstructed from the whole run instead, and its score on
        # that end is then in sample (a polynomial model fitted below a contact's engagement can
        # diverge past it)
        base, kind = resolve_baseline(run, baseline, whole=True, settings=settings)
        base.baseline.provenance["fitted_on_held_out"] = "the whole run (its fitting part alone diverged)"
        data, null, given = _reference_fits(run, base, max_nfev, settings)
    bkeys = rank.baseline_keys(base.baseline)
    full_free = every_parameter(base)
    before = given.nrmse
    _check_null(null if math.isfinite(null.mse_held) else given, data, run)
    # the reference every candidate must beat on the held-out samples: the better of the baseline as
    # given and the null model. When the refit is worse there (it absorbed the effect, or one tone
    # per stage leaves it poorly determined), the baseline's own parameters stay as given in every
    # candidate fit, so a candidate gets no credit for undoing a refit.
    refit_better = math.isfinite(null.mse_held) and not (math.isfinite(given.mse_held) and given.mse_held <= null.mse_held)
    ref = null if refit_better else given
    ref_name = "refit" if refit_better else "as_given"
    # candidate fits free the baseline's parameters from the null model; from the baseline as given
    # only its linear terms (c, k: where a baseline reconstructed from the same data absorbs an
    # effect, friction as extra viscous damping), the rest stays as given
    base_free = full_free if refit_better else list(GIVEN_FREE)
    sims = ref.sims
    progress.step("locating the mismatch", share=0.05)

    derivs = stage_derivatives(run, data)
    findings, ctx = locate(ref.model, run, data, sims, derivs)
    noise_mse = rank.held_noise_mse(data)
    tested = []
    fits = {}
    ids = candidates or list(CATALOG)

    def fit_candidate(cid, cand, src, free, step_keys):
        """One candidate's augmented fit started from ``src`` with ``free`` baseline keys; a candidate
        with a discrete shape parameter the fit cannot move (``fit_each``: the contact's side) is
        fitted once per value, and the fit with the lower fitting cost is kept (a start that ranks
        first by output error can still end worse than a full fit from the other value)."""
        if not cand.fit_each:
            return fit_from(cid, cand, src, free, step_keys, cand.starts)
        values = sorted({m.extras[cand.fit_each] for m, _, _, _ in cand.starts(src.model.baseline, ctx)})
        got, err = [], None
        for v in values:
            def group(base, ctx_, v=v):
                return [s for s in cand.starts(base, ctx_) if s[0].extras[cand.fit_each] == v]
            try:
                got.append(fit_from(cid, cand, src, free, step_keys, group))
            except CANDIDATE_FAILURES as exc:
                err = exc
        if not got:
            raise err
        return min(got, key=lambda g: g[0].cost_fit if math.isfinite(g[0].cost_fit) else math.inf)

    def fit_from(cid, cand, src, free, step_keys, make_starts):
        """:func:`fit_candidate` from the starts ``make_starts`` makes."""

        def starts_from(make):
            out = make(src.model.baseline, ctx)
            for m, _, _, _ in out:      # keep extras already in the baseline
                for k, v in src.model.extras.items():
                    m.extras.setdefault(k, v)
                m.added = list(src.model.added) + [cid]
            return out

        def screened(starts):
            """(model, keys, scales, bounds) of the best of ``starts`` after a short fit of the new terms."""
            fits = [rank.fit(m, keys[:cand.screen_keys], data, sc, max_nfev=5, bounds=b) for m, keys, sc, b in starts]
            i = int(np.argmin([f.cost_fit for f in fits]))
            return (fits[i].model,) + tuple(starts[i][1:])

        starts = starts_from(make_starts)
        if cand.column is not None:     # linear in its first parameter: equation-error step per start
            stepped = [rank.equation_step(m, step_keys, keys[0], cand.column, derivs, data)
                       for m, keys, _, _ in starts]
            if cand.screen_output and len(starts) > 1:
                # the starts differ in a fixed shape parameter (friction's v0): the equation residual
                # cannot rank them (differentiation noise), a short output-error fit can
                # (from the source model, the new term at its scale: the equation step's increments of
                # the baseline's terms are biased by the same differentiation noise)
                scr = []
                for mm, keys, sc, b in starts:
                    mm = mm.copy()
                    set_parameter(mm, keys[0], sc[keys[0]])
                    scr.append(rank.fit(mm, [keys[0]], data, sc, max_nfev=8, bounds=b))
                i = int(np.argmin([f.cost_fit for f in scr]))
                # the equation step itself is kept where its output error is lower still: where the
                # source's damping holds the friction (a baseline whose viscous c is the friction's
                # pre-sliding mu / v0, many times the true c), mu alone fitted from the source only
                # adds damping and stays at 0; the step moves c and mu together, to near their true
                # values
                step_cost = [rank.fit_cost(mm, data)
                             if within_bound(mm, starts[j][1][0], starts[j][3]) else math.inf
                             for j, (mm, _) in enumerate(stepped)]
                j = int(np.argmin(step_cost))
                if not step_cost[j] < scr[i].cost_fit:
                    stepped[i] = (scr[i].model, 0.0)
                else:
                    i = j
            else:
                # a start whose step puts the new term inside its physical bound first: the equation
                # residuals of the starts differ by a few per cent at most (differentiation noise),
                # and a step across the bound says that start is wrong (a contact's start on the
                # wrong side steps to kc < 0 with a residual as low as the true side's, and a fit
                # from there can end worse than no contact)
                inside = [j for j, (mm, _) in enumerate(stepped) if within_bound(mm, starts[j][1][0], starts[j][3])]
                if len(inside) > 1:
                    # and among those, the step the output error says fits best: the equation
                    # residuals differ by differentiation noise (a contact's wrong side can rank
                    # first by equation residual and lead the fit away from the truth)
                    cost = {j: rank.fit_cost(stepped[j][0], data) for j in inside}
                    if len(starts[inside[0]][1]) > 1:
                        # the starts differ in a shape parameter fitted beside the stepped one (the
                        # contact's gap): a step alone ranks them by where they start, a short fit
                        # of the new terms by where they lead (the contact gap whose stepped start
                        # has the lowest output error can be one the fit stays stuck near, while
                        # other gaps lead to the true one)
                        for j in inside:
                            _, kj, scj, bj = starts[j]
                            try:
                                short = rank.fit(stepped[j][0], kj, data, scj, max_nfev=SHAPE_SCREEN_NFEV,
                                                 bounds=bj)
                            except CANDIDATE_FAILURES:
                                continue    # that start is ranked by its step alone
                            if math.isfinite(short.cost_fit) and short.cost_fit < cost[j]:
                                stepped[j], cost[j] = (short.model, stepped[j][1]), short.cost_fit
                    i = min(inside, key=cost.get)
                else:
                    i = min(inside or range(len(stepped)), key=lambda j: stepped[j][1])
                # the step is an equation-error estimate, and differentiation errors can point it the
                # wrong way: kept only if the output error says it is a better start than none
                # (a step of the wrong sign, for a stiffness drift, holds the fit there; from 0 it
                # reaches the truth). Only for a term free of bounds: "none" would put a bounded one
                # (c2, kc, mu >= 0) on its bound, where the fit does not move it and the effect
                # goes unnamed
                lo_, hi_ = starts[i][3].get(starts[i][1][0], (-np.inf, np.inf))
                if (not (np.isfinite(lo_) or np.isfinite(hi_))
                        and rank.fit_cost(stepped[i][0], data) > rank.fit_cost(starts[i][0], data)):
                    stepped[i] = (starts[i][0].copy(), stepped[i][1])
            _, keys, sc, b = starts[i]
            m = stepped[i][0]
            lo = b.get(keys[0], (-np.inf, np.inf))[0]
            if keys[0].startswith("x:") and np.isfinite(lo) and m.extras[keys[0][2:]] < lo:
                # the equation-error step points across the term's physical bound (input-estimation
                # errors bias it): also start from two values inside the bound, refit with c and k,
                # and keep the start that fits best
                m.extras[keys[0][2:]] = lo
                tries = [m]
                for mult in (1.0, 5.0):
                    mm = m.copy()
                    mm.extras[keys[0][2:]] = lo + mult * sc[keys[0]]
                    tries.append(mm)
                screened = [rank.fit(mm, [keys[0], "c_m", "k_m"], data, sc, max_nfev=8, bounds=b) for mm in tries]
                m = screened[int(np.argmin([f.cost_fit for f in screened]))].model
        elif len(starts) > 1:           # screen the starts with only the new terms free
            m, keys, sc, b = screened(starts)
        else:
            m, keys, sc, b = starts[0]
        fr = rank.fit(m, list(dict.fromkeys(free + keys)), data, sc, max_nfev=max_nfev, bounds=b)
        if cand.admissible_starts is not None and implausible(cid, fr, src.model, data, intervals=False):
            # the fit ended outside the physical range (hysteresis: a negative alpha):
            # fitted again from starts inside it, kept if it ends inside
            m2, keys2, sc2, b2 = screened(starts_from(cand.admissible_starts))
            fr2 = rank.fit(m2, list(dict.fromkeys(free + keys2)), data, sc2, max_nfev=max_nfev, bounds=b2)
            if math.isfinite(fr2.mse_held) and not implausible(cid, fr2, src.model, data, intervals=False):
                fr, keys, sc, b = fr2, keys2, sc2, b2
        if not (math.isfinite(fr.mse_held) and fr.n_held > 0):
            raise FloatingPointError(f"held-out mean-square error is {fr.mse_held} on {fr.n_held} samples")
        return fr, keys, sc, b

    # where candidate fits start: the reference, and the other of the two: the null model with every
    # baseline parameter free (a refit that is worse alone may be right with the missing term), or
    # the baseline as given with c and k free; the start with the lower held-out error is scored,
    # against the reference
    origins = [(ref, base_free, bkeys if refit_better else list(GIVEN_FREE), ref_name)]
    if not refit_better and math.isfinite(null.mse_held):
        origins.append((null, full_free, bkeys, "refit"))
    elif refit_better and math.isfinite(given.mse_held):
        # and the other way round: a refit that is better alone can lead the candidate's fit astray
        # (for an offset, c and k can run far from their true values from the refit and the
        # validation simulation diverge, where from the baseline as given the offset is found)
        origins.append((given, list(GIVEN_FREE), list(GIVEN_FREE), "as_given"))
    if not refit_better:
        # and the baseline as given with only the term's own parameters free: where refitting the
        # baseline hurts the held-out samples, c and k moved beside the term can too (where one
        # stage that every model misfits, the truth included, holds the fitting cost, c and k free
        # trade the other stages for it; a sensor-scale term alone does better)
        origins.append((given, [], [], "term_alone"))
    pruned_refs = {}
    nulls = []          # null models fitted from where a significant candidate's fit ended
    core = linear_core(base, data, bkeys, max_nfev) if ref.nrmse_held > LINEAR_CORE_NRMSE else None
    if core is not None:
        # a reference that misses most of the response is no place for a local fit to start from:
        # reconstruct's library has no friction term, and on friction sweeps it made the paper
        # baseline of huge opposite-signed y^3 and y^2 y' terms; from there no candidate moves
        # (friction's mu stays at 0), from the linear core (c and k refitted, the fn terms at 0 and
        # free) friction reaches the truth's figure. The core is also a null model every candidate
        # must beat
        origins.append((core, full_free, bkeys, "linear_core"))
        nulls.append(core)
    unlooped_origins = []
    evenless_origins = []
    even_terms = tuple(even_stiffness_terms(base))
    if any(CATALOG[c].hysteresis_absorbs for c in ids if c in CATALOG):
        # the dissipative candidates and the sensor scale (catalog: hysteresis_absorbs) also start
        # from the baseline without its Bouc-Wen law (a law the reconstruction may have made of the
        # missing dissipation or of part of a reading error); that core alone is a null
        # model too, so a candidate gets no credit for dropping the law
        loopless_free = [k for k in full_free if k not in HYSTERESIS_KEYS]
        unlooped = hysteresis_free_core(base, data, loopless_free, max_nfev)
        if unlooped is not None:
            nulls.append(unlooped)
            unlooped_origins.append((unlooped, loopless_free, [k for k in bkeys if k not in HYSTERESIS_KEYS],
                                     "without_hysteresis"))
    if any(CATALOG[c].even_stiffness_absorbs for c in ids if c in CATALOG):
        # a one-sided stiffness also starts from the baseline without its even stiffness terms (which
        # the reconstruction may have made of it); that core alone is a null model too
        even = {f"fn:{t}" for t in even_terms}
        evenless_free = [k for k in full_free if k not in even]
        evenless = even_stiffness_free_core(base, even_terms, data, evenless_free, max_nfev)
        if evenless is not None:
            nulls.append(evenless)
            evenless_origins = [(evenless, evenless_free, [k for k in bkeys if k not in even],
                                 "without_even_stiffness")]
    references = {}     # candidate id: (the reference it was scored against, its added parameters)

    for cid in ids:
        progress.step(f"candidate {cid} ({ids.index(cid) + 1} of {len(ids)})", share=0.65 / len(ids))
        if cid not in CATALOG:
            raise UserFacingError(f"unknown candidate {cid!r} (catalog: {', '.join(CATALOG)})")
        cand = CATALOG[cid]
        if cid in ref.model.added or not cand.applies(ref.model.baseline, ctx):
            continue
        tc = time.perf_counter()
        try:
            got, errs = [], []
            for src, free, step_keys, oname in (origins + (unlooped_origins if cand.hysteresis_absorbs else [])
                                               + (evenless_origins if cand.even_stiffness_absorbs else [])):
                try:
                    got.append((fit_candidate(cid, cand, src, free, step_keys), free, oname))
                    fr0, keys0, sc0, b0 = got[-1][0]
                    if (oname == "as_given" and not refit_better and set(full_free) - set(free)
                            and fr0.cost_fit < FOLLOW_ON_SHARE * src.cost_fit):
                        # the refit alone is worse than the baseline as given, and the term took
                        # half the fitting cost with only c and k free: the rest of the baseline,
                        # fitted without the term, is refitted beside it too (a baseline whose
                        # Bouc-Wen law absorbed a friction: with c and k alone the friction does
                        # not reach significance, with every parameter free it reaches the truth's
                        # figure). Also where the c-and-k fit already predicts the held-out
                        # samples better: it can still fall short of significance that the full
                        # refit reaches
                        fa = rank.fit(fr0.model, list(dict.fromkeys(full_free + keys0)), data, sc0,
                                      max_nfev=max(max_nfev // 2, 5), bounds=b0)
                        if math.isfinite(fa.mse_held) and fa.n_held > 0:
                            got.append(((fa, keys0, sc0, b0), full_free, "as_given_then_refit"))
                except CANDIDATE_FAILURES as exc:
                    errs.append(exc)
            if not got:
                raise errs[0]
            (fr, keys, sc, b), free, oname = min(got, key=lambda g: g[0][0].mse_held)
            if oname == "as_given_then_refit":
                # every fn term of the baseline was refitted beside the term already; dropping them
                # one set at a time with every parameter free costs minutes (friction on the
                # harmonic offset test: 29 s without the follow-on fit, 113 s with it and the drops)
                drop, against = (), ref
            else:
                fr, free, drop, against = prune_absorbed(fr, keys, sc, b, free, ref, data, max_nfev, pruned_refs,
                                                         rule)
            sc_ = rank.score(against, fr, len(keys), noise_mse, rule)
            before_nested = None
            if sc_["significant"]:
                nn = nested_null(fr, keys, free, cid, ref.model, data, max_nfev)
                if nn is not None:
                    nulls.append(nn)
                    if nn.mse_held < against.mse_held:
                        # the score that made the nested null be fitted, kept so that a change of the
                        # rule can be judged on stored rows (it decides whether this null exists)
                        before_nested = {k: sc_[k] for k in SCORE_KEYS if k in sc_}
                        against = nn
                        sc_ = rank.score(against, fr, len(keys), noise_mse, rule)
        except CANDIDATE_FAILURES as exc:
            # a candidate whose fit or simulation fails is recorded with its reason and not ranked
            tested.append({"id": cid, "failed": f"{type(exc).__name__}: {exc}", "significant": False,
                           "seconds": time.perf_counter() - tc})
            continue
        fits[cid] = (fr, keys, sc, b, free)
        entry = {"id": cid, **sc_, "held_out_nrmse": fr.nrmse_held, "started_from": oname,
                 "seconds": time.perf_counter() - tc}
        entry["compared_with_held_out_nrmse"] = against.nrmse_held
        if any(against is n for n in nulls):
            entry["compared_with_nested_null"] = True
        if before_nested is not None:
            entry["before_nested_null"] = before_nested
        references[cid] = (against, len(keys))
        if drop:
            entry["baseline_terms_dropped"] = list(drop)
        if oname == "without_hysteresis":
            entry["hysteresis_dropped"] = True
        if oname == "without_even_stiffness":
            entry["baseline_terms_dropped"] = sorted(set(entry.get("baseline_terms_dropped", []))
                                                     | set(even_terms))
        why = implausible(cid, fr, ref.model, data)
        if why:
            entry["implausible"] = why
            entry["significant"] = False
        tested.append(entry)
    friction_from_loop(tested, fits, references, data, ctx, fit_candidate, ref.model, full_free, bkeys, noise_mse,
                       rule)
    # the best null model found anywhere (the reference, or a candidate's fit with its term off
    # and the baseline refitted) is the one every candidate must beat: scored again against it
    if nulls:
        best_null = min(nulls, key=lambda f: f.mse_held)
        for t in tested:
            if t.get("significant") and t["id"] in references:
                against, k_added = references[t["id"]]
                if best_null.mse_held < against.mse_held:
                    t.update(rank.score(best_null, fits[t["id"]][0], k_added, noise_mse, rule))
                    t["compared_with_held_out_nrmse"] = best_null.nrmse_held
                    t["compared_with_nested_null"] = True
    # never an improvement that is worse on a held-out stage (stagewise.py): a candidate significant
    # on the held-out samples together must also be no worse than the baseline as given on each
    # held-out stage beyond that stage's noise band; one that is is kept out of the ranking, and the
    # answer is "partly explained" if nothing else is named
    partly = []
    for t in tested:
        if t.get("significant") and t["id"] in fits:
            figs = held_stage_figures(given, fits[t["id"]][0], data, rule.stage_level)
            t["held_out_stages"] = figs
            bad = worse_stages(figs)
            if bad:
                t["significant"] = False
                t["worse_on_stages"] = bad
                partly.append(partly_entry([t["id"]], figs, fits[t["id"]][0], given) | {"explained": t["explained"]})
    # what the record can show: the size at which each candidate's effect, added to it, would be named
    # (an estimate; sensitivity.py)
    progress.step("detection limits", share=0.1)
    limits = detection_limits(ref, fits, data, noise_mse, CANDIDATE_FAILURES, rule)
    for t in tested:
        if t["id"] in limits:
            t["detection_limit"] = limits[t["id"]]
    sig = [t for t in tested if t["significant"]]
    sig.sort(key=lambda t: -t["explained"])
    combined = None
    if not sig:

        def refit_on(cid, first):
            """``cid``'s fit (its own starts) from the fit ``first`` of another candidate."""
            fr0, keys0, _, _, free0 = first
            return fit_candidate(cid, CATALOG[cid], fr0, list(dict.fromkeys(free0 + keys0)),
                                 [k for k in free0 if k in bkeys])[0]

        sig, combined = joint_pair(tested, fits, nulls + [ref], ref.model, data, noise_mse, max_nfev, refit_on,
                                   unexplained_mismatch(ref, noise_mse, []) is not None, rule)
        if combined is not None:
            figs = held_stage_figures(given, combined, data, rule.stage_level)
            if worse_stages(figs):      # the pair is held to every held-out stage too
                partly.append(partly_entry([t["id"] for t in sig], figs, combined, given)
                              | {"explained": min(t["explained"] for t in sig)})
                for t in sig:
                    t.update(significant=False, worse_on_stages=worse_stages(figs), held_out_stages=figs)
                sig, combined = [], None
    ranked = list(sig)
    if len(sig) > 1 and combined is None:
        # forward step: a runner-up is reported only if it still adds on top of the best one
        best_fr, _, _, _, best_free = fits[sig[0]["id"]]
        kept = [sig[0]]
        for t in sig[1:]:
            _, keys1, sc1, b1, _ = fits[t["id"]]
            try:
                frc = combined_fit(fits[sig[0]["id"]], fits[t["id"]], t["id"], data, max_nfev)
                s2 = rank.score(best_fr, frc, len(keys1), noise_mse, rule)
            except CANDIDATE_FAILURES as exc:
                t["on_top_of_best"] = {"failed": f"{type(exc).__name__}: {exc}", "significant": False}
                continue
            why = implausible(t["id"], frc, ref.model, data) + implausible(sig[0]["id"], frc, ref.model, data)
            if why:
                s2 = {**s2, "implausible": why, "significant": False}
            if s2["significant"]:
                figs = held_stage_figures(given, frc, data, rule.stage_level)
                if worse_stages(figs):      # the two together are held to every held-out stage too
                    s2 = {**s2, "significant": False, "worse_on_stages": worse_stages(figs)}
            t["on_top_of_best"] = s2
            if s2["significant"]:
                kept.append(t)
                fits[t["id"]] = (frc, keys1, sc1, b1, best_free)
                combined = frc
                break
        sig = kept
    pair = ambiguous_pair(ranked, {t["id"] for t in sig[1:]}, {c: f[0].mse_held for c, f in fits.items()},
                          rule.bic_margin, noise_mse)
    ambiguity = separating_stage(pair) if pair else None
    missing = []
    for t in sig:
        fr, keys = fits[t["id"]][:2]
        cand = CATALOG[t["id"]]
        ev_kinds = SIGNATURES.get(t["id"], ())
        missing.append({
            "id": t["id"], "explanation": cand.explanation, "adds": cand.adds, "simulated": cand.simulated,
            "parameters": _params_of(fr, [k for k in cand.parameters if k in keys or k == "x:side"]),
            "evidence": {"held_out_nrmse_before": given.nrmse_held, "held_out_nrmse_after": fr.nrmse_held,
                         "held_out_nrmse_refit": null.nrmse_held, "compared_with": ref_name,
                         "explained_fraction_of_excess": t["explained"], "delta_bic_held_out": t["dbic"],
                         "effective_samples": t["n_eff"],
                         "compared_with_held_out_nrmse": t["compared_with_held_out_nrmse"],
                         "located": [f for f in findings if f["kind"] in ev_kinds][:4]},
            "fit_after": {"nrmse": fr.nrmse},
            "baseline_terms_dropped": t.get("baseline_terms_dropped", []),
            "hysteresis_dropped": bool(t.get("hysteresis_dropped", False)),
        })
        if t["id"] == "hysteresis":
            # a named loop that slides within the record's travel is a friction law (wording.py)
            b = fr.model.baseline
            travel = max((float(np.ptp(d.displacement)) for d in data), default=0.0)
            missing[-1]["as_friction"] = friction_reading(b.alpha_m, b.gamma, b.delta, travel)
    if combined is not None:
        best_fr = combined
    elif missing:
        best_fr = fits[missing[0]["id"]][0]
    else:
        best_fr = ref
    # fit_before: the baseline as given (nrmse, held_out_nrmse); the null model's figures under refit_*
    partly_explained = (None if missing or not partly
                        else {k: v for k, v in max(partly, key=lambda p: p["explained"]).items() if k != "explained"})
    fit_before = {"nrmse": before, "refit_nrmse": null.nrmse, "held_out_nrmse": given.nrmse_held,
                  "held_out_nrmse_as_given": given.nrmse_held, "refit_held_out_nrmse": null.nrmse_held,
                  "compared_with": ref_name,
                  "noise_nrmse": {d.name: d.noise / d.rms for d in data},
                  # the share of each stage's samples the models are compared on (a validation stage
                  # whole; the end of a stage the validation stages do not reach, rank.uncovered_stages)
                  "held_out_share": {d.name: float(np.mean(d.held)) for d in data if d.held.any()}}
    if core is not None:
        # candidate fits also started from the baseline's linear core (LINEAR_CORE_NRMSE)
        fit_before["linear_core_held_out_nrmse"] = core.nrmse_held
    return Diagnosis(baseline=base, baseline_kind=kind, fit_before=fit_before, null=null, mismatch=findings,
                     candidates=tested, missing=missing, best=best_fr.model, best_fit=best_fr, context=ctx,
                     seconds=time.perf_counter() - t0, reference=ref, ambiguity=ambiguity,
                     unexplained=unexplained_mismatch(best_fr, noise_mse, [m["id"] for m in missing]),
                     partly=partly_explained)

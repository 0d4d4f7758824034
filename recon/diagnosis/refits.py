"""A candidate's fit refitted: without the baseline terms that absorbed it, with its own term
off (the nested null), and together with a second candidate.

- :func:`prune_absorbed`: a reconstructed baseline absorbs missing physics into fn terms of its
  own (friction as y'^3 and y'^5, which compensate each other); a candidate fitted next to them
  cannot show what it explains, so a candidate that removes much of the fitting cost is refitted
  without them, and scored against the baseline without the same terms.
- :func:`nested_null`: the null model fitted from where the candidate's fit ended, so that a
  candidate gets no credit for baseline parameters its fit moved somewhere better.
- :func:`combined_fit`, :func:`joint_pair`: two candidates fitted together, when each alone explains
  too little or a runner-up is tested on top of the best one.
- :func:`friction_from_loop`: friction fitted again from a Bouc-Wen fit that is a friction law.

Every function takes and returns :class:`recon.diagnosis.candidate_fit.CandidateFit` records; a
refit that fails numerically is skipped, never raised.
"""
from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.candidate_fit import CANDIDATE_FAILURES, CandidateFit, fit_candidate, implausible
from recon.diagnosis.catalog import CATALOG
from recon.diagnosis.context import DiagnosisContext
from recon.diagnosis.references import HYSTERESIS_KEYS, without_terms
from recon.diagnosis.settings import DEFAULT_RULE, DEFAULTS, DiagnosisSettings, SignificanceRule
from recon.diagnosis.wording import friction_reading
from recon.library import monomials
from recon.output_error.problem import get_parameter, set_parameter


def drop_sets(terms: list[str], settings: DiagnosisSettings = DEFAULTS) -> list[tuple]:
    """The sets of baseline fn terms a candidate is refitted without: each term, each pair (up to
    ``settings.prune_pairs_up_to`` terms), all of them, and each parity class of y' in full: the
    terms odd in y' (dissipative, where friction or nonlinear damping is absorbed) and the even ones
    (elastic, where a stiffness law is). A baseline that absorbed friction holds several dissipative
    terms next to true elastic ones (odd terms in y' such as y^2 y', y'^3, y'^5 beside y^2, y^3);
    neither the pairs nor the whole set take out just the absorbing ones."""
    out = [(t,) for t in terms]
    if len(terms) <= settings.prune_pairs_up_to:
        out += list(itertools.combinations(terms, 2))
    if len(terms) > 2:
        out.append(tuple(terms))
    for odd in (1, 0):
        cls = tuple(t for t in terms if monomials.parse(t)[1] % 2 == odd)
        if 1 < len(cls) < len(terms) and cls not in out:
            out.append(cls)
    return out


def prune_absorbed(cf: CandidateFit, ref: rank.FitResult, data, max_nfev: int, cache: dict | None = None,
                   settings: DiagnosisSettings = DEFAULTS) -> tuple[CandidateFit, tuple, rank.FitResult]:
    """(the candidate's fit, the baseline fn terms dropped, the reference to score it against).

    The fit ``cf`` is refitted without the baseline fn terms it may have made redundant, and the
    refit kept when it predicts the held-out samples better; tried only for a candidate that leaves
    at most ``settings.prune_fit_share`` of the reference's fitting cost, or lowers its held-out
    NRMSE by the rule's min_rel_gain (where one stage misfitted by every model holds most of the
    fitting cost, no candidate removes much of it, yet the held-out error can show a baseline term
    standing in for the candidate's). The reference is then the better of ``ref`` and the baseline
    without the same terms, refitted as the candidate's fit was: the candidate gets no credit for
    what dropping them and refitting the rest alone does. ``cache`` keeps those pruned references
    between candidates."""
    cache = {} if cache is None else cache
    fr, keys, sc, b, free = cf.fit, cf.keys, cf.scales, cf.bounds, list(cf.free)
    terms = [t for t in fr.model.baseline.fn_m if f"fn:{t}" not in keys]
    promising = (math.isfinite(fr.nrmse_held) and math.isfinite(ref.nrmse_held)
                 and fr.nrmse_held <= (1.0 - settings.rule.min_rel_gain) * ref.nrmse_held)
    if not terms or not (fr.cost_fit < settings.prune_fit_share * ref.cost_fit or promising):
        return cf, (), ref
    best, best_free, best_drop = fr, free, ()
    for drop in drop_sets(terms, settings):
        # first with the baseline's other fn terms as they are; then, from there, with them refitted
        # too: they were fitted next to the dropped ones and may compensate them. The reference
        # below refits what the kept fit refitted, so the candidate gets no credit for that
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
        return cf, (), ref
    key = (best_drop, tuple(best_free))
    if key not in cache:
        try:    # the reference frees what the candidate's fit freed of the baseline
            cache[key] = rank.fit(without_terms(ref.model, best_drop), best_free, data, max_nfev=max_nfev)
        except CANDIDATE_FAILURES:
            cache[key] = None
    pr = cache[key]
    against = pr if pr is not None and math.isfinite(pr.mse_held) and pr.mse_held < ref.mse_held else ref
    return dataclasses.replace(cf, fit=best, free=best_free), best_drop, against


def nested_null(cf: CandidateFit, cid: str | tuple, ref_model: AugmentedModel, data,
                max_nfev: int) -> rank.FitResult | None:
    """The candidate's fit with its own terms put back to the reference's values (off), and the
    baseline parameters its fit freed refitted from there: a null model fitted from where the
    candidate's fit ended. A candidate whose gain comes from its baseline parameters landing
    somewhere better, not from its term, does no better than this. ``cid``: the candidate's id,
    or the ids of a pair fitted together. None if the fit fails."""
    m = cf.fit.model.copy()
    free = list(cf.free)
    for k in cf.keys:
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
        out = rank.fit(m, free, data, max_nfev=max_nfev)
    except CANDIDATE_FAILURES:
        return None
    return out if math.isfinite(out.mse_held) else None


def combined_fit(first: CandidateFit, second: CandidateFit, second_id: str, data, max_nfev: int) -> rank.FitResult:
    """The fit of ``first`` with ``second``'s new terms added at their fitted values, and every
    parameter of both (``first``'s free baseline keys, both candidates' keys) fitted together."""
    m = first.fit.model.copy()
    for k in second.keys:
        set_parameter(m, k, get_parameter(second.fit.model, k))
    if second_id == "contact_stiffness":
        m.extras["side"] = second.fit.model.get("side")
    m.added = list(first.fit.model.added) + [second_id]
    return rank.fit(m, list(dict.fromkeys(list(first.free) + first.keys + second.keys)), data,
                    {**first.scales, **second.scales}, max_nfev=max_nfev, bounds={**first.bounds, **second.bounds})


def refit_on(cid: str, first: CandidateFit, bkeys: list, dctx: DiagnosisContext) -> rank.FitResult:
    """Candidate ``cid``'s whole fit (its own starts) from the fit ``first`` of another candidate,
    with everything ``first`` fitted free."""
    return fit_candidate(cid, CATALOG[cid], first.fit, first.fitted_keys(),
                         [k for k in first.free if k in bkeys], dctx).fit


def joint_pair(tested: list, fits: dict, nulls: list, ref_model: AugmentedModel, data, noise_mse: float,
               max_nfev: int, refit_on=None, far_from_floor: bool = False,
               rule: SignificanceRule = DEFAULT_RULE) -> tuple[list, rank.FitResult | None]:
    """When no candidate is significant alone: two fitted together (``fits``: {id: CandidateFit}).
    Two effects (or an effect and a term the baseline lacks) can each explain too little of the
    mismatch alone.

    First the two that lower the held-out error most. They are fitted together from the better
    one's fit with the other's terms added at their fitted values, and (``refit_on(id, fit)``: a
    candidate's whole fit, its starts included, from another's CandidateFit) each fitted again from
    the other's fit: one candidate's fit can stand in for the other term and hold the pair there,
    while fitted on top of the other term it reaches the truth.
    Then, when the reference is far above the noise floor (``far_from_floor``), every other candidate
    plausible alone fitted on top of the one that lowers the fitting cost most, and the pair with the
    lowest fitting cost tried (a candidate refused alone is not taken). This is for a baseline that
    lacks two things at once: each alone does no better than the reference, the pair reaches the
    truth.

    A pair is named (the one that lowers the fitting cost more alone first) only if it passes the
    rule against the best null model with both terms counted, each term adds significantly on top of
    the other one's own fit, both are plausible, and the null model fitted from where the pair ended
    does not explain it. Returns (the two tested entries, updated with the joint score, their
    figures alone kept under "alone"; the joint fit), or ([], None). ``fits`` of the pair are
    updated to the joint fit."""
    plausible = [t for t in tested if t["id"] in fits and not t.get("implausible")]
    lower = sorted((t for t in plausible if fits[t["id"]].fit.nrmse_held < t["compared_with_held_out_nrmse"]),
                   key=lambda t: fits[t["id"]].fit.mse_held)[:2]
    rounds = []
    if len(lower) == 2:
        a, b = lower
        rounds.append([(a, b, lambda a=a, b=b: combined_fit(fits[a["id"]], fits[b["id"]], b["id"], data, max_nfev))]
                      + ([(a, b, lambda a=a, b=b: refit_on(b["id"], fits[a["id"]])),
                          (a, b, lambda a=a, b=b: refit_on(a["id"], fits[b["id"]]))] if refit_on else []))
    if far_from_floor and refit_on is not None and len(plausible) > 1:
        first = min(plausible, key=lambda t: fits[t["id"]].fit.cost_fit)
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
        if fits[b["id"]].fit.cost_fit < fits[a["id"]].fit.cost_fit:
            a, b = b, a
        fit_a, fit_b = fits[a["id"]], fits[b["id"]]
        k2 = len(fit_a.keys) + len(fit_b.keys)
        joint = rank.score(against0, frc, k2, noise_mse, rule)
        if not (joint["significant"] and rank.score(fit_b.fit, frc, len(fit_a.keys), noise_mse, rule)["significant"]
                and rank.score(fit_a.fit, frc, len(fit_b.keys), noise_mse, rule)["significant"]):
            continue
        if implausible(a["id"], frc, ref_model, data) or implausible(b["id"], frc, ref_model, data):
            continue
        against = against0
        pair = CandidateFit(fit=frc, keys=fit_a.keys + fit_b.keys, scales={}, bounds={}, free=fit_a.free)
        nn = nested_null(pair, (a["id"], b["id"]), ref_model, data, max_nfev)
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
            fits[t["id"]] = dataclasses.replace(fits[t["id"]], fit=frc, free=fit_a.free)
        return [a, b], frc
    return [], None


def friction_from_loop(tested: list, fits: dict, references: dict, dctx: DiagnosisContext,
                       ref_model: AugmentedModel, full_free: list, bkeys: list) -> None:
    """Friction competes with a friction-like loop from the same start. A Bouc-Wen loop that slides
    within the record's travel is a friction law with presliding (wording.friction_reading); where
    the hysteresis candidate's fit is such a loop, coulomb_friction is fitted again from that fit
    with the loop taken out (its baseline's c, k and terms as fitted beside the loop, friction's own
    starts for mu and v0), and the better of its two fits on the held-out samples is scored by the
    same rule against the same reference (``references``: {id: (reference, parameters added)}).
    ``tested`` and ``fits`` are updated in place."""
    cid = "coulomb_friction"
    data = dctx.data
    entry = next((t for t in tested if t["id"] == cid and cid in fits and cid in references), None)
    if entry is None or "hysteresis" not in fits:
        return
    loop = fits["hysteresis"].fit.model
    b = loop.baseline
    travel = max((float(np.ptp(d.displacement)) for d in data), default=0.0)
    if friction_reading(b.alpha_m, b.gamma, b.delta, travel, dctx.settings) is None:
        return
    src_model = without_terms(loop, ())
    src_model.baseline.alpha_m = src_model.baseline.gamma = src_model.baseline.delta = 0.0
    src_model.added = [a for a in src_model.added if a != "hysteresis"]
    free = [k for k in full_free if k not in HYSTERESIS_KEYS]
    name = "hysteresis_fit_without_its_loop"
    try:
        src = rank.fit(src_model, [], data)
        cf = fit_candidate(cid, CATALOG[cid], src, free, [k for k in bkeys if k not in HYSTERESIS_KEYS], dctx, name)
    except CANDIDATE_FAILURES:
        return
    fr = cf.fit
    if not (math.isfinite(fr.mse_held) and fr.mse_held < fits[cid].fit.mse_held):
        return
    against, k_added = references[cid]
    fits[cid] = cf
    entry.update(rank.score(against, fr, k_added, dctx.noise_mse, dctx.rule))
    entry.update(held_out_nrmse=fr.nrmse_held, started_from=name)
    why = implausible(cid, fr, ref_model, data)
    entry.pop("implausible", None)
    if why:
        entry["implausible"] = why
        entry["significant"] = False

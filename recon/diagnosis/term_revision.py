"""The baseline's fn terms chosen again under a candidate.

A reconstructed baseline that lacks an effect holds fn terms that stand in for it (friction as
y y'^2 and y'^3, quadratic damping as y^2 y'^3) and may lack true terms the effect's absence let
it trade away. A candidate fitted with those terms free explains only what they leave it: dropping
them one at a time (refits.prune_absorbed) cannot add a true term the baseline never had, so the
effect can end "partly explained" or short of the rule.

:func:`revise_terms` revises the fn terms of a fit by output error with the candidate in, as
reconstruct revises its own model's terms (recon.output_error.term_selection), but on the
diagnosis's fitting samples:

1. around the fit, one Jacobian of the fitting residual with respect to every free parameter, the
   fit's fn terms and the low-order monomials it lacks (coefficient 0; each scaled to 1 % of the
   elastic force at the record's motion);
2. each move (add one monomial, drop one term, swap one for another) scored by its linearised
   refit; moves tried in the order of their predicted information criterion
   ``n_eff ln(cost) + k ln(n_eff)`` (``n_eff``: the fitting residual's effective sample count,
   recon.regression.criteria.effective_samples: the residual of a model error is correlated);
3. a move is kept when the actual refit lowers that criterion; repeated until no move does.

The fitting samples choose the terms; the held-out samples, which took no part in it, judge the
result: the caller keeps a revision only where it predicts them better, and scores it against the
reference revised the same way, so that a candidate gets no credit for the revision itself.
"""
from __future__ import annotations

import math

import numpy as np

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.candidate_fit import CANDIDATE_FAILURES
from recon.diagnosis.jacobian import fit_jacobian
from recon.diagnosis.settings import DEFAULTS, DiagnosisSettings
from recon.output_error.problem import forward_differences, get_parameter, parameter_scales, set_parameter, term_scale
from recon.output_error.term_selection import CANDIDATES
from recon.regression.criteria import effective_samples


def judged_motion(data: list) -> tuple[float, float]:
    """(rms y, rms y') of the relative displacement of the stage that moves most: the motion a
    term's size is judged at."""
    d = max(data, key=lambda d: float(np.std(d.displacement)))
    y = np.asarray(d.displacement, float)
    return float(np.std(y)) or 1.0, float(np.std(np.gradient(y, d.dt))) or 1.0


def fn_keys(terms) -> list[str]:
    return [f"fn:{t}" for t in terms]


def criterion(cost: float, k: int, n_eff: float) -> float:
    """The information criterion of a fitting cost with ``k`` fn terms (module doc, 2)."""
    return n_eff * math.log(max(cost, 1e-300)) + k * math.log(n_eff)


def revise_terms(fr: rank.FitResult, free: list, keys: list, scales: dict, bounds: dict, data: list,
                 max_nfev: int, settings: DiagnosisSettings = DEFAULTS) -> tuple[rank.FitResult, dict]:
    """(the fit with its fn terms revised, the moves taken) from the fit ``fr``, whose non-fn
    baseline parameters ``free`` and candidate parameters ``keys`` (``scales``, ``bounds``: theirs)
    are refitted beside the terms at every move. Returns ``fr`` itself with no move when none lowers
    the criterion (at most ``settings.revision_steps`` moves, each step trying its
    ``settings.revision_tries`` best predicted). Numerical failures of a trial skip that move."""
    free = [k for k in free if not k.startswith("fn:")]
    y_rms, v_rms = judged_motion(data)
    cur, moves = fr, []
    for _ in range(settings.revision_steps):
        step = _best_moves(cur.model, free, keys, scales, data, y_rms, v_rms, settings.revision_tries, bounds)
        if step is None:
            break
        n_eff, ranked = step
        taken = False
        for _ic, kind, terms, keep, start, term_sc in ranked:
            try:
                trial = rank.fit(start, list(dict.fromkeys(free + fn_keys(keep) + keys)), data,
                                 {**scales, **term_sc}, max_nfev=max_nfev, bounds=bounds)
            except CANDIDATE_FAILURES:
                continue
            if not (math.isfinite(trial.cost_fit) and math.isfinite(trial.mse_held)):
                continue
            n_now = len(cur.model.baseline.fn_m)
            if criterion(trial.cost_fit, len(keep), n_eff) < criterion(cur.cost_fit, n_now, n_eff):
                moves.append({"move": kind, "terms": list(terms)})
                cur, taken = trial, True
                break
        if not taken:
            break
    return cur, {"moves": moves, "terms_before": sorted(fr.model.baseline.fn_m),
                 "terms_after": sorted(cur.model.baseline.fn_m)}


def _best_moves(am: AugmentedModel, free: list, keys: list, scales: dict, data: list, y_rms: float,
                v_rms: float, tries: int, bounds: dict | None = None):
    """(the effective sample count of ``am``'s fitting residual, the moves that lower the
    predicted criterion, the ``tries`` best first, each (criterion, kind, terms, kept terms, start
    model, the kept terms' scales)); None where no finite Jacobian can be taken. A start's
    parameters are held inside their ``bounds``: the linearised step does not know them, and a fit
    started outside its range stays there."""
    present = list(am.baseline.fn_m)
    offered = [t for t in CANDIDATES if t not in present]
    work = am.copy()
    for t in offered:
        work.baseline.fn_m[t] = 0.0
    K = am.baseline.K_m
    term_sc = {f"fn:{t}": term_scale(t, K, y_rms, v_rms) for t in present + offered}
    cols = list(dict.fromkeys(free + fn_keys(present + offered) + keys))
    x0 = np.array([get_parameter(work, k) for k in cols], float)
    sc = parameter_scales(cols, x0, work.baseline.gamma + work.baseline.delta, {**scales, **term_sc})

    def build(p):
        m = work.copy()
        for i, k in enumerate(cols):
            set_parameter(m, k, x0[i] + p[i] * sc[i])
        return m

    thin = rank.own_starts(work, [d.thinned() for d in data])
    p0 = np.zeros(len(cols))
    r0 = rank.fit_residual(work, thin)
    if not np.all(np.isfinite(r0)):
        return None
    jac = fit_jacobian(build, cols, sc, thin, rank.initial_for, rank.fit_scale, work)
    J = jac(p0) if jac is not None else forward_differences(lambda p: rank.fit_residual(build(p), thin), p0)
    if not np.all(np.isfinite(J)):
        return None
    n_stages = max(len([d for d in data if d.fit.any()]), 1)
    c0 = float(r0 @ r0) / n_stages
    n_eff = effective_samples(r0)
    idx = {k: i for i, k in enumerate(cols)}
    fixed_cols = [idx[k] for k in free + keys]
    ic0 = criterion(c0, len(present), n_eff)
    candidates = ([("add", (t,)) for t in offered] + [("drop", (t,)) for t in present]
                  + [("swap", (a, b)) for a in present for b in offered])
    ranked = []
    for kind, terms in candidates:
        out = terms[0] if kind in ("drop", "swap") else None
        keep = [t for t in present if t != out] + ([terms[-1]] if kind in ("add", "swap") else [])
        use = fixed_cols + [idx[f"fn:{t}"] for t in keep]
        p = np.zeros(len(cols))
        rhs = -r0
        if out is not None:       # the dropped term's coefficient to 0
            j = idx[f"fn:{out}"]
            p[j] = -x0[j] / sc[j]
            rhs = rhs - J[:, j] * p[j]
        sol, *_ = np.linalg.lstsq(J[:, use], rhs, rcond=None)
        p[use] = sol
        e = r0 + J @ p
        ic = criterion(float(e @ e) / n_stages, len(keep), n_eff)
        if ic < ic0:
            ranked.append((ic, kind, terms, keep, p))
    ranked.sort(key=lambda r: r[0])

    def start(keep, p):
        m = build(p)
        for t in list(m.baseline.fn_m):
            if t not in keep:
                del m.baseline.fn_m[t]
        for k, (lo, hi) in (bounds or {}).items():
            if k in idx:
                set_parameter(m, k, min(max(get_parameter(m, k), lo), hi))
        return m
    return n_eff, [(ic, kind, terms, keep, start(keep, p), {f"fn:{t}": term_sc[f"fn:{t}"] for t in keep})
                       for ic, kind, terms, keep, p in ranked[:tries]]

"""One catalog candidate fitted as an augmented model: from which start, and the record of its fit.

A candidate (recon.diagnosis.candidates) proposes starts: the source model with its new terms at
a few values. :func:`fit_candidate` chooses among them cheaply (an equation-error step for a term
linear in its first parameter, else a short output-error fit of the new terms alone), fits the
chosen start by output error with the source's free baseline parameters beside the new terms, and
returns a :class:`CandidateFit`. :func:`implausible` says why a fit is not physical: such a fit is
never reported, however well it predicts.

Contract: a fit either returns a CandidateFit that predicts every held-out sample with a finite
error, or raises one of :data:`CANDIDATE_FAILURES` (recorded by the caller, never propagated).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.catalog import CATALOG
from recon.diagnosis.context import DiagnosisContext
from recon.output_error.problem import get_parameter, set_parameter

# numerical failures of one candidate's fit or simulation: recorded, never raised
CANDIDATE_FAILURES = (ArithmeticError, ValueError, np.linalg.LinAlgError)

Z95 = 1.96      # statistical, not a tuned choice: the two-sided 95 % normal quantile of a parameter's interval


@dataclass(frozen=True)
class CandidateFit:
    """A candidate's output-error fit and what it was fitted with."""
    fit: rank.FitResult          # the fitted augmented model and its scores
    keys: list                   # the candidate's own parameters ("x:mu", "fn:y^2", ...), the first its size
    scales: dict                 # {key: typical magnitude} the fit normalises by
    bounds: dict                 # {key: (lo, hi)} the physical range of the candidate's parameters
    free: list = ()              # the baseline parameters fitted beside the candidate's keys
    started_from: str = ""       # the origin its fit started from (references.Origin.name)

    def fitted_keys(self) -> list:
        """Every parameter the fit moved: the free baseline ones, then the candidate's."""
        return list(dict.fromkeys(list(self.free) + list(self.keys)))


def interval95(v: float, se) -> list | None:
    """The 95 % interval of a value with standard error ``se`` (None without a finite one)."""
    if se is None or not math.isfinite(se):
        return None
    return [v - Z95 * se, v + Z95 * se]


def within_bound(am: AugmentedModel, key: str, bounds: dict) -> bool:
    """Whether ``am``'s parameter ``key`` lies inside its bounds (inclusive; unbounded: always)."""
    lo, hi = bounds.get(key, (-np.inf, np.inf))
    return bool(lo <= get_parameter(am, key) <= hi)


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
        iv = interval95(get_parameter(m, k0), fr.stderr[k0])
        if iv is not None and iv[0] <= 0.0 <= iv[1]:
            why.append(f"the 95 % interval of {k0.split(':', 1)[-1]} [{iv[0]:.4g}, {iv[1]:.4g}] holds 0")
    return why


def fit_candidate(cid: str, cand, src: rank.FitResult, free: list, step_keys: list, dctx: DiagnosisContext,
                  started_from: str = "") -> CandidateFit:
    """Candidate ``cid`` (catalog entry ``cand``) fitted from the fit ``src`` with the baseline keys
    ``free`` beside its own (``step_keys``: those an equation-error step may move). A candidate with
    a discrete shape parameter the fit cannot move (``fit_each``: the contact's side) is fitted once
    per value and the fit with the lower fitting cost is kept: a start that ranks first by output
    error can still end worse than a full fit from the other value."""
    if not cand.fit_each:
        return fit_from(cid, cand, src, free, step_keys, cand.starts, dctx, started_from)
    values = sorted({m.extras[cand.fit_each] for m, _, _, _ in cand.starts(src.model.baseline, dctx.located)})
    got, err = [], None
    for v in values:
        def group(base, located, v=v):
            return [s for s in cand.starts(base, located) if s[0].extras[cand.fit_each] == v]
        try:
            got.append(fit_from(cid, cand, src, free, step_keys, group, dctx, started_from))
        except CANDIDATE_FAILURES as exc:
            err = exc
    if not got:
        raise err
    return min(got, key=lambda g: g.fit.cost_fit if math.isfinite(g.fit.cost_fit) else math.inf)


def fit_from(cid: str, cand, src: rank.FitResult, free: list, step_keys: list, make_starts,
             dctx: DiagnosisContext, started_from: str = "") -> CandidateFit:
    """:func:`fit_candidate` from the starts ``make_starts(baseline, located)`` makes: the chosen
    start fitted with ``free`` and the candidate's keys; refitted from the candidate's admissible
    starts when it ends outside the physical range."""
    data, max_nfev = dctx.data, dctx.max_nfev
    starts = starts_from(cid, src, make_starts, dctx)
    if cand.column is not None:     # linear in its first parameter: equation-error step per start
        m, keys, sc, b = equation_stepped_start(cand, starts, step_keys, dctx)
    elif len(starts) > 1:           # screen the starts with only the new terms free
        m, keys, sc, b = screen_starts(cand, starts, dctx)
    else:
        m, keys, sc, b = starts[0]
    fr = rank.fit(m, list(dict.fromkeys(free + keys)), data, sc, max_nfev=max_nfev, bounds=b)
    if cand.admissible_starts is not None and implausible(cid, fr, src.model, data, intervals=False):
        # the fit ended outside the physical range (hysteresis: a negative alpha):
        # fitted again from starts inside it, kept if it ends inside
        m2, keys2, sc2, b2 = screen_starts(cand, starts_from(cid, src, cand.admissible_starts, dctx), dctx)
        fr2 = rank.fit(m2, list(dict.fromkeys(free + keys2)), data, sc2, max_nfev=max_nfev, bounds=b2)
        if math.isfinite(fr2.mse_held) and not implausible(cid, fr2, src.model, data, intervals=False):
            fr, keys, sc, b = fr2, keys2, sc2, b2
    if not (math.isfinite(fr.mse_held) and fr.n_held > 0):
        raise FloatingPointError(f"held-out mean-square error is {fr.mse_held} on {fr.n_held} samples")
    return CandidateFit(fit=fr, keys=keys, scales=sc, bounds=b, free=list(free), started_from=started_from)


def starts_from(cid: str, src: rank.FitResult, make, dctx: DiagnosisContext) -> list:
    """The starts (model, keys, scales, bounds) ``make`` proposes on ``src``'s baseline, each keeping
    the extras ``src`` already holds and naming ``cid`` as added."""
    out = make(src.model.baseline, dctx.located)
    for m, _, _, _ in out:
        for k, v in src.model.extras.items():
            m.extras.setdefault(k, v)
        m.added = list(src.model.added) + [cid]
    return out


def screen_starts(cand, starts: list, dctx: DiagnosisContext) -> tuple:
    """(model, keys, scales, bounds) of the best of ``starts`` after a short fit of the new terms
    (the candidate's first ``screen_keys`` of them)."""
    n = dctx.settings.start_screen_nfev
    fits = [rank.fit(m, keys[:cand.screen_keys], dctx.data, sc, max_nfev=n, bounds=b, scored=False)
            for m, keys, sc, b in starts]
    i = int(np.argmin([f.cost_fit for f in fits]))
    return (fits[i].model,) + tuple(starts[i][1:])


def equation_stepped_start(cand, starts: list, step_keys: list, dctx: DiagnosisContext) -> tuple:
    """(model, keys, scales, bounds) to fit a candidate linear in its first parameter from: each
    start stepped by equation error (``step_keys`` and the term's first key), the step chosen by
    output error, and a step across the term's physical bound brought back inside it."""
    data = dctx.data
    stepped = [rank.equation_step(m, step_keys, keys[0], cand.column, dctx.derivs, data, dctx.settings)
               for m, keys, _, _ in starts]
    if cand.screen_output and len(starts) > 1:
        i = rank_by_output_error(starts, stepped, dctx)
    else:
        i = first_step_inside_bound(starts, stepped, dctx)
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
        tried = [rank.fit(mm, [keys[0], "c_m", "k_m"], data, sc, max_nfev=dctx.settings.output_screen_nfev,
                          bounds=b, scored=False) for mm in tries]
        m = tried[int(np.argmin([f.cost_fit for f in tried]))].model
    return m, keys, sc, b


def short_term_fit(m: AugmentedModel, start: tuple, dctx: DiagnosisContext) -> rank.FitResult:
    """The short output-error fit, from ``m``, of the first key of ``start`` (model, keys, scales,
    bounds) alone, with that start's scales and bounds: how :func:`rank_by_output_error` judges
    where a start, or an equation step, leads."""
    _, keys, sc, b = start
    return rank.fit(m, [keys[0]], dctx.data, sc, max_nfev=dctx.settings.output_screen_nfev, bounds=b, scored=False)


def rank_by_output_error(starts: list, stepped: list, dctx: DiagnosisContext) -> int:
    """The start to fit when the starts differ in a fixed shape parameter (friction's v0): the
    equation residual cannot rank them (differentiation noise), a short output-error fit of the new
    term from the source model can (the equation step's increments of the baseline's terms carry
    the same noise). The equation step itself is kept where its output error, after the same short
    fit of the term, is lower still: where the source's damping holds the effect, the term alone
    fitted from the source stays at 0 while the step moves the damping and the term together.
    ``stepped`` is updated in place."""
    data = dctx.data
    scr = []
    for start in starts:
        mm, keys, sc, _ = start
        mm = mm.copy()
        if get_parameter(mm, keys[0]) == 0.0:      # a start that gives the term a size keeps it
            set_parameter(mm, keys[0], sc[keys[0]])
        scr.append(short_term_fit(mm, start, dctx))
    i = int(np.argmin([f.cost_fit for f in scr]))
    step_cost = [rank.fit_cost(mm, data) if within_bound(mm, starts[j][1][0], starts[j][3]) else math.inf
                 for j, (mm, _) in enumerate(stepped)]
    j = int(np.argmin(step_cost))
    if math.isfinite(step_cost[j]):
        # the best step is judged where the same short fit leads from it, as the starts are: its own
        # output error ranks it by where it starts, and a step that lands in the effect's basin can
        # start above a start that a short fit of the term alone takes to a shallow basin nearby
        try:
            sf = short_term_fit(stepped[j][0], starts[j], dctx)
        except CANDIDATE_FAILURES:
            sf = None
        if sf is not None and math.isfinite(sf.cost_fit) and sf.cost_fit < step_cost[j]:
            stepped[j], step_cost[j] = (sf.model, stepped[j][1]), sf.cost_fit
    if not step_cost[j] < scr[i].cost_fit:
        stepped[i] = (scr[i].model, 0.0)
        return i
    return j


def first_step_inside_bound(starts: list, stepped: list, dctx: DiagnosisContext) -> int:
    """The start to fit among equation-stepped ones: a step that puts the new term inside its
    physical bound first (a step across it says that start is wrong, though the starts' equation
    residuals differ by differentiation noise only), and among those the one whose output error is
    lowest, after a short fit of the new terms where the starts differ in a fitted shape parameter
    (the contact's gap: a step ranks them by where they start, a short fit by where they lead).
    A step of a term free of bounds is kept only where its output error is lower than no step's
    (differentiation errors can point it the wrong way); a bounded term is not reset, since its
    bound is where a fit would leave it. ``stepped`` is updated in place."""
    data = dctx.data
    inside = [j for j, (mm, _) in enumerate(stepped) if within_bound(mm, starts[j][1][0], starts[j][3])]
    if len(inside) > 1:
        cost = {j: rank.fit_cost(stepped[j][0], data) for j in inside}
        if len(starts[inside[0]][1]) > 1:
            for j in inside:
                _, kj, scj, bj = starts[j]
                try:
                    short = rank.fit(stepped[j][0], kj, data, scj, max_nfev=dctx.settings.shape_screen_nfev,
                                     bounds=bj, scored=False)
                except CANDIDATE_FAILURES:
                    continue    # that start is ranked by its step alone
                if math.isfinite(short.cost_fit) and short.cost_fit < cost[j]:
                    stepped[j], cost[j] = (short.model, stepped[j][1]), short.cost_fit
        i = min(inside, key=cost.get)
    else:
        i = min(inside or range(len(stepped)), key=lambda j: stepped[j][1])
    lo_, hi_ = starts[i][3].get(starts[i][1][0], (-np.inf, np.inf))
    if (not (np.isfinite(lo_) or np.isfinite(hi_))
            and rank.fit_cost(stepped[i][0], data) > rank.fit_cost(starts[i][0], data)):
        stepped[i] = (starts[i][0].copy(), stepped[i][1])
    return i

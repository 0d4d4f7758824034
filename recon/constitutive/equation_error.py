"""The agent-model regression of a force law: the library's joint form with the force as Fn.

With the displacement imposed, Fn = F - f0 - c x' - K x = fn + zn (K = k + alpha), and the
agent model of recon.library.agent holds as it is (y = x):

    s Fn' = sum_j a_j s phi_j' + lambda sum_j a_j y' phi_j - lambda alpha y y' - lambda y' Fn

Written for the measured force (Fn' = F' - c y'' - K y') it is linear in its coefficients,
so c, K and f0 need no separate linear step:

    s F' = c s y'' + K s y' + sum_j a_j s phi_j' + sum_j (lambda a_j) y' phi_j
           + (lambda k) y y' - lambda y' F + (lambda f0) y' + (lambda c) y'^2

These are the columns of ``AgentLibrary(order, "joint", linear_correction=True)`` built with
Fn = F (``s*ddy`` -> c, ``s*dy`` -> K, ``y*dy`` -> lambda k, ``dy*Fn`` -> -lambda, ``dy^2`` ->
lambda c) plus one column y' (lambda f0). ``recon.steps.bouc_wen.extract`` then gives lambda,
fn and alpha = K - k exactly as for a structure (the ``s*dy`` column plays the role of the
linear step's stiffness error). Damping (``s*ddy``, ``dy^2``) and offset (``dy``) are offered
as groups to the sparse selector (a quasi-static test has no viscous force), the rest of the
core is always in.

Inertia (``fit_mass``): a term m x'' adds m s x''' and (lambda m) x' x'' to the right side,
two more columns offered as a group (x''' from the same filter).

Rows: the library's kernel needs the sign of z where y and y' agree. A component test need
not be centred on x = 0, so the first pass clusters on the displacement about its mid-range
(recon.library.clustering), and a second pass on the sign of z implied by the first pass's
law (rows where z and x' share their sign, |z| above a tenth of its range); delta comes from
the rows where they differ (recon.steps.bouc_wen.estimate_delta).
"""
from __future__ import annotations

import numpy as np

from recon.constitutive.law import ConstitutiveLaw
from recon.constitutive.signals import ComponentSignals
from recon.library.agent import AgentLibrary, dphi, phi
from recon.library import monomials
from recon.library.clustering import cluster
from recon.regression.criteria import filter_correlation_length
from recon.regression.sparse import GroupedSparseSelector
from recon.steps.bouc_wen import HysteresisParams, estimate_delta, extract, fn_values, project_lambda
from shakerlab.errors import UserFacingError



def regress(sig: ComponentSignals, h: np.ndarray, order: int, n_folds: int, fit_mass: bool = False):
    """One pass of the sparse regression on the rows ``h != 0`` (s = h). Returns (law, info).
    ``fit_mass``: an inertia term m x'' too, columns s x''' (m) and x' x'' (lambda m), a group."""
    y, dy, ddy, F, dF = sig.y, sig.dy, sig.ddy, sig.F, sig.dF
    lib = AgentLibrary(order, "joint", linear_correction=True)
    theta, target = lib.build(y, dy, ddy, F, dF, h)
    mask = lib.rows(h)
    extra = [dy[mask]] + ([(h[mask] * sig.dddy[mask]), dy[mask] * ddy[mask]] if fit_mass else [])
    theta = np.column_stack([theta] + extra)
    n_lib = len(lib.columns)
    if theta.shape[0] < 4 * theta.shape[1]:
        raise UserFacingError(f"only {theta.shape[0]} samples where the force and the velocity agree in sign for "
                              f"{theta.shape[1]} library columns: record more loops or lower --library-order")
    names = lib.names + ["dy (offset)"] + (["s*dddy (mass)", "dy*ddy"] if fit_mass else [])
    idx = {c.name: k for k, c in enumerate(lib.columns)}
    k_c, k_K, k_c2, k_f0 = idx["s*ddy"], idx["s*dy"], idx["dy^2"], n_lib
    groups, core = lib.groups()
    core = [k for k in core if k not in (k_c, k_c2)]
    groups = groups + [[k_c, k_c2], [k_f0]] + ([[n_lib + 1, n_lib + 2]] if fit_mass else [])
    selector = GroupedSparseSelector(groups, core, n_folds=n_folds, corr_len=filter_correlation_length(sig.choice))
    sp = selector.fit(theta, target)
    hp = extract(lib, sp.coef[:n_lib], sp.stderr[:n_lib], sp.support[:n_lib])
    hp.info.pop("linear_step_correction", None)
    has_c = bool(sp.support[k_c] or sp.support[k_c2])
    has_f0 = bool(sp.support[k_f0])
    c = float(sp.coef[k_c]) if sp.support[k_c] else (float(sp.coef[k_c2]) / hp.lam if has_c else 0.0)
    K = float(sp.coef[k_K])
    f0 = float(sp.coef[k_f0]) / hp.lam if has_f0 else 0.0
    m = 0.0
    if fit_mass and (sp.support[n_lib + 1] or sp.support[n_lib + 2]):
        m = float(sp.coef[n_lib + 1]) if sp.support[n_lib + 1] else float(sp.coef[n_lib + 2]) / hp.lam
    info = {"library": dict(zip(names, (float(v) for v in sp.coef))), "sparse_regression": sp.summary(),
            "damping_selected": has_c, "offset_selected": has_f0, "rows": int(mask.sum()),
            "equation_error": {"lambda": hp.lam, "alpha": hp.alpha, "c": c, "K": K, "f0": f0, "fn": dict(hp.fn),
                               **({"mass": m} if fit_mass else {})}}
    s = h[mask].astype(float)
    Fi, dFi = F, dF
    if m:   # the inertia force stays at the regression's m in the refit (the polish fits it)
        Fi, dFi = F - m * ddy, dF - m * sig.dddy
    hp, c, K, f0 = refit(hp, y[mask], dy[mask], ddy[mask], Fi[mask], dFi[mask], s, c, K, f0, has_c, has_f0)
    Fn = Fi - f0 - c * dy - K * y
    dFn = dFi - c * ddy - K * dy
    hp = estimate_delta(hp, y, dy, ddy, Fn, dFn, h)
    info["hysteresis"] = hp.info
    law = ConstitutiveLaw(c=c, k=K - hp.alpha, alpha=hp.alpha, gamma=hp.gamma, delta=hp.delta, f0=f0, fn=dict(hp.fn),
                          mass=m)
    return law, info, sp


def refit(params: HysteresisParams, y, dy, ddy, F, dF, s, c, K, f0, has_c: bool, has_f0: bool):
    """Structured refit with the pattern fixed: for a fixed lambda the equation

        s F' + lambda y' F = sum_j a_j (s phi_j' + lambda y' phi_j) - (lambda alpha) y y'
                             + c (s y'' + lambda y'^2) + K (s y' + lambda y y') + f0 lambda y'

    is linear in (a_j, lambda alpha, c, K, f0), so only lambda is searched
    (recon.steps.bouc_wen.project_lambda; its input-gain slot carries f0). A damping or offset
    the selector left out stays 0 (its column is zero)."""
    terms = [monomials.parse(k) for k in params.fn]
    P0 = [s * dphi(y, dy, ddy, p, r) for p, r in terms]
    P1 = [dy * phi(y, dy, p, r) for p, r in terms]
    zero = np.zeros_like(y)

    def system(lam):
        cols = [a0 + lam * a1 for a0, a1 in zip(P0, P1)] + [-y * dy]
        cols += [s * ddy + lam * dy * dy if has_c else zero, s * dy + lam * y * dy]
        cols.append(lam * dy if has_f0 else zero)
        return np.column_stack(cols), s * dF + lam * dy * F

    return project_lambda(params, system, c, K, f0, fit_linear=True, fit_g=True, alpha_sign=1.0, relative=False,
                          form="constitutive")


def z_sign_clusters(sig: ComponentSignals, law: ConstitutiveLaw, z_margin: float) -> np.ndarray:
    """h = sign(x') where the hysteretic force implied by ``law`` has the sign of x' (and |z| is above
    ``z_margin`` of half its 1-99 % range: ConstitutiveSettings.z_margin), else 0."""
    z = sig.F - law.f0 - law.c * sig.dy - law.k * sig.y - fn_values(law.fn, sig.y, sig.dy) - law.mass * sig.ddy
    s = np.sign(sig.dy)
    lo, hi = np.percentile(z, [1, 99])
    margin = z_margin * 0.5 * (hi - lo)
    return np.where((np.sign(z) == s) & (np.abs(z) > margin), s, 0.0).astype(int)


def equation_error(sig: ComponentSignals, order: int = 5, n_folds: int = 5, passes: int = 2, fit_mass: bool = False,
                   *, z_margin: float):
    """The law from the agent-model regression (``passes`` clusterings, module docstring;
    ``fit_mass``: with an inertia term, ``sig`` must carry x'''). Returns (law, info, sparse fit
    of the last pass; ``z_margin``: of the z-sign clustering, :func:`z_sign_clusters`)."""
    centre = 0.5 * (float(np.max(sig.y)) + float(np.min(sig.y)))
    h = cluster(sig.y - centre, sig.dy)
    history = []
    law = info = sp = None
    for k in range(passes):
        try:
            law_k, info_k, sp_k = regress(sig, h, order, n_folds, fit_mass)
        except UserFacingError:
            if law is None:
                raise
            break
        history.append({"clusters": "displacement" if k == 0 else "z sign", "rows": info_k["rows"],
                        "parameters": law_k.parameters()})
        law, info, sp = law_k, info_k, sp_k
        if not (law.alpha > 0 and law.lam > 0):
            break
        h = z_sign_clusters(sig, law, z_margin)
    info["passes"] = history
    return law, info, sp

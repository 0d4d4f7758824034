"""From library coefficients to physical parameters: lambda, fn, alpha, delta, gamma.

- lambda: either directly from the y'*Fn column (-coefficient), or by the
  paper's Eq. 24, least squares over the pairs (lambda a_j, a_j) of the terms
  whose both columns survived. The estimate with the smaller propagated
  standard error (from the regression's covariance) is used; both are reported.
- fn: in the joint form a_j is the coefficient of s*d(phi_j)/dt (or, if only
  its partner survived, (lambda a_j)/lambda). In the paper's AB form the
  non-pure a_j come from the psi block and the pure-y ones by back-substitution
  from m = q down to 2:  a_{y^q} = xi_{q,0}/lambda,
  a_{y^m} = (xi_{m,0} - (m+1) a_{y^(m+1)})/lambda.
- alpha = -coef(y y')/lambda (joint) or (2 a_{y^2} - coef(y y'))/lambda (AB).
- structured refit: with the sparsity pattern fixed, (a_j, lambda, alpha) are
  refit jointly on the same equation. For a fixed lambda the equation is linear
  in (a_j, lambda*alpha), so only lambda is searched (variable projection).
- delta from the h = 0 samples: z = alpha y + Fn - fn, zn' = Fn' - fn',
  l = zn' + lambda |y'| z = delta (|y'| z - y' |z|); gamma = lambda - delta.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from recon.library import monomials
from recon.library.agent import AgentLibrary, dphi, phi
from recon.regression.sparse import scaled_lstsq
from shakerlab.errors import EstimateRefused, UserFacingError


@dataclass
class HysteresisParams:
    lam: float
    alpha: float
    fn: dict                          # monomial name -> coefficient
    delta: float = float("nan")
    gamma: float = float("nan")
    info: dict = field(default_factory=dict)


def extract(lib: AgentLibrary, coef: np.ndarray, stderr: np.ndarray, support: np.ndarray) -> HysteresisParams:
    cols = lib.columns
    by_role = {}
    for k, c in enumerate(cols):
        by_role.setdefault(c.role, {})[(c.p, c.r)] = k
    info = {}
    lam_col = cols.index(next(c for c in cols if c.role in ("lam", "yFn")))
    lam_direct = -coef[lam_col] if support[lam_col] else np.nan
    se_direct = stderr[lam_col] if support[lam_col] else np.inf

    pairs_a, pairs_b, se_a, se_b = [], [], [], []
    if lib.form == "joint":
        for pr, ka in by_role["a"].items():
            kb = by_role["lam_a"][pr]
            if support[ka] and support[kb]:
                pairs_a.append(coef[ka]); pairs_b.append(coef[kb])
                se_a.append(stderr[ka]); se_b.append(stderr[kb])
    else:
        for pr, ka in by_role["psi"].items():
            kb = by_role["xi"].get(pr)
            if kb is not None and support[ka] and support[kb]:
                pairs_a.append(coef[ka]); pairs_b.append(coef[kb])
                se_a.append(stderr[ka]); se_b.append(stderr[kb])
    lam_pairs, se_pairs = np.nan, np.inf
    if pairs_a:
        a, b = np.array(pairs_a), np.array(pairs_b)
        S = float(a @ a)
        lam_pairs = float(a @ b) / S
        se_pairs = float(np.sqrt(np.sum(a * a * (np.array(se_b) ** 2 + lam_pairs ** 2 * np.array(se_a) ** 2)))) / S
    info.update(lambda_direct=float(lam_direct), lambda_direct_se=float(se_direct),
                lambda_eq24=float(lam_pairs), lambda_eq24_se=float(se_pairs))
    if np.isnan(lam_direct) and np.isnan(lam_pairs):
        raise UserFacingError("the sparse regression found no hysteresis (no y'*Fn term and no "
                              "(lambda a_j, a_j) pair): the nonlinear stage does not excite the loop")
    if se_pairs < se_direct:
        lam, info["lambda_source"] = lam_pairs, "eq24_pairs"
    else:
        lam, info["lambda_source"] = lam_direct, "dy*Fn column"

    fn = {}
    if lib.form == "joint":
        for pr, ka in by_role["a"].items():
            kb = by_role["lam_a"][pr]
            if support[ka]:
                fn[pr] = coef[ka]
            elif support[kb]:
                fn[pr] = coef[kb] / lam
        kyy = next(iter(by_role["lam_alpha"].values()))
        alpha = -coef[kyy] / lam
        if "lin" in by_role:
            # y y' also carries lambda*dK from the linear step's error; dK is -coef(s y')
            k_dy = by_role["lin"][(0, 1)]
            alpha = -(coef[kyy] - lam * coef[k_dy]) / lam
            info["linear_step_correction"] = {"dK_m": float(-coef[k_dy]),
                                              "dc_m": float(-coef[by_role["lin"][(0, 0)]])}
        if "const" in by_role:
            # Fn as built is off by a constant d: its coefficient is lambda d (AgentLibrary)
            info["constant_error"] = float(coef[by_role["const"][(0, 0)]] / lam)
    else:
        for pr, ka in by_role["psi"].items():
            kb = by_role["xi"].get(pr)
            if support[ka]:
                fn[pr] = coef[ka]
            elif kb is not None and support[kb]:
                fn[pr] = coef[kb] / lam
        # back-substitution for the pure-y terms
        # a_{y^m} = (xi_{m,0} - (m+1) a_{y^(m+1)}) / lambda, m = q..2; a term is kept when its
        # share lambda*a_{y^m} of the column is significant (> 3 standard errors of the column)
        a_next = 0.0
        for m in range(lib.order, 1, -1):
            k = by_role["xi"][(m, 0)]
            xi = coef[k] if support[k] else 0.0
            a_m = (xi - (m + 1) * a_next) / lam
            if support[k] and abs(lam * a_m) > 3 * stderr[k]:
                fn[(m, 0)] = a_m
            else:
                a_m = 0.0
            a_next = a_m
        kyy = next(iter(by_role["yy"].values()))
        alpha = (2 * fn.get((2, 0), 0.0) - coef[kyy]) / lam
    fn = {monomials.name(*pr): float(v) for pr, v in sorted(fn.items(), key=lambda kv: (sum(kv[0]), kv[0][1]))}
    return HysteresisParams(lam=float(lam), alpha=float(alpha), fn=fn, info=info)


def refit(params: HysteresisParams, y, dy, ddy, dddy, u, du, s, c_m, K_m, g, fit_g: bool,
          fit_linear: bool = True):
    """Joint refit with the sparsity pattern fixed (variable projection on lambda).

    Equation (rows with s = +-1, multiplied by s), Fn = g u - y'' - c y' - K y:
        s Fn' + lambda y' Fn = sum_j a_j (s phi_j' + lambda y' phi_j) - lambda alpha y y'
    For a fixed lambda it is linear in (a_j, lambda*alpha) and, with ``fit_linear``, in
    (c, K[, g]) too, so only lambda is searched. Returns (params, c, K, g).
    """
    terms = [monomials.parse(k) for k in params.fn]
    P0 = [s * dphi(y, dy, ddy, p, r) for p, r in terms]
    P1 = [dy * phi(y, dy, p, r) for p, r in terms]

    def system(lam):
        cols = [a0 + lam * a1 for a0, a1 in zip(P0, P1)] + [-y * dy]
        T = -s * dddy - lam * dy * ddy
        gu = s * du + lam * dy * u
        if fit_linear:
            cols += [s * ddy + lam * dy * dy, s * dy + lam * y * dy]
        else:
            T = T - c_m * (s * ddy + lam * dy * dy) - K_m * (s * dy + lam * y * dy)
        if fit_g:
            cols.append(-gu)
        else:
            T = T + g * gu
        return np.column_stack(cols), T

    return project_lambda(params, system, c_m, K_m, g, fit_linear, fit_g, alpha_sign=1.0, relative=False)


def project_lambda(params: HysteresisParams, system, c_m, K_m, g, fit_linear: bool, fit_g: bool,
                   alpha_sign: float, relative: bool, form: str | None = None):
    """Variable projection on lambda for the structured refits (pointwise and weak).

    ``system(lam)`` returns (A, b) of a problem linear in [a_j (pattern order),
    alpha_sign*lambda*alpha, (c, K if fit_linear), (g if fit_g)]; lambda is searched over
    [0.2, 5] x its start, minimising the residual (``relative``: divided by |b|^2, for rows
    whose right side depends on lambda). Returns (params, c, K, g)."""
    def solve(lam):
        A, b = system(lam)
        x, rss = scaled_lstsq(A, b)
        return (rss / float(b @ b) if relative else rss), x

    lam0 = params.lam
    lo, hi = sorted((0.2 * lam0, 5.0 * lam0))
    res = minimize_scalar(lambda L: solve(L)[0], bounds=(lo, hi), method="bounded",
                          options={"xatol": 1e-9 * abs(lam0)})
    lam = float(res.x)
    _, x = solve(lam)
    nf = len(params.fn)
    fn = {k: float(v) for k, v in zip(params.fn, x[:nf])}
    alpha = float(alpha_sign * x[nf] / lam)
    i = nf + 1
    if fit_linear:
        c_m, K_m = float(x[i]), float(x[i + 1])
        i += 2
    if fit_g:
        g = float(x[i])
    info = dict(params.info)
    info["before_refit"] = {"lambda": params.lam, "alpha_m": params.alpha, "fn_m": dict(params.fn)}
    info["refit"] = {"linear_terms_refit": bool(fit_linear), "lambda_bounds": [lo, hi]}
    if form:
        info["refit"]["form"] = form
    return HysteresisParams(lam=lam, alpha=alpha, fn=fn, info=info), c_m, K_m, g


def term_contributions(fn: dict, K: float, y, dy) -> dict:
    """rms of each fn term over (y, y') relative to the rms of the elastic force K y (a term below
    EstimatorTuning.negligible of it is dropped after the polish: the SDOF pipeline and chains;
    ConstitutiveSettings.negligible for a force law)."""
    ref = float(np.sqrt(np.mean((K * y) ** 2))) or 1.0
    out = {}
    for name, a in fn.items():
        p, r = monomials.parse(name)
        out[name] = float(np.sqrt(np.mean((a * phi(y, dy, p, r)) ** 2))) / ref
    return out


def hysteretic_share(model, t, u) -> float:
    """rms of ``model``'s hysteretic force z over the rms of its elastic force K y, simulated from
    rest on the input ``u`` (0 for a model without hysteresis; inf when the simulation is not finite)."""
    if model.alpha_m == 0.0 and model.gamma == 0.0 and model.delta == 0.0:
        return 0.0
    y, _, z = model.simulate(t, u)
    ref = float(np.sqrt(np.mean((model.K_m * y) ** 2)))
    share = float(np.sqrt(np.mean(z ** 2))) / ref if ref > 0 else math.inf
    return share if math.isfinite(share) else math.inf


def fn_values(fn: dict, y, dy):
    out = np.zeros_like(y)
    for k, a in fn.items():
        p, r = monomials.parse(k)
        out = out + a * phi(y, dy, p, r)
    return out


def fn_derivative(fn: dict, y, dy, ddy):
    out = np.zeros_like(y)
    for k, a in fn.items():
        p, r = monomials.parse(k)
        out = out + a * dphi(y, dy, ddy, p, r)
    return out


def estimate_delta(params: HysteresisParams, y, dy, ddy, Fn, dFn, h) -> HysteresisParams:
    mask = h == 0
    z = params.alpha * y + Fn - fn_values(params.fn, y, dy)
    dzn = dFn - fn_derivative(params.fn, y, dy, ddy)
    l = (dzn + params.lam * np.abs(dy) * z)[mask]
    r = (np.abs(dy) * z - dy * np.abs(z))[mask]
    rr = float(r @ r)
    if rr == 0 or mask.sum() < 10:
        raise EstimateRefused("no samples where y' and z have opposite signs: delta cannot be identified "
                              "(the nonlinear stage must cycle through the whole loop)")
    delta = float(r @ l) / rr
    info = dict(params.info)
    info["delta_samples"] = int(np.count_nonzero(r))
    return HysteresisParams(lam=params.lam, alpha=params.alpha, fn=params.fn, delta=delta,
                            gamma=params.lam - delta, info=info)

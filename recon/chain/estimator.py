"""Multi-degree-of-freedom chains: the agent model per layer in relative coordinates.

Chain (see recon/chain/model.py): masses x_1..x_n, element i between x_i and x_(i+1),
element n to the ground, y_i = x_i - x_(i+1), y_n = x_n, forces f_j on the masses.
Summing the equations of masses 1..i, the element force of layer i appears alone:

    sum_{j<=i} m_j x_j'' + E_i(y_i, y_i', z_i) = U_i,      U_i = sum_{j<=i} f_j

Divided by m_i it is the SDOF equation of layer i with extra inputs:

    y_i'' + c y_i' + K y_i + Fn_i = w_i,   w_i = g U_i - sum_{j<i} r_j x_j'' - x_(i+1)''

with g = 1/m_i, r_j = m_j/m_i (x_(n+1) = 0). Linear step per layer (stage 'linear'):
least squares of x_i'' on (-x_j'' (j < i), -y_i', -y_i, U_i). Nonlinear step: the core's
agent model (recon.library.agent / optimizers / hysteresis) on (y_i, y_i', Fn_i) with u = w_i,
then the core's structured refit and delta.

Layers without hysteresis: the agent model's premise (y y' and y' Fn columns) is then
empty, lambda comes out at the noise level. A layer is reported hysteretic only when
lambda exceeds five standard errors and lambda, alpha > 0 after the refit; otherwise it
falls back to a plain sparse regression of Fn on the monomials (the core selector, every
monomial its own group, no forced columns) and alpha = gamma = delta = 0 are reported.
No hysteresis is ever invented.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from recon.chain.model import ChainModel, ChainRun, ChainStage
from recon.differentiation import choose_window, derivatives
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.library import monomials
from recon.library.agent import AgentLibrary, phi
from recon.library.clustering import cluster
from recon.output_error.problem import DIVERGED_RESIDUAL, FD_STEP, parameter_scales
from recon.regression.criteria import filter_correlation_length
from recon.regression.sparse import GroupedSparseSelector
from recon.steps.bouc_wen import HysteresisParams, estimate_delta, extract, refit, term_contributions
from recon.validation import nrmse
from recon.weak.path import fit_path, path_width
from recon.weak.segments import WeakLayer, smoothed_noise
from shakerlab.errors import UserFacingError


@dataclass
class LayerResult:
    index: int
    c_m: float
    k_m: float
    alpha_m: float
    gamma: float
    delta: float
    inv_m: float
    fn_m: dict
    mass_ratios: list
    hysteresis: bool
    info: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("c_m", "k_m", "alpha_m", "gamma", "delta", "inv_m", "fn_m",
                                              "mass_ratios", "hysteresis")} | {"layer": self.index + 1}


@dataclass
class ChainResult:
    layers: list
    model: ChainModel
    validation: dict
    timings: dict

    def to_dict(self) -> dict:
        return {"layers": [L.to_dict() for L in self.layers], "validation": self.validation,
                "timings_s": self.timings,
                "convention": "layer i per unit mass of mass i: y_i = x_i - x_(i+1), inv_m = 1/m_i, "
                              "mass_ratios[j] = m_j/m_i for j < i"}


def _derivs(stage: ChainStage, deriv: int, for_regression: bool):
    ch = choose_window({f"x{i + 1}": x for i, x in enumerate(stage.x)}, stage.dt, deriv=deriv,
                       for_regression=for_regression)
    X = [derivatives(x, stage.dt, ch.window, ch.order, deriv) for x in stage.x]
    F = [derivatives(f, stage.dt, ch.window, ch.order, 1) if np.any(f) else [f, np.zeros_like(f)]
         for f in stage.f]
    half = ch.window // 2
    sl = slice(half, stage.t.size - half)
    X = [[a[sl] for a in d] for d in X]
    F = [[a[sl] for a in d] for d in F]
    return X, F, ch


def _rel(X, i, d):
    n = len(X)
    return X[i][d] - X[i + 1][d] if i < n - 1 else X[i][d]


def linear_layer(X, F, i: int, stage_name: str = "linear"):
    """(c_m, K_m, inv_m, mass ratios, condition number) of layer i."""
    U = sum(F[j][0] for j in range(i + 1))
    cols = [-X[j][2] for j in range(i)] + [-_rel(X, i, 1), -_rel(X, i, 0), U]
    A = np.column_stack(cols)
    b = X[i][2]
    norms = np.sqrt(np.sum(A * A, axis=0))
    if np.any(norms == 0):
        raise UserFacingError(f"stage {stage_name!r}, layer {i + 1}: a linear-step column is zero "
                              "(no force reaches this layer?)")
    sv = np.linalg.svd(A / norms, compute_uv=False)
    cond = float(sv[0] / sv[-1])
    if cond > 1e8:
        raise UserFacingError(f"stage {stage_name!r}, layer {i + 1}: rank-deficient linear step (condition "
                              f"number {cond:.3g}); excite with broadband forces")
    x, *_ = np.linalg.lstsq(A / norms, b, rcond=None)
    x = x / norms
    return float(x[i]), float(x[i + 1]), float(x[i + 2]), [float(v) for v in x[:i]], cond


def _plain_fn(y, dy, Fn, order, n_folds, corr_len):
    """No-hysteresis fallback: sparse regression Fn = sum a_j phi_j (core selector)."""
    terms = monomials.up_to(order)
    A = np.column_stack([phi(y, dy, p, r) for p, r in terms])
    sp = GroupedSparseSelector([[k] for k in range(len(terms))], [], n_folds=n_folds,
                               corr_len=corr_len).fit(A, Fn)
    return {monomials.name(*terms[k]): float(sp.coef[k]) for k in np.flatnonzero(sp.support)}, sp


def _path_layer(nst: ChainStage, ch, i: int, ratios: list, g: float, y, dy, c, K, hp, order: int,
                tuning: EstimatorTuning):
    """The weak path form (recon/weak_path.py) on layer i of a chain: D = x_i + sum_{j<i} r_j x_j,
    F = U_i = sum_{j<=i} f_j, y = x_i - x_(i+1); y, y' smoothed (trimmed like ``y``, ``dy``).
    Returns (HysteresisParams, c, K)."""

    n = nst.x.shape[0]
    half = ch.window // 2
    sl = slice(half, nst.t.size - half)
    x = [xx[sl] for xx in nst.x]
    D = x[i] + sum(r * x[j] for j, r in enumerate(ratios))
    U = sum(nst.f[j][sl] for j in range(i + 1))
    y_raw = x[i] - x[i + 1] if i < n - 1 else x[i]
    names = [f"x{i + 1}"] + ([f"x{i + 2}"] if i < n - 1 else [])
    choice = {"window": ch.window, "order": ch.order, "noise_level": {k: ch.noise_level[k] for k in names}}
    L = WeakLayer(dt=nst.dt, y_raw=y_raw, D_raw=D, y=y, dy=dy, Rdd=np.zeros_like(y), F=U, choice=choice)
    pf = fit_path(L, c, K, g, hp.lam, [monomials.parse(k) for k in hp.fn], order, smoothed_noise(L),
                  path_width(y, nst.dt, tuning), tuning=tuning)
    info = dict(hp.info, path_form=pf.info())
    return (HysteresisParams(lam=pf.gamma + pf.delta, alpha=pf.alpha, fn=pf.fn, delta=pf.delta, gamma=pf.gamma,
                             info=info), pf.c, pf.K)


def reconstruct_chain(run: ChainRun, order: int = 5, n_folds: int = 5, refit_params: bool = True,
                      polish: bool = True, validate_model: bool = True, polish_substeps: int = 2,
                      path_form: bool = True, tuning: EstimatorTuning = DEFAULT_TUNING) -> ChainResult:
    """Per-layer identification (linear step, agent model or the no-hysteresis fallback),
    then (``polish``) an output-error refinement of the whole chain on the nonlinear stage.

    ``path_form``: in a layer found hysteretic, the structured refit and delta come from the
    weak form along the hysteresis path (recon/weak_path.py; pattern revised stepwise) instead
    of the pointwise refit and the h = 0 step. ``tuning``: the estimator's weak_* fields and
    ``negligible`` (recon.estimator.tuning)."""

    t0 = time.perf_counter()
    lst, nst = run.stage("linear"), run.stage("nonlinear")
    n = lst.x.shape[0]
    XL, FL, _ = _derivs(lst, 2, False)
    XN, FN, ch = _derivs(nst, 3, True)
    corr = filter_correlation_length(ch.to_dict())
    layers = []
    for i in range(n):
        c, K, g, ratios, cond = linear_layer(XL, FL, i)
        U = [sum(FN[j][d] for j in range(i + 1)) for d in (0, 1)]
        # w_i = g U_i - sum r_j x_j'' - x_(i+1)''  and its derivative
        w = [g * U[d] - sum(r * XN[j][2 + d] for j, r in enumerate(ratios))
             - (XN[i + 1][2 + d] if i < n - 1 else 0.0) for d in (0, 1)]
        y, dy, ddy, dddy = (_rel(XN, i, d) for d in range(4))
        Fn = w[0] - ddy - c * dy - K * y
        dFn = w[1] - dddy - c * ddy - K * dy
        h = cluster(y, dy)
        lib = AgentLibrary(order, "joint")
        theta, target = lib.build(y, dy, ddy, Fn, dFn, h)
        groups, core = lib.groups()
        sp = GroupedSparseSelector(groups, core, n_folds=n_folds, corr_len=corr).fit(theta, target)
        info = {"linear_condition_number": cond, "library_terms": int(sp.support.sum())}
        hyst = False
        try:
            hp = extract(lib, sp.coef, sp.stderr, sp.support)
            lam_se = hp.info["lambda_direct_se"] if hp.info["lambda_source"] != "eq24_pairs" else hp.info["lambda_eq24_se"]
            info["lambda_equation_error"] = hp.lam
            info["lambda_se"] = float(lam_se)
            hyst = hp.lam > 5 * lam_se and hp.alpha > 0
            if hyst and path_form:
                hp, c, K = _path_layer(nst, ch, i, ratios, g, y, dy, c, K, hp, order, tuning)
                info["path_form"] = hp.info["path_form"]
                hyst = hp.lam > 0 and hp.alpha > 0
            elif hyst and refit_params:
                mask = lib.rows(h)
                hp, c, K, _ = refit(hp, y[mask], dy[mask], ddy[mask], dddy[mask], w[0][mask], w[1][mask],
                                    h[mask].astype(float), c, K, 1.0, fit_g=False, fit_linear=True)
                Fn = w[0] - ddy - c * dy - K * y
                dFn = w[1] - dddy - c * ddy - K * dy
                hyst = hp.lam > 0 and hp.alpha > 0
            if hyst and not path_form:
                hp = estimate_delta(hp, y, dy, ddy, Fn, dFn, h)
        except UserFacingError as exc:
            info["agent_model"] = str(exc)
            hyst = False
        if hyst:
            lay = LayerResult(i, c, K - hp.alpha, hp.alpha, hp.gamma, hp.delta, g, hp.fn, ratios, True, info)
        else:
            fn, sp2 = _plain_fn(y, dy, Fn, order, n_folds, corr)
            info["fallback"] = "plain sparse regression of Fn on monomials (no hysteresis)"
            lay = LayerResult(i, c, K, 0.0, 0.0, 0.0, g, fn, ratios, False, info)
        layers.append(lay)
    timings = {"fit": time.perf_counter() - t0}
    model = chain_model(layers)
    if polish:
        tp = time.perf_counter()
        ee = [L.to_dict() for L in layers]
        model, pinfo = polish_chain(model, [nst], n_sub=polish_substeps)
        # terms the output error leaves negligible (< tuning.negligible of the layer's elastic force)
        # are dropped and the chain is polished once more
        ys = [(_rel(XN, i, 0), _rel(XN, i, 1)) for i in range(n)]
        dropped = prune(model, ys, tuning.negligible)
        if any(dropped):
            model, pinfo2 = polish_chain(model, [nst], n_sub=polish_substeps)
            pinfo = {"first": pinfo, "after_pruning": pinfo2}
        layers = layers_of(model, layers)
        for L, d in zip(layers, dropped):
            L.info["pruned_after_polish"] = d
        for L, e in zip(layers, ee):
            L.info["equation_error_estimate"] = e
            L.info["output_error_polish"] = pinfo
        timings["polish"] = time.perf_counter() - tp
    t1 = time.perf_counter()
    val = validate_chain(model, run) if validate_model else {}
    timings["validation"] = time.perf_counter() - t1
    return ChainResult(layers=layers, model=model, validation=val, timings=timings)


def chain_model(layers: list) -> ChainModel:
    """Absolute-unit chain from the per-layer results (m_i = 1/inv_m of layer i)."""
    m = [1.0 / L.inv_m for L in layers]
    return ChainModel(m=m, c=[L.c_m * mi for L, mi in zip(layers, m)], k=[L.k_m * mi for L, mi in zip(layers, m)],
                      alpha=[L.alpha_m * mi for L, mi in zip(layers, m)], gamma=[L.gamma for L in layers],
                      delta=[L.delta for L in layers],
                      fn=[{k: v * mi for k, v in L.fn_m.items()} for L, mi in zip(layers, m)],
                      provenance={"method": "per-layer agent-model regression (recon.chain.estimator)"})


def validate_chain(model: ChainModel, run: ChainRun) -> dict:
    """NRMSE of every mass displacement on the 'validation' stage(s), simulated from rest."""
    names = [k for k in run.stages if k.startswith("validation")] or ["nonlinear"]
    out = {}
    for name in names:
        st = run.stage(name)
        X, _, _ = model.simulate_recorded(st.t, st.f)
        out[name] = [nrmse(X[i], st.x[i]) for i in range(st.x.shape[0])]
    main = names[0]
    return {"stage": main, "nrmse": float(np.max(out[main])), "per_mass": out}


def contributions(model: ChainModel, i: int, y, dy) -> dict:
    """rms of each fn term of element i relative to the rms of its elastic force (k + alpha) y."""
    return term_contributions(model.fn[i], model.k[i] + model.alpha[i], y, dy)


def prune(model: ChainModel, ys: list, negligible: float) -> list:
    """Drop (in place) the fn terms whose contribution is below ``negligible``; returns the names per layer."""
    dropped = []
    for i, (y, dy) in enumerate(ys):
        small = [k for k, v in contributions(model, i, y, dy).items() if v < negligible]
        for k in small:
            del model.fn[i][k]
        dropped.append(small)
    return dropped


def polish_chain(model: ChainModel, stages: list, max_nfev: int = 30, n_sub: int = 2):
    """Output-error refinement of every chain parameter (masses included) on the recorded
    displacements of ``stages`` (simulated from rest with the recorded forces); kept only
    if it lowers the error. Returns (model, info)."""

    keys = []
    for i in range(model.n):
        keys += [("m", i), ("c", i), ("k", i)]
        if model.alpha[i] != 0.0:
            keys += [("alpha", i), ("gamma", i), ("delta", i)]
        keys += [("fn", i, name) for name in model.fn[i]]

    def get(mod, key):
        return mod.fn[key[1]][key[2]] if key[0] == "fn" else getattr(mod, key[0])[key[1]]

    x0 = np.array([get(model, k) for k in keys], float)
    scale = parameter_scales(keys, x0, lambda k: model.gamma[k[1]] + model.delta[k[1]])

    def build(p):
        x = x0 + p * scale
        d = {a: list(getattr(model, a)) for a in ("m", "c", "k", "alpha", "gamma", "delta")}
        fn = [dict(f) for f in model.fn]
        for j, k in enumerate(keys):
            if k[0] == "fn":
                fn[k[1]][k[2]] = float(x[j])
            else:
                d[k[0]][k[1]] = float(x[j])
        return ChainModel(fn=fn, provenance=dict(model.provenance), **d)

    data = [(st, np.sqrt(np.mean((st.x - st.x.mean(axis=1, keepdims=True)) ** 2, axis=1))) for st in stages]
    n_res = sum(st.x.size for st, _ in data)

    def resid(p):
        m = build(p)
        if min(m.m) <= 0:
            return np.full(n_res, DIVERGED_RESIDUAL)
        out = []
        for st, rms in data:
            X, _, _ = m.simulate_recorded(st.t, st.f, n_sub)
            if not np.all(np.isfinite(X)):
                return np.full(n_res, DIVERGED_RESIDUAL)
            out.append(((X - st.x) / (rms[:, None] * np.sqrt(st.t.size))).ravel())
        return np.concatenate(out)

    r0 = resid(np.zeros(len(keys)))
    sol = least_squares(resid, np.zeros(len(keys)), method="trf", diff_step=FD_STEP, max_nfev=max_nfev,
                        xtol=1e-10, ftol=1e-12)
    c0, c1 = float(np.sqrt(r0 @ r0)), float(np.sqrt(sol.fun @ sol.fun))
    info = {"applied": c1 < c0, "error_before": c0, "error_after": c1, "nfev": int(sol.nfev), "parameters": len(keys)}
    return (build(sol.x) if c1 < c0 else model), info


def layers_of(model: ChainModel, previous: list) -> list:
    """Per-layer results (per unit mass) of an absolute-unit chain, keeping the decisions
    and info of ``previous``."""
    out = []
    for i, L in enumerate(previous):
        d = model.layer(i)
        out.append(LayerResult(i, d["c_m"], d["k_m"], d["alpha_m"], d["gamma"], d["delta"], d["inv_m"], d["fn_m"],
                               d["mass_ratios"], L.hysteresis, dict(L.info)))
    return out

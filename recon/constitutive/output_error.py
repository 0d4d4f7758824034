"""Output-error polish of a force law, by variable projection.

The displacement is imposed, so a trial law is simulated by integrating only the unit-gain
hysteretic state w (and the command lag u; recon.simulation.imposed), which is cheap. The
predicted force

    F = c x' + k x + sum_j a_j phi_j(x, x') + alpha w + f0   [+ c1 u x' + alpha1 u w]

is linear in every parameter except gamma, delta (and eta, and the start state w0 of each
record), and so is a fitted inertia term m x'' (a column x''), so for each trial of those the rest is solved by least squares and the residual is
(F_pred - F_recorded) / rms(F) over the record (variable projection). The nonlinear search is
``scipy.optimize.least_squares`` on scaled parameters (recon.output_error.problem's scaling rule
and diverged-trial residual). Records faster than the polish rate are decimated as in
recon.output_error.polish.

Term revision (:func:`revise_terms`): fn terms are dropped one at a time while the
information criterion of the output error (recon.regression.criteria.bic, with the
residual's effective sample count) does not grow.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from recon.constitutive.law import ConstitutiveLaw
from recon.constitutive.signals import ComponentSignals
from recon.library import monomials
from recon.library.agent import phi
from recon.output_error.problem import DIVERGED_RESIDUAL, parameter_scales
from recon.regression.criteria import bic, effective_samples
from recon.regression.sparse import scaled_lstsq
from recon.simulation.imposed import hysteretic_state
from recon.steps.bouc_wen import term_contributions


class ForceOutputError:
    """The projected output-error problem of a law's structure on records ``items``.

    Structure: the fn terms of ``law``, damping if ``law.c`` (or a command law), the offset
    f0 always (a force sensor's offset costs one column), the command law if ``law.eta`` > 0
    (its records must have a command)."""

    def __init__(self, law: ConstitutiveLaw, items: list[ComponentSignals], fit_eta: bool = True,
                 extras: dict | None = None, *, fit_rate: float):
        """``extras`` {name: f(y, dy, ddy) -> array}: further linear force terms (the constitutive
        diagnosis's candidates, recon.constitutive.diagnosis), coefficients named ``x:<name>``.
        ``fit_rate``: records sampled faster than twice this are taken on every q-th sample
        (ConstitutiveSettings.fit_rate)."""
        self.law = law
        self.extras = dict(extras or {})
        self.items = []
        for s in items:
            q = max(1, int((1.0 / s.dt) // fit_rate))
            self.items.append((s.dt * q, s.y[::q], s.dy[::q], s.F_raw[::q], None if s.cmd is None else s.cmd[::q],
                               s.F[0], s.y[0], s.dy[0], s.ddy[::q]))
        self.decimation = [max(1, int((1.0 / s.dt) // fit_rate)) for s in items]
        self.terms = list(law.fn)
        self.has_c = bool(law.c) or law.commanded
        self.has_f0 = True
        self.has_m = bool(law.mass)
        self.commanded = law.commanded
        self.keys = ["gamma", "delta"] + (["eta"] if self.commanded and fit_eta else []) + \
            [f"w0:{i}" for i in range(len(items))]
        x0 = [law.gamma, law.delta] + ([law.eta] if "eta" in self.keys else []) + \
            [law.start_state(F0, y0, dy0, None if cmd is None else cmd[0], ddy[0])
             for _, _, _, _, cmd, F0, y0, dy0, ddy in self.items]
        self.x0 = np.array(x0, float)
        lam = law.lam if law.lam else 1.0
        self.scale = parameter_scales(self.keys, self.x0, lam,
                                      {**{k: 1.0 / abs(lam) for k in self.keys if k.startswith("w0:")},
                                       **({"eta": max(abs(law.eta), 1.0)} if "eta" in self.keys else {})})
        self.rms = [float(np.std(it[3])) or 1.0 for it in self.items]
        self.n_rows = sum(it[1].size for it in self.items)

    def values(self, p):
        x = self.x0 + np.asarray(p, float) * self.scale
        v = dict(zip(self.keys, x))
        eta = v.get("eta", self.law.eta)
        return v["gamma"], v["delta"], eta, [v[f"w0:{i}"] for i in range(len(self.items))]

    def columns(self, p):
        """Per record: (A, names) of the linear problem at the nonlinear parameters p (None: diverged)."""
        gamma, delta, eta, w0 = self.values(p)
        out = []
        for (dt, y, dy, F, cmd, _, _, _, ddy), w_start in zip(self.items, w0):
            w, u = hysteretic_state(dy, dt, gamma, delta, w_start, cmd if self.commanded else None, eta)
            if not np.all(np.isfinite(w)) or (u is not None and not np.all(np.isfinite(u))):
                return None
            cols, names = [y, w], ["k", "alpha"]
            if self.has_c:
                cols.append(dy); names.append("c")
            if self.has_f0:
                cols.append(np.ones_like(y)); names.append("f0")
            if self.has_m:
                cols.append(ddy); names.append("mass")
            if self.commanded:
                cols += [u * dy, u * w]; names += ["c1", "alpha1"]
            for t in self.terms:
                cols.append(phi(y, dy, *monomials.parse(t))); names.append(f"fn:{t}")
            for name, f in self.extras.items():
                cols.append(f(y, dy, ddy)); names.append(f"x:{name}")
            out.append((np.column_stack(cols), names))
        return out

    def solve(self, p):
        """(coefficients {name: value}, list of residual arrays per record) or (None, None)."""
        cols = self.columns(p)
        if cols is None:
            return None, None
        A = np.vstack([a / r / np.sqrt(a.shape[0]) for (a, _), r in zip(cols, self.rms)])
        b = np.concatenate([it[3] / r / np.sqrt(it[3].size) for it, r in zip(self.items, self.rms)])
        x, _ = scaled_lstsq(A, b)
        res = [(a @ x - it[3]) / r for (a, _), it, r in zip(cols, self.items, self.rms)]
        return dict(zip(cols[0][1], (float(v) for v in x))), res

    def residual(self, p) -> np.ndarray:
        _, res = self.solve(p)
        if res is None:
            return np.full(self.n_rows, DIVERGED_RESIDUAL)
        return np.concatenate([e / np.sqrt(e.size) for e in res])

    def build(self, p) -> ConstitutiveLaw:
        coef, _ = self.solve(p)
        gamma, delta, eta, _ = self.values(p)
        law = self.law
        return ConstitutiveLaw(c=coef.get("c", 0.0), k=coef["k"], alpha=coef["alpha"], gamma=float(gamma),
                               delta=float(delta), f0=coef.get("f0", 0.0),
                               fn={t: coef[f"fn:{t}"] for t in self.terms}, mass=coef.get("mass", law.mass),
                               c1=coef.get("c1", 0.0), alpha1=coef.get("alpha1", 0.0),
                               eta=float(eta) if self.commanded else 0.0, provenance=dict(law.provenance))


def polish(law: ConstitutiveLaw, items: list[ComponentSignals], max_nfev: int = 60, fit_eta: bool = True,
           extras: dict | None = None, *, fit_rate: float):
    """(law, info): the projected output-error fit of ``law``'s structure on ``items`` (with
    ``extras``: their coefficients in ``info["extras"]``; ``fit_rate``: ConstitutiveSettings.fit_rate)."""
    prob = ForceOutputError(law, items, fit_eta, extras, fit_rate=fit_rate)
    p0 = np.zeros(len(prob.keys))
    r0 = prob.residual(p0)
    sol = least_squares(prob.residual, p0, method="trf", diff_step=1e-6, max_nfev=max_nfev, xtol=1e-10,
                        ftol=1e-12)
    cost0 = float(np.sqrt(r0 @ r0 / len(items)))
    cost1 = float(np.sqrt(sol.fun @ sol.fun / len(items)))
    info = {"nrmse_before": cost0, "nrmse_after": cost1, "nfev": int(sol.nfev), "decimation": prob.decimation,
            "nonlinear_parameters": prob.keys}
    p = sol.x if (cost1 <= cost0 and cost1 < DIVERGED_RESIDUAL) else p0
    if extras:
        coef, _ = prob.solve(p)
        info["extras"] = {k[2:]: v for k, v in (coef or {}).items() if k.startswith("x:")}
    if p is p0:
        # the start's own projected fit (the equation-error structure, linear parameters re-solved)
        return prob.build(p0) if cost0 < DIVERGED_RESIDUAL else law, dict(info, applied=False)
    return prob.build(sol.x), dict(info, applied=True)


def score(law: ConstitutiveLaw, items: list[ComponentSignals], fit_rate: float) -> tuple[float, float, float]:
    """(rms of the normalised residual, effective samples, number of linear + nonlinear parameters)."""
    prob = ForceOutputError(law, items, fit_eta=False, fit_rate=fit_rate)
    _, res = prob.solve(np.zeros(len(prob.keys)))
    if res is None:
        return float("inf"), 1.0, 0.0
    r = np.concatenate(res)
    n_eff = sum(effective_samples(e) for e in res)
    k = len(prob.terms) + 2 + prob.has_c + prob.has_f0 + prob.has_m + 2 * prob.commanded + len(prob.keys)
    return float(np.mean(r * r)), n_eff, float(k)


def revise_terms(law: ConstitutiveLaw, items: list[ComponentSignals], max_nfev: int = 30, *, fit_rate: float,
                 negligible: float):
    """Drop fn terms (one at a time, the one whose removal lowers the BIC most) while the
    output error's BIC does not grow; each trial is polished. First, the terms whose rms force
    is below ``negligible`` (ConstitutiveSettings.negligible) of the elastic force K x go at once
    (kept only if the BIC does not grow). Returns (law, steps)."""
    steps = []
    mse, n_eff, k = score(law, items, fit_rate)
    share = {}
    for it in items:
        for t, v in term_contributions(law.fn, law.K, it.y, it.dy).items():
            share[t] = max(share.get(t, 0.0), v)
    small = sorted(t for t, v in share.items() if v < negligible)
    if small:
        trial = ConstitutiveLaw(**{**law.__dict__, "fn": {t: v for t, v in law.fn.items() if t not in small}})
        trial, _ = polish(trial, items, max_nfev=max_nfev, fit_rate=fit_rate)
        m2, _, k2 = score(trial, items, fit_rate)
        if bic(m2, int(k2), n_eff) <= bic(mse, int(k), n_eff):
            steps.append({"drop": small, "reason": "negligible", "bic_before": bic(mse, int(k), n_eff),
                          "bic_after": bic(m2, int(k2), n_eff), "mse_after": m2})
            law, mse, k = trial, m2, k2
    current = bic(mse, int(k), n_eff)
    while law.fn:
        best = None
        for t in list(law.fn):
            trial = ConstitutiveLaw(**{**law.__dict__, "fn": {kk: v for kk, v in law.fn.items() if kk != t}})
            trial, _ = polish(trial, items, max_nfev=max_nfev, fit_rate=fit_rate)
            m2, n2, k2 = score(trial, items, fit_rate)
            b = bic(m2, int(k2), n_eff)
            if best is None or b < best[0]:
                best = (b, t, trial, m2)
        if best[0] > current:
            break
        steps.append({"drop": best[1], "bic_before": current, "bic_after": best[0], "mse_after": best[3]})
        current, law = best[0], best[2]
    return law, steps


def intervals(law: ConstitutiveLaw, items: list[ComponentSignals], level_z: float = 1.96, rel_step: float = 1e-6,
              *, fit_rate: float) -> dict:
    """Linearised intervals of every parameter of ``law`` at the projected fit's optimum.

    The Jacobian of the weighted force residual with respect to all parameters (the linear
    ones exactly: their columns; gamma, delta, eta by finite differences of the simulated state
    with the linear parameters held), the covariance s^2 (J^T J)^-1 inflated by N / N_eff (the
    residual's effective samples, recon.regression.criteria.effective_samples: a slowly varying
    model error is not white noise). Returns {"parameters": {name: {"value", "se", "low",
    "high"}}, "method", "n_eff", "n"}; the start states w0 are nuisance parameters (left out).
    ``fit_rate``: as the fit took the records (ConstitutiveSettings.fit_rate)."""
    prob = ForceOutputError(law, items, fit_eta=True, fit_rate=fit_rate)
    p0 = np.zeros(len(prob.keys))
    coef, res = prob.solve(p0)
    if coef is None:
        return {"parameters": {}, "method": "diverged"}
    cols = prob.columns(p0)
    names = cols[0][1]
    x = np.array([coef[n] for n in names])
    w = [1.0 / r / np.sqrt(a.shape[0]) for (a, _), r in zip(cols, prob.rms)]
    J_lin = np.vstack([a * wi for (a, _), wi in zip(cols, w)])
    base = np.concatenate([(a @ x) * wi for (a, _), wi in zip(cols, w)])
    nl_keys = [k for k in prob.keys if not k.startswith("w0:")] + [k for k in prob.keys if k.startswith("w0:")]
    J_nl = []
    for key in nl_keys:
        i = prob.keys.index(key)
        p = p0.copy()
        h = rel_step * max(abs(prob.x0[i]) / prob.scale[i], 1.0)
        p[i] = h
        cp = prob.columns(p)
        if cp is None:
            return {"parameters": {}, "method": "diverged"}
        moved = np.concatenate([(a @ x) * wi for (a, _), wi in zip(cp, w)])
        J_nl.append((moved - base) / (h * prob.scale[i]))
    J = np.column_stack([J_lin] + J_nl)
    r = np.concatenate([e * wi * r_ for e, wi, r_ in zip(res, w, prob.rms)])
    n = r.size
    n_eff = sum(effective_samples(e) for e in res)
    s2 = float(r @ r) / max(n - J.shape[1], 1)
    sc = np.sqrt(np.sum(J * J, axis=0))
    sc[sc == 0] = 1.0
    cov = np.linalg.pinv((J / sc).T @ (J / sc)) / np.outer(sc, sc) * s2 * (n / max(n_eff, 1.0))
    se = np.sqrt(np.abs(np.diag(cov)))
    values = dict(coef)
    values.update({k: float(prob.x0[prob.keys.index(k)]) for k in nl_keys})
    out = {}
    for j, name in enumerate(list(names) + nl_keys):
        if name.startswith("w0:"):
            continue
        v = values[name]
        out[name] = {"value": float(v), "se": float(se[j]), "low": float(v - level_z * se[j]),
                     "high": float(v + level_z * se[j])}
    return {"parameters": out, "n": int(n), "n_eff": float(n_eff),
            "method": "linearised at the projected output-error optimum, covariance inflated by N/N_eff; "
                      f"+-{level_z:g} standard errors"}

"""Mismatch diagnosis of a force law: which physics the law leaves out of a component test.

    from recon.constitutive.diagnosis import diagnose_law
    d = diagnose_law(run)            # or diagnose_law(run, law) for a saved law

The baseline law (reconstructed from the run, or given) is refitted on the fitted stage by the
projected output error (recon.constitutive.output_error): the *null* fit. Each candidate of
:data:`CANDIDATES` adds one force term, linear in its coefficient, so its fit is the same
projected problem with one more column (a candidate with a shape parameter, the friction's
smoothing velocity or the contact's gap, tries a few values and keeps the best fit). Every fit is
judged on the held-out stages (``validation*``; without one, the second half of the fitted
stage is held out and the fit uses the first): a candidate is reported when it lowers the
held-out force NRMSE by at least ``min_gain`` (ConstitutiveSettings) of the null fit's, ranked by that gain.
The law's own library already holds the smooth monomials, so the candidates are what it lacks:
non-smooth friction, a contact (gap or end stop), velocity-squared damping, inertia.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from recon.constitutive.estimator import ConstitutiveSettings, reconstruct_constitutive
from recon.constitutive.law import ConstitutiveLaw
from recon.constitutive.output_error import polish
from recon.constitutive.signals import ComponentSignals, component_signals
from recon.validation import nrmse
from shakerlab.errors import UserFacingError
from shakerlab.run_data import Run, Stage

def _coulomb(v0):
    return lambda y, dy, ddy: np.tanh(dy / v0)


def _contact(gap):
    return lambda y, dy, ddy: np.sign(y) * np.maximum(np.abs(y) - gap, 0.0)


@dataclass(frozen=True)
class Candidate:
    id: str
    explanation: str
    unit: str


CANDIDATES = {
    "coulomb_friction": Candidate("coulomb_friction", "dry friction: a force Fc tanh(x'/v0) that switches with the "
                                  "sign of the velocity (v0 small)", "N"),
    "contact_stiffness": Candidate("contact_stiffness", "a contact or end stop: extra stiffness k_c beyond a gap "
                                   "|x| > g, k_c sgn(x) max(|x| - g, 0)", "N/m"),
    "quadratic_damping": Candidate("quadratic_damping", "velocity-squared damping c2 x'|x'| (orifice flow)",
                                   "N s^2/m^2"),
    "inertia": Candidate("inertia", "the inertia of the moving parts, m x''", "kg"),
}


def candidate_terms(cid: str, sig: ComponentSignals):
    """(shape name, grid of shape values, column maker value -> f(y, dy, ddy)) of one candidate;
    a candidate without a shape parameter has the grid [None]."""
    vrms = float(np.std(sig.dy)) or 1.0
    xmax = float(np.max(np.abs(sig.y))) or 1.0
    if cid == "coulomb_friction":
        return "v0 [m/s]", [f * vrms for f in (0.01, 0.05, 0.2)], _coulomb
    if cid == "contact_stiffness":
        return "gap [m]", [f * xmax for f in (0.5, 0.6, 0.7, 0.8, 0.9)], _contact
    if cid == "quadratic_damping":
        return None, [None], lambda _: (lambda y, dy, ddy: dy * np.abs(dy))
    if cid == "inertia":
        return None, [None], lambda _: (lambda y, dy, ddy: ddy)
    raise ValueError(cid)


def predict_with(law: ConstitutiveLaw, stage: Stage, extras: dict | None = None, coef: dict | None = None):
    """(recorded force, predicted force) of ``stage`` under ``law`` plus extra terms."""
    sig = component_signals(stage, for_regression=False)
    cmd = sig.cmd if law.commanded else None
    w0 = law.start_state(sig.F[0], sig.y[0], sig.dy[0], None if cmd is None else float(cmd[0]), sig.ddy[0])
    F, _, _ = law.simulate(sig.dt, sig.y, sig.dy, cmd, w0, sig.ddy)
    for name, f in (extras or {}).items():
        F = F + coef[name] * f(sig.y, sig.dy, sig.ddy)
    return sig.F_raw, F


@dataclass
class LawDiagnosis:
    baseline: ConstitutiveLaw
    baseline_kind: str
    held_out: list
    fit_before: dict
    min_gain: float                                    # the gain a candidate needs (ConstitutiveSettings)
    candidates: list = field(default_factory=list)     # every candidate's best fit
    missing: list = field(default_factory=list)        # the significant ones, best first

    def to_dict(self) -> dict:
        return {"mode": "constitutive", "baseline": self.baseline.equation(), "baseline_kind": self.baseline_kind,
                "held_out": self.held_out, "fit_before": self.fit_before, "candidates": self.candidates,
                "missing_physics": self.missing, "min_gain": self.min_gain,
                "result": ("the law explains the held-out force as well as any candidate" if not self.missing else
                           "missing: " + ", ".join(m["id"] for m in self.missing))}


def _split(run: Run, fit_stage: str):
    """(fit stages, held-out stages): the validation stages, else the two halves of the fitted one."""
    held = [run.stage(n) for n in run.stages if n.startswith("validation")]
    st = run.stage(fit_stage)
    if held:
        return [st], held, [h.name for h in held]
    n = st.t.size // 2
    first = Stage(f"{st.name}[first half]", st.t[:n], {k: v[:n] for k, v in st.channels.items()}, st.excitation)
    second = Stage(f"{st.name}[second half]", st.t[n:] - st.t[n], {k: v[n:] for k, v in st.channels.items()},
                   st.excitation)
    return [first], [second], [second.name]


def diagnose_law(run: Run, law: ConstitutiveLaw | None = None, settings: ConstitutiveSettings | None = None,
                 candidates=None) -> LawDiagnosis:
    s = settings or ConstitutiveSettings()
    fit_stages, held, held_names = _split(run, s.fit_stage)
    kind = "given law"
    if law is None:
        law = reconstruct_constitutive(run, s, validate_law=False).law
        kind = "reconstructed from the run"
    sigs = [component_signals(st) for st in fit_stages]
    null, _ = polish(law, sigs, fit_rate=s.fit_rate)

    def held_out(model, extras=None, coef=None):
        errs = {}
        for st in held:
            F, Fp = predict_with(model, st, extras, coef)
            errs[st.name] = nrmse(Fp, F)
        return errs

    before = held_out(null)
    ref = float(np.mean(list(before.values())))
    if not math.isfinite(ref):
        raise UserFacingError("the baseline law, refitted on the fitted stage, does not predict the held-out stages "
                              "(the simulation diverged)")
    results = []
    for cid in candidates or CANDIDATES:
        if cid == "inertia" and law.mass:
            continue
        shape, grid, make = candidate_terms(cid, sigs[0])

        def fit(value):
            fitted, info = polish(null, sigs, max_nfev=30, extras={cid: make(value)}, fit_rate=s.fit_rate)
            return info["nrmse_after"], fitted, info.get("extras", {})

        # the shape parameter by the fit (never by the held-out data): the best of the grid, then
        # a bounded search between its neighbours
        fits = [(fit(v), v) for v in grid]
        (cost, fitted, coef), value = min(fits, key=lambda f: f[0][0])
        if shape is not None:
            k = grid.index(value)
            lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
            res = minimize_scalar(lambda v: fit(v)[0], bounds=(lo, hi), method="bounded",
                                  options={"xatol": 0.01 * (hi - lo), "maxiter": 12})
            if res.fun < cost:
                value = float(res.x)
                cost, fitted, coef = fit(value)
        if cid not in coef:
            continue
        errs = held_out(fitted, {cid: make(value)}, coef)
        e = float(np.mean(list(errs.values())))
        results.append({"id": cid, "explanation": CANDIDATES[cid].explanation,
                        "shape": None if shape is None else {shape: value},
                        "coefficient": float(coef[cid]), "unit": CANDIDATES[cid].unit, "fit_nrmse": cost,
                        "held_out_nrmse": e, "per_stage": errs, "gain": (ref - e) / ref,
                        "law": fitted.parameters()})
    results.sort(key=lambda r: -r["gain"])
    missing = [r for r in results if r["gain"] >= s.min_gain]
    return LawDiagnosis(baseline=null, baseline_kind=kind, held_out=held_names,
                        fit_before={"held_out_nrmse": ref, "per_stage": before}, min_gain=s.min_gain,
                        candidates=results,
                        missing=missing)

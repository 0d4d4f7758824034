"""From a component test to a shaker run: a constitutive law as the baseline of the structure.

A law identified on the bench (force in N as a function of the specimen's deformation y and y')
becomes the equation of motion of the same specimen on the shaker once its moving mass m and
its support are known. The support adds a stiffness k_s and a damping c_s in parallel; per unit
mass (recon.model.HystereticModel):

    c_m = (c + c_s)/m,  k_m = (k + k_s)/m,  alpha_m = alpha/m,  fn_m = fn/m,  gamma, delta as they are

(and inv_m = 1/m under force excitation). The law's offset f0 is a bench sensor's, not the
structure's, and is left out. m, k_s and c_s are the only unknowns: fitted by output error on
the run's linear and nonlinear stages (recon.output_error.problem.OutputError, decimated as
the polish), from the mass the linear step implies (m0 = (k + alpha) / K_m) and no support.
Under base excitation the per-unit-mass model alone cannot give m; the law in newtons does.

A command-dependent law needs the command level of the shaker test: refused.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from recon.constitutive.law import ConstitutiveLaw
from recon.differentiation import estimate_spectrum
from recon.estimator.tuning import DEFAULT_TUNING
from recon.model import HystereticModel
from recon.output_error.polish import decimate
from recon.output_error.problem import OutputError
from recon.signals import stage_signals
from recon.steps.linear import count_lines, fit_linear
from recon.validation import nrmse
from shakerlab.errors import UserFacingError
from shakerlab.run_data import BASE, Run

KIND = "constitutive law + fitted mass and support"


def structure_model(law: ConstitutiveLaw, excitation: str, m: float, k_s: float = 0.0, c_s: float = 0.0,
                    provenance: dict | None = None) -> HystereticModel:
    return HystereticModel(excitation=excitation, c_m=(law.c + c_s) / m, k_m=(law.k + k_s) / m,
                           alpha_m=law.alpha / m, gamma=law.gamma, delta=law.delta,
                           fn_m={k: v / m for k, v in law.fn.items()},
                           inv_m=None if excitation == BASE else 1.0 / m, provenance=provenance or {})


def linear_mass(law: ConstitutiveLaw, run: Run, stage: str) -> float:
    """m0 = (k + alpha) / K_m, K_m from the linear step of ``stage``."""
    st = run.stage(stage)
    s = stage_signals(st, deriv=2, for_regression=False)
    lines = None
    if st.excitation != BASE:
        lines = count_lines(estimate_spectrum(st.channels["force"], st.dt).freqs, 1.0 / (st.t[-1] - st.t[0]))
    lf = fit_linear(s.y[0], s.y[1], s.y[2], s.u[0], st.excitation, s.column_noise, stage, lines)
    if not lf.K_m > 0:
        raise UserFacingError(f"stage {stage!r}: the linear step gives K_m = {lf.K_m:.4g}; no mass follows from it")
    return law.K / lf.K_m


def shaker_baseline(law: ConstitutiveLaw, run: Run, stages=None, max_nfev: int = 40):
    """(HystereticModel, info): ``law`` with the mass and support fitted on ``run``."""
    if law.commanded:
        raise UserFacingError("the constitutive law depends on a command (an MR damper's): identify the law at the "
                              "command level of the shaker test (a record with a constant command) and use that")
    names = stages or [n for n in ("linear", "nonlinear") if n in run.stages] or list(run.stages)[:1]
    excitation = run.stage(names[0]).excitation
    m0 = linear_mass(law, run, "linear" if "linear" in run.stages else names[0])
    c_ref = max(abs(law.c), 0.02 * 2.0 * np.sqrt(abs(law.K) * m0))
    probe = structure_model(law, excitation, m0)
    # the data items (input, start state) once, from the start model, as the polish does: each trial
    # still gets its own z0 from the recorded start (OutputError.response)
    items = [decimate(probe.fit_item(run.stage(n)), DEFAULT_TUNING.polish_fs)[0] for n in names]

    def model(p):
        return structure_model(law, excitation, m0 * float(np.exp(p[0])), float(p[1]) * law.K, float(p[2]) * c_ref)

    def residual(p):
        prob = OutputError(model(p), items)
        return prob.residual(np.zeros(len(prob.keys)))

    r0 = residual(np.zeros(3))
    sol = least_squares(residual, np.zeros(3), method="trf", diff_step=1e-4, max_nfev=max_nfev,
                        xtol=1e-10, ftol=1e-12)
    m_fit, ks, cs = m0 * float(np.exp(sol.x[0])), float(sol.x[1]) * law.K, float(sol.x[2]) * c_ref
    info = {"kind": KIND, "mass": m_fit, "mass_from_linear_step": m0, "support_stiffness": ks,
            "support_damping": cs, "stages": names, "nfev": int(sol.nfev),
            "cost_before": float(np.sqrt(r0 @ r0)), "cost_after": float(np.sqrt(sol.fun @ sol.fun)),
            "law": law.parameters()}
    best = structure_model(law, excitation, m_fit, ks, cs,
                           provenance={"method": "constitutive law of a component test, mass and support fitted "
                                                 "(recon.constitutive.bridge)", "bridge": info,
                                       "law_provenance": law.provenance})
    info["nrmse"] = {n: nrmse(best.simulate_stage(run.stage(n))[1], run.stage(n).y) for n in run.stages}
    return best, info

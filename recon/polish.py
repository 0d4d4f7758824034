"""Output-error polish of the SDOF HystereticModel: refine all parameters by simulating it.

With the sparsity pattern fixed by the equation-error regression, the
parameters (c_m, k_m, alpha_m, gamma, delta, a_j[, inv_m]) are refined by
nonlinear least squares on the simulated response: the residual is
(y_sim - y_meas)/rms(y_meas) over the fitting stages (the linear and the
nonlinear one), simulated from rest with the recorded input. This uses the
whole time history instead of a third derivative, so it removes most of the
differentiation bias the equation-error estimates carry.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from recon.model import HystereticModel
from shakerlab.run_data import BASE

NAMES = ("c_m", "k_m", "alpha_m", "gamma", "delta")


def polish(model: HystereticModel, data: list, max_nfev: int = 60):
    """Refine ``model`` on ``data`` = [(t, u, y_meas[, (y0, dy0, a0)]), ...]; returns (model, info).

    The optional start (y, y', y'' at the first sample) sets the initial state; z0 follows
    from the equation of motion for each trial parameter set."""
    keys = list(NAMES) + [f"fn:{k}" for k in model.fn_m] + (["inv_m"] if model.excitation != BASE else [])

    def get(m, k):
        return m.fn_m[k[3:]] if k.startswith("fn:") else getattr(m, k)

    x0 = np.array([get(model, k) for k in keys], float)
    lam = abs(model.gamma + model.delta) or 1.0
    scale = np.where(np.abs(x0) > 0, np.abs(x0), 1.0)
    for i, k in enumerate(keys):
        if k in ("gamma", "delta"):
            scale[i] = max(abs(x0[i]), 0.1 * lam)

    def build(p):
        x = x0 + p * scale
        kw = {k: x[i] for i, k in enumerate(keys) if not k.startswith("fn:")}
        fn = {k[3:]: x[i] for i, k in enumerate(keys) if k.startswith("fn:")}
        return HystereticModel(excitation=model.excitation, fn_m=fn, provenance=model.provenance,
                               inv_m=kw.pop("inv_m", model.inv_m), **kw)

    rms = [float(np.sqrt(np.mean((d[2] - d[2].mean()) ** 2))) or 1.0 for d in data]

    def resid(p):
        m = build(p)
        out = []
        for d, r in zip(data, rms):
            t, u, y = d[:3]
            init = None
            if len(d) > 3 and d[3] is not None:
                y0, v0, a0 = d[3]
                z0 = m.input_gain * u[0] - a0 - m.c_m * v0 - m.k_m * y0 - float(m.fn(np.array([y0]), np.array([v0]))[0])
                init = (y0, v0, z0)
            ys, _, _ = m.simulate(t, u, initial=init)
            if not np.all(np.isfinite(ys)):
                return np.full(sum(d[2].size for d in data), 1e3)
            out.append((ys - y) / (r * np.sqrt(y.size)))
        return np.concatenate(out)

    r0 = resid(np.zeros(len(keys)))
    sol = least_squares(resid, np.zeros(len(keys)), method="trf", x_scale=1.0, diff_step=1e-6,
                        max_nfev=max_nfev, xtol=1e-10, ftol=1e-12)
    new = build(sol.x)
    cost0 = float(np.sqrt(r0 @ r0 / len(data)))
    cost1 = float(np.sqrt(sol.fun @ sol.fun / len(data)))
    if not cost1 < cost0:      # keep the equation-error model if polishing did not help
        return model, {"applied": False, "nrmse_before": cost0, "nrmse_after": cost1, "nfev": int(sol.nfev)}
    return new, {"applied": True, "nrmse_before": cost0, "nrmse_after": cost1, "nfev": int(sol.nfev)}

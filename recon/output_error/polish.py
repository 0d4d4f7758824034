"""Output-error polish of the SDOF HystereticModel: refine all parameters by simulating it.

With the sparsity pattern fixed by the equation-error regression, the
parameters (c_m, k_m, alpha_m, gamma, delta, a_j[, inv_m]) are refined by
nonlinear least squares on the simulated response: the residual is
(y_sim - y_meas)/rms(y_meas) over the fitting stages, simulated with the
recorded input from each stage's estimated start state. This uses the whole
time history instead of a third derivative, so it removes most of the
differentiation bias the equation-error estimates carry.

:class:`OutputError` is the reusable piece (parameter vector <-> model, the
simulated residual, optionally restricted to a mask of "fit" samples); the
term selection by output error (recon/term_selection.py) uses it too.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from recon.model import HystereticModel
from shakerlab.run_data import BASE

NAMES = ("c_m", "k_m", "alpha_m", "gamma", "delta")
POLISH_FS = 2000.0   # Hz: the polish simulates at no less than this rate (faster stages are decimated)


def _get(m: HystereticModel, k: str) -> float:
    return m.fn_m.get(k[3:], 0.0) if k.startswith("fn:") else getattr(m, k)


class OutputError:
    """The output-error problem of ``model`` on ``data`` = [(t, u, y_meas[, (y0, dy0, a0)]), ...].

    Parameters are ``x = x0 + p * scale``; ``extra_terms`` = {monomial: scale} adds fn terms
    that the model does not have (coefficient 0 at p = 0). ``masks`` (one boolean array per
    data item, or None) selects the samples the residual is taken over; the simulation always
    runs over the whole item. The optional start (y, y', y'' at the first sample) sets the
    initial state; z0 follows from the equation of motion for each trial parameter set."""

    def __init__(self, model: HystereticModel, data: list, masks=None, extra_terms: dict | None = None):
        self.model = model
        self.data = data
        self.keys = list(NAMES) + [f"fn:{k}" for k in model.fn_m] + [f"fn:{k}" for k in (extra_terms or {})
                                                                       if k not in model.fn_m]
        if model.excitation != BASE:
            self.keys.append("inv_m")
        self.x0 = np.array([_get(model, k) for k in self.keys], float)
        lam = abs(model.gamma + model.delta) or 1.0
        scale = np.where(np.abs(self.x0) > 0, np.abs(self.x0), 1.0)
        for i, k in enumerate(self.keys):
            if k in ("gamma", "delta"):
                scale[i] = max(abs(self.x0[i]), 0.1 * lam)
            if k.startswith("fn:") and k[3:] in (extra_terms or {}) and self.x0[i] == 0.0:
                scale[i] = float(extra_terms[k[3:]])
        self.scale = scale
        self.masks = masks if masks is not None else [None] * len(data)
        self.rms = [float(np.sqrt(np.mean((d[2] - d[2].mean()) ** 2))) or 1.0 for d in data]
        self.n_rows = sum(int(d[2].size if m is None else np.count_nonzero(m)) for d, m in zip(data, self.masks))

    def build(self, p) -> HystereticModel:
        x = self.x0 + np.asarray(p, float) * self.scale
        kw = {k: x[i] for i, k in enumerate(self.keys) if not k.startswith("fn:")}
        fn = {k[3:]: x[i] for i, k in enumerate(self.keys) if k.startswith("fn:")}
        m = self.model
        return HystereticModel(excitation=m.excitation, fn_m=fn, provenance=m.provenance,
                               inv_m=kw.pop("inv_m", m.inv_m), **kw)

    def simulate(self, m: HystereticModel) -> list:
        """Normalised residual (y_sim - y_meas)/rms per data item over ALL samples (None: diverged)."""
        out = []
        for d, r in zip(self.data, self.rms):
            t, u, y = d[:3]
            init = None
            if len(d) > 3 and d[3] is not None:
                y0, v0, a0 = d[3]
                init = (y0, v0, m.balance(u[0], y0, v0, a0))
            ys, _, _ = m.simulate(t, u, initial=init)
            if not np.all(np.isfinite(ys)):
                return None
            out.append((ys - y) / r)
        return out

    def residual(self, p) -> np.ndarray:
        """The fitted residual: masked samples, each item weighted by 1/sqrt(its sample count)."""
        res = self.simulate(self.build(p))
        if res is None:
            return np.full(self.n_rows, 1e3)
        return np.concatenate([(e if mk is None else e[mk]) / np.sqrt(e.size if mk is None else np.count_nonzero(mk))
                               for e, mk in zip(res, self.masks)])


def decimate(item: tuple, fs_target: float = POLISH_FS):
    """Every q-th sample of a data item (t, u, y[, start]) so that its rate is >= ``fs_target``
    (q = floor(fs / fs_target)); returns (item, q). The input u is a Savitzky-Golay-smoothed
    derivative (base) or a force, so taking every q-th sample does not alias the response band."""
    t = item[0]
    fs = 1.0 / float(t[1] - t[0])
    q = max(1, int(fs // fs_target))
    if q == 1:
        return item, 1
    return (t[::q], item[1][::q], item[2][::q], *item[3:]), q


def polish(model: HystereticModel, data: list, max_nfev: int = 60, masks=None, fs_target: float | None = POLISH_FS):
    """Refine ``model`` on ``data`` = [(t, u, y_meas[, (y0, dy0, a0)]), ...]; returns (model, info).

    ``masks``: per data item, the samples the residual is taken over (None: all).
    Items sampled faster than twice ``fs_target`` are decimated to >= ``fs_target`` for the
    fit (a 10 kHz rig stage to 2 kHz: 5x fewer simulated samples; None: never)."""
    q = [1] * len(data)
    if fs_target:
        dec = [decimate(d, fs_target) for d in data]
        data, q = [d for d, _ in dec], [k for _, k in dec]
        if masks is not None:
            masks = [None if m is None else m[::k] for m, k in zip(masks, q)]
    prob = OutputError(model, data, masks)
    p0 = np.zeros(len(prob.keys))
    r0 = prob.residual(p0)
    sol = least_squares(prob.residual, p0, method="trf", x_scale=1.0, diff_step=1e-6,
                        max_nfev=max_nfev, xtol=1e-10, ftol=1e-12)
    new = prob.build(sol.x)
    cost0 = float(np.sqrt(r0 @ r0 / len(data)))
    cost1 = float(np.sqrt(sol.fun @ sol.fun / len(data)))
    if not cost1 < cost0:      # keep the equation-error model if polishing did not help
        return model, {"applied": False, "nrmse_before": cost0, "nrmse_after": cost1, "nfev": int(sol.nfev),
                       "decimation": q}
    return new, {"applied": True, "nrmse_before": cost0, "nrmse_after": cost1, "nfev": int(sol.nfev),
                 "decimation": q}

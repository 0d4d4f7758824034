"""Output-error polish of the SDOF HystereticModel: refine all parameters by simulating it.

With the sparsity pattern fixed by the equation-error regression, the
parameters (c_m, k_m, alpha_m, gamma, delta, a_j[, inv_m]) are refined by
nonlinear least squares on the simulated response: the residual is
(y_sim - y_meas)/rms(y_meas) over the fitting stages, simulated with the
recorded input from each stage's estimated start state (in the quantity the response was
recorded in: y' of a velocity record, y'' of an acceleration record;
recon.output_error.problem.item_target). This uses the whole
time history instead of a third derivative, so it removes most of the
differentiation bias the equation-error estimates carry.

The problem itself (parameter vector <-> model, the simulated residual, optionally
restricted to a mask of "fit" samples) is :class:`recon.output_error.problem.OutputError`.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from recon.differentiation import estimate_spectrum
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.model import HystereticModel
from recon.output_error.problem import FD_STEP, OutputError, item_target
from recon.simulation.resampling import thinned_input
from recon.threads import fd_map


def decimate(item: tuple, fs_target: float):
    """Every q-th sample of a data item (t, u, y[, start[, target]]) so that its rate is >= ``fs_target``
    (q = floor(fs / fs_target)); returns (item, q). The input u is low-passed before it is thinned
    (recon.simulation.resampling.thinned_input), so that its noise above the thinned Nyquist frequency does not
    fold into the response band."""
    t = item[0]
    fs = 1.0 / float(t[1] - t[0])
    q = max(1, int(fs // fs_target))
    if q == 1:
        return item, 1
    out = (t[::q], thinned_input(item[1], q), item[2][::q], *item[3:4])
    if len(item) > 4:           # the measured target (recon.output_error.problem.item_target)
        out += ((item[4][0], item[4][1][::q]),)
    return out, q


def item_cost(model: HystereticModel, item: tuple, tuning: EstimatorTuning = DEFAULT_TUNING,
              mask=None) -> tuple[float, int]:
    """(``model``'s NRMSE on a data item as :func:`polish` fits it: decimated to ``tuning.polish_fs``,
    over ``mask``'s samples when given (a boolean array on the item's own samples); the number of
    samples it is taken over)."""
    dec, q = decimate(item, tuning.polish_fs)
    m = None if mask is None else np.asarray(mask, bool)[::q]
    prob = OutputError(model, [dec], [m])
    r = prob.residual(np.zeros(len(prob.keys)))
    return float(np.sqrt(r @ r)), int(dec[2].size if m is None else np.count_nonzero(m))


def output_noise(item: tuple) -> float:
    """The white-noise std of a data item's recorded output in the quantity its residual is taken
    in (item_target: displacement, or the velocity a vibrometer gave), its spectrum's upper-half
    floor."""
    t, y = item[0], item_target(item)[1]
    if y.size < 64:
        return float("nan")
    return float(estimate_spectrum(y, float(t[1] - t[0])).noise_std)


def polish(model: HystereticModel, data: list, max_nfev: int | None = None, masks=None,
           free: list | None = None, noise: list | None = None, tuning: EstimatorTuning = DEFAULT_TUNING):
    """Refine ``model`` on ``data`` = [(t, u, y_meas[, (y0, dy0, a0)[, target]]), ...]; returns (model, info).
    ``free``: the parameter keys refined (None: every key of the model, problem.parameter_keys).

    ``masks``: per data item, the samples the residual is taken over (None: all).
    Items sampled faster than twice ``tuning.polish_fs`` are decimated to >= that rate for the
    fit (a 10 kHz rig stage to 2 kHz: 5x fewer simulated samples). ``max_nfev``: the evaluation
    budget (None: ``tuning.polish_nfev``); the fit stops at ``tuning.stop_chi2``."""
    max_nfev = tuning.polish_nfev if max_nfev is None else max_nfev
    # the stop's noise (recon.output_error.stopping): each item's white floor, taken before decimation
    stop_noise = noise if noise is not None else [output_noise(d) for d in data]
    dec = [decimate(d, tuning.polish_fs) for d in data]
    data, q = [d for d, _ in dec], [k for _, k in dec]
    if masks is not None:
        masks = [None if m is None else m[::k] for m, k in zip(masks, q)]
    prob = OutputError(model, data, masks, free=free, noise=noise)
    p0 = np.zeros(len(prob.keys))
    r0 = prob.residual(p0)
    sol = least_squares(prob.residual, p0, jac=prob.jac_option(), method="trf", x_scale=1.0, diff_step=FD_STEP,
                        max_nfev=max_nfev, xtol=1e-10, ftol=1e-12, workers=None if prob.analytic else fd_map(),
                        callback=prob.stop(stop_noise, tuning.stop_chi2))
    new = prob.build(sol.x)
    cost0 = float(np.sqrt(r0 @ r0 / len(data)))
    cost1 = float(np.sqrt(sol.fun @ sol.fun / len(data)))
    if not cost1 < cost0:      # keep the equation-error model if polishing did not help
        return model, {"applied": False, "nrmse_before": cost0, "nrmse_after": cost1, "nfev": int(sol.nfev),
                       "decimation": q}
    return new, {"applied": True, "nrmse_before": cost0, "nrmse_after": cost1, "nfev": int(sol.nfev),
                 "decimation": q}

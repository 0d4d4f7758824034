"""The state a recorded stage starts in, fitted by output error.

A stage that starts in motion (a steady-state sine record, a stage that follows another
without a pause) needs its start state (y0, y0', z0) for any simulation of it. The edge
estimate (a Savitzky-Golay fit at the first samples, z0 from the equation of motion) takes
z0 from the edge's y'', the noisiest of the three; a wrong z0 costs a transient that decays
only with the damping. Three numbers are better fitted to the response itself: the start
that makes the simulated y match the recorded y over the stage's first seconds, from the
edge estimate, with rest as the other candidate (the better of the two is kept).

The edge estimate alone is poor: on the independent generator's rig protocol the truth model
simulated from it validates orders of magnitude above its figure from the true start, and
worse at lower SNR (recon/model.py HystereticModel.stage_start, docs/method.md).
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

def fit_start(simulate, y: np.ndarray, dt: float, edge: tuple, scales: tuple, seconds: float, max_nfev: int,
              n_free: int = 3, offset: bool = False) -> tuple[tuple, dict]:
    """The start (y0, y0', z0) that best fits the first ``seconds`` of the recorded ``y`` (the
    transient of a wrong start), in at most ``max_nfev`` simulations (EstimatorTuning's
    start_fit_seconds and start_fit_nfev).

    ``simulate(init, n)`` returns the simulated y over the first n samples from ``init``;
    ``edge`` is the edge estimate the fit starts from, ``scales`` the typical size of each state;
    ``n_free`` = 2 keeps z0 at the edge's value (a model without hysteresis: z0 = 0). ``offset``:
    a constant offset of ``y`` (a velocity sensor's) is a nuisance, taken out of every error (its
    least-squares value, the error's mean), as the output-error fits in velocity take it.
    Returns (start, info) with the fitted and the rest start's errors (rms over rms(y))."""
    n = int(min(y.size, max(round(seconds / dt), 16)))
    seg = y[:n]
    rms = float(np.sqrt(np.mean((seg - seg.mean()) ** 2))) or 1.0
    edge = np.asarray(edge, float)
    sc = np.asarray(scales, float)[:n_free]

    def state(p):
        s = edge.copy()
        s[:n_free] = edge[:n_free] + p * sc
        return s

    def error(ys):
        e = ys - seg
        return e - e.mean() if offset else e

    def resid(p):
        ys = simulate(tuple(state(p)), n)
        if not np.all(np.isfinite(ys)):
            return np.full(n, 1e3)
        return error(ys) / (rms * np.sqrt(n))

    with np.errstate(all="ignore"):
        r_edge = resid(np.zeros(n_free))
        sol = least_squares(resid, np.zeros(n_free), method="trf", x_scale=1.0, max_nfev=max_nfev,
                            xtol=1e-10, ftol=1e-10)
        ys_rest = simulate((0.0, 0.0, 0.0), n)
    e_rest = float(np.sqrt(np.sum((error(ys_rest) / rms) ** 2) / n)) if np.all(np.isfinite(ys_rest)) else np.inf
    e_fit = float(np.sqrt(sol.fun @ sol.fun))
    e_edge = float(np.sqrt(r_edge @ r_edge))
    info = {"samples": n, "nrmse_edge": e_edge, "nrmse_fitted": e_fit, "nrmse_rest": e_rest}
    if e_rest <= min(e_fit, e_edge):
        return (0.0, 0.0, 0.0), {**info, "kept": "rest"}
    if e_edge <= e_fit:
        return tuple(float(v) for v in edge), {**info, "kept": "edge"}
    return tuple(float(v) for v in state(sol.x)), {**info, "kept": "fitted"}

"""Output-error (simulation-error) refinement of the physical parameters.

The agent-model regression (recon.steps.bouc_wen / recon.benchmark.single_level) works on
differentiated, noisy records and is biased at low signal-to-noise ratio.  The
parameters it returns are a good *starting point*; this module polishes them by
minimising the simulation error

    J(theta) = sum_t (y_sim(t; theta) - y_meas(t))^2

with :func:`scipy.optimize.least_squares` (trust-region reflective, finite
difference Jacobian), where ``y_sim`` comes from the same chain that made the
data (:func:`recon.simulation.newmark.simulate_chain`: upsample, Newmark, decimate).

Conditioning: the parameters span eleven decades (1/m ~ 0.5, k/m ~ 2.5e4), so
the optimiser works on relative perturbations ``x`` with
``theta = theta0 * (1 + x)`` (``theta0`` the starting value; a parameter that
starts at zero is scaled by a caller-supplied typical size).  A nonzero
starting value is therefore required for every free parameter that is not
given a scale.

The refinement is generic: it accepts :class:`recon.simulation.newmark.NewmarkParameters`
or anything with the HystereticModel attributes (``c_m, k_m, alpha_m, gamma,
delta, inv_m, fn_m``) through :meth:`NewmarkParameters.from_model`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from dataclasses import replace
from dataclasses import replace as dc_replace

import numpy as np
from scipy.optimize import least_squares

from recon.output_error.problem import DIVERGED_RESIDUAL, FD_STEP
from recon.simulation.newmark import NewmarkParameters, simulate_chain
from shakerlab.errors import UserFacingError

__all__ = ["OutputErrorResult", "refine", "refine_model", "PARAMETER_NAMES"]

PARAMETER_NAMES = NewmarkParameters.NAMES


def _to_vector(p: NewmarkParameters) -> tuple[np.ndarray, list[str]]:
    names = list(PARAMETER_NAMES) + [f"fn:{n}" for n, _ in p.fn]
    vals = [p.b, p.c, p.k, p.alpha, p.gamma, p.delta] + [v for _, v in p.fn]
    return np.asarray(vals, dtype=float), names


def _from_vector(theta: np.ndarray, template: NewmarkParameters) -> NewmarkParameters:
    fn = tuple((n, float(theta[6 + j])) for j, (n, _) in enumerate(template.fn))
    return replace(template, b=float(theta[0]), c=float(theta[1]), k=float(theta[2]),
                   alpha=float(theta[3]), gamma=float(theta[4]), delta=float(theta[5]), fn=fn)


@dataclass
class OutputErrorResult:
    """Refined parameters and figures of the fit."""

    params: NewmarkParameters
    initial: NewmarkParameters
    rms_initial: float           # rms simulation error at the start [m]
    rms_final: float             # rms simulation error at the optimum [m]
    nfev: int
    message: str
    relative_std: dict = field(default_factory=dict)  # parameter -> 1-sigma / |value| (from J'J)
    y_sim: np.ndarray | None = None

    def summary(self) -> str:
        lines = [f"output-error refinement: rms error {self.rms_initial:.3e} -> {self.rms_final:.3e} m "
                 f"({self.nfev} simulations; {self.message})"]
        for name, s in self.relative_std.items():
            lines.append(f"  {name:>12s}: 1-sigma {100 * s:.3g} %")
        return "\n".join(lines)


def refine(initial, u, y, fs: float, *, periodic: bool, upsample: int = 20, n_warmup_periods: int = 0,
           free=None, scales: dict | None = None, discard: int = 0, max_nfev: int = 200,
           xtol: float = 1e-10, ftol: float = 1e-12) -> OutputErrorResult:
    """Refine ``initial`` so the simulated chain output matches ``y``.

    ``u, y``: input and measured output at rate ``fs``.  ``periodic`` and
    ``n_warmup_periods`` are passed to :func:`recon.simulation.newmark.simulate_chain`
    (for a multi-period record simulated from zero state: ``periodic=True,
    n_warmup_periods=0``).  ``free``: names of the parameters to fit (default
    all: b, c, k, alpha, gamma, delta and every fn term as ``"fn:<name>"``).
    ``scales``: typical sizes for parameters that start at zero.
    ``discard``: number of leading samples left out of the cost.
    """
    p0 = initial if isinstance(initial, NewmarkParameters) else NewmarkParameters.from_model(initial)
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    if u.shape != y.shape or u.ndim != 1:
        raise UserFacingError(f"output-error: input and output must be 1-D records of equal length, "
                              f"got {u.shape} and {y.shape}")
    if not 0 <= discard < y.size - 10:
        raise UserFacingError(f"output-error: discard={discard} leaves too few samples of {y.size}")
    theta0, names = _to_vector(p0)
    base_model = not isinstance(initial, NewmarkParameters) and getattr(initial, "inv_m", None) is None
    if free is None:  # the input coefficient is exactly 1 under base excitation: never fit it there
        free = [n for n in names if not (base_model and n == "b")]
    free = list(free)
    unknown = [f for f in free if f not in names]
    if unknown:
        raise UserFacingError(f"output-error: unknown parameter(s) {unknown}; known: {names}")
    idx = np.array([names.index(f) for f in free], dtype=int)
    scales = dict(scales or {})
    scale = np.array([abs(theta0[i]) if theta0[i] != 0 else float(scales.get(names[i], 0.0)) for i in idx])
    if np.any(scale <= 0):
        bad = [names[i] for i, s in zip(idx, scale) if s <= 0]
        raise UserFacingError(f"output-error: parameter(s) {bad} start at zero and have no scale; "
                              "pass scales={name: typical size}")

    def params_of(x):
        theta = theta0.copy()
        theta[idx] = theta0[idx] + scale * x
        return _from_vector(theta, p0)

    def residual(x):
        try:
            ys = simulate_chain(params_of(x), u, fs, upsample=upsample, periodic=periodic,
                                n_warmup_periods=n_warmup_periods)
        except FloatingPointError:
            return np.full(y.size - discard, DIVERGED_RESIDUAL * (np.std(y) + 1.0))  # unstable trial point
        return ys[discard:] - y[discard:]

    r0 = residual(np.zeros(idx.size))
    sol = least_squares(residual, np.zeros(idx.size), method="trf", x_scale=1.0, diff_step=FD_STEP,
                        xtol=xtol, ftol=ftol, gtol=1e-12, max_nfev=max_nfev)
    p_fit = params_of(sol.x)
    rel_std = {}
    dof = max(sol.fun.size - idx.size, 1)
    s2 = float(sol.fun @ sol.fun) / dof
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2
        theta_fit, _ = _to_vector(p_fit)
        for j, i in enumerate(idx):
            val = theta_fit[i]
            rel_std[names[i]] = float(np.sqrt(max(cov[j, j], 0.0)) * scale[j] / abs(val)) if val else float("nan")
    except np.linalg.LinAlgError:
        pass
    y_sim = sol.fun + y[discard:]
    return OutputErrorResult(params=p_fit, initial=p0, rms_initial=float(np.sqrt(np.mean(r0 ** 2))),
                             rms_final=float(np.sqrt(np.mean(sol.fun ** 2))), nfev=int(sol.nfev),
                             message=str(sol.message), relative_std=rel_std, y_sim=y_sim)


def refine_model(model, u, y, fs: float, **kwargs):
    """Refine a :class:`recon.model.HystereticModel`; returns ``(refined_model, OutputErrorResult)``.

    The refined model keeps the excitation kind and the fn terms of ``model``
    (with refitted coefficients) and records the refinement in its provenance.
    Keyword arguments go to :func:`refine`.
    """

    res = refine(model, u, y, fs, **kwargs)
    p = res.params
    provenance = dict(getattr(model, "provenance", {}) or {})
    provenance["output_error"] = {"rms_initial": res.rms_initial, "rms_final": res.rms_final, "nfev": res.nfev,
                                  "relative_std": res.relative_std, "message": res.message}
    inv_m = None if getattr(model, "inv_m", None) is None else p.b
    new = dc_replace(model, c_m=p.c, k_m=p.k, alpha_m=p.alpha, gamma=p.gamma, delta=p.delta,
                     fn_m=dict(p.fn), inv_m=inv_m, provenance=provenance)
    return new, res

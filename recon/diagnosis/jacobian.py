"""The Jacobian of a candidate's output-error fit (recon.diagnosis.rank.fit) from forward
sensitivities.

The fit's residual is, per fitting stage, (y_rec - y) over the fitting samples, divided by the
stage's fit scale and the square root of its sample count, with

    base:  y_rec = (1 + tip_scale) shift(x_in + y + phi2 q, delay) - x_in
    force: y_rec = (1 + tip_scale) shift(y + phi2 q, delay)

(recon.diagnosis.augmented; in velocity every motion differentiated once, with the constant that
best matches the record over the fitting samples added). The parameters that act through the
simulation (the baseline's and the extras that are kernel slots) get their columns from
recon.simulation.sensitivity.simulate_extended_sensitivities, carried through the reading (shift
is linear in what it shifts); the reading's own parameters (phi2, tip_scale, delay) are
differentiated on the simulated states directly, with no simulation at all: the delay as a
forward step sees the linear interpolation, on the segment left of each shifted sample. The start
state's z0 follows the candidate's own force balance (rank.initial_for), whose derivative is the
initial sensitivity.

:func:`fit_jacobian` returns None where this does not reach (an exciter model, a parameter that is
neither, the forward differences' switch recon.output_error.problem.JACOBIAN); the fit then takes
forward differences.
"""
from __future__ import annotations

import math

import numpy as np

from recon.output_error import problem
from recon.simulation.rk4 import I_C2, I_DRIFT, I_G, I_KC, I_MU, I_V0, I_W2, kernel_input
from recon.simulation.sensitivity import (FEATURES, X_COLUMNS, column_codes, extended_column_codes,
                                          simulate_extended_sensitivities, simulate_plain_sensitivities)
from shakerlab.run_data import BASE

# the parameter keys of a fit whose column comes from the simulation's sensitivities: the kernel slot
SIMULATED = {"c_m": "c", "k_m": "k", "alpha_m": "alpha", "gamma": "gamma", "delta": "delta", "inv_m": "g",
             **{f"x:{name}": name for name in X_COLUMNS if name not in ("g", "c", "k", "alpha", "gamma", "delta")}}
READING = ("x:phi2", "x:tip_scale", "x:delay")


def supported(am, keys: list[str]) -> bool:
    """Whether :func:`fit_jacobian` covers a fit of ``keys`` on ``am``."""
    return (problem.JACOBIAN == "sensitivities" and not am.baseline.has_drive
            and all(k in SIMULATED or k in READING or k.startswith("fn:") for k in keys))


def shift_columns(S: np.ndarray, delay: float, dt: float) -> np.ndarray:
    """Each column of S shifted as augmented.shift shifts a signal (linear interpolation at
    k - delay/dt, the ends held)."""
    if delay == 0.0:
        return S
    n = S.shape[0]
    idx = np.clip(np.arange(n) - delay / dt, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(idx).astype(np.int64), n - 2)
    frac = (idx - i0)[:, None]
    # S[i0] * (1 - frac) + S[i0 + 1] * frac, each product in its own gathered copy (a rows x
    # columns array fewer at once)
    out = S[i0]
    out *= 1.0 - frac
    right = S[i0 + 1]
    right *= frac
    out += right
    return out


def delay_derivative(x: np.ndarray, delay: float, dt: float) -> np.ndarray:
    """d shift(x, delay) / d delay as a forward step in the delay sees it: -(slope of the segment
    left of k - delay/dt) / dt; 0 where the shifted index is held at an end."""
    n = x.size
    idx = np.arange(n) - delay / dt
    i1 = np.ceil(idx).astype(np.int64)          # the segment (i1 - 1, i1] the index falls back into
    inside = (i1 >= 1) & (i1 <= n - 1)
    out = np.zeros(n)
    j = i1[inside]
    out[inside] = -(x[j] - x[j - 1]) / dt
    return out


def fit_jacobian(build, keys: list[str], scales: np.ndarray, data: list, initial_for, fit_scale, am):
    """The Jacobian callable of rank.fit's residual (``build``: scaled parameters -> model, ``data``:
    the stages as the fit takes them, ``initial_for`` and ``fit_scale``: rank's, which this module
    does not import), or None where it does not reach (module doc)."""
    if not keys or not supported(am, keys):
        return None
    stages = [d for d in data if d.fit.any()]
    if any(d.order not in (0, 1) for d in stages):
        return None
    rows = sum(int(d.fit.sum()) for d in stages)

    def jacobian(p) -> np.ndarray:
        m = build(p)
        base = m.baseline
        coef, pe, re = base.fn_arrays()
        fn_index = {k: j for j, k in enumerate(base.fn_m)}
        sim_cols = [c for c, k in enumerate(keys) if k not in READING]
        names = [fn_index[keys[c][3:]] if keys[c].startswith("fn:") else SIMULATED[keys[c]] for c in sim_cols]
        P = m.kernel_vector()
        # no extra physics switched on and no column of one: the plain model's kernel, about a third
        # of the extended one's cost, gives the same states and columns
        plain = (P[I_MU] == 0.0 and P[I_C2] == 0.0 and P[I_KC] == 0.0 and P[I_DRIFT] == 0.0 and P[I_W2] <= 0.0
                 and all(isinstance(nm, int) or nm in FEATURES for nm in names))
        if plain:
            fi, eq = column_codes(names)
        else:
            codes = extended_column_codes(names)
        # friction's features where mu = 0 use the smoothing velocity it would be simulated with
        P[I_V0] = m.get("v0") if m.get("v0") > 0.0 else (m.friction_v0() or 1e-4)
        force = base.excitation != BASE
        phi2, scale, delay = m.get("phi2"), 1.0 + m.get("tip_scale"), m.get("delay")
        def stage_columns(job):
            d, at = job    # the stage and its first row in the whole Jacobian
            dt = d.dt
            u = base.drive(np.asarray(d.u, float), dt)
            y0, v0, z0 = (float(v) for v in initial_for(m, d))
            S0 = np.zeros((5, len(names)))
            if _balanced(m, d):
                for col, name in enumerate(names):
                    S0[2, col] = _balance_partial(base, name, float(d.u[0]), y0, v0, pe, re)
            # the columns the reading sees, sy + phi2 sq, formed in place in the kernel's own arrays:
            # at a 10 kHz stage each rows x columns array is ~10 MiB, a few at once
            if plain:
                st3, sy = simulate_plain_sensitivities(kernel_input(u), dt, int(m.substeps(dt, d.step_factor)), P[I_G],
                                                       base.c_m, base.k_m, base.alpha_m, base.gamma, base.delta,
                                                       coef, pe, re, y0, v0, z0, fi, eq, S0[:3].copy(),
                                                       int(d.order))
                st = np.zeros((5, st3.shape[1]))
                st[:3] = st3
                read_cols = sy          # the plain kernel has no sq: sy + phi2 sq is sy
            else:
                st, sy, read_cols = simulate_extended_sensitivities(kernel_input(u), float(d.t[0]), dt,
                                                                    int(m.substeps(dt, d.step_factor)), P, coef, pe, re, y0, v0,
                                                                    z0, codes, S0, int(d.order), force)
                read_cols *= phi2
                read_cols += sy
            del sy
            if not np.all(np.isfinite(st[d.order])):
                return None
            J = np.zeros((d.t.size, len(keys)))
            read_cols = shift_columns(read_cols, delay, dt)
            read_cols *= scale
            J[:, sim_cols] = read_cols
            del read_cols
            read = st[d.order] + phi2 * st[3 + d.order]
            motion = read + d.x_in if (d.x_in is not None and not force) else read
            for c, k in enumerate(keys):
                if k == "x:phi2":
                    J[:, c] = scale * shift_columns(st[3 + d.order][:, None], delay, dt)[:, 0]
                elif k == "x:tip_scale":
                    J[:, c] = shift_columns(motion[:, None], delay, dt)[:, 0]
                elif k == "x:delay":
                    J[:, c] = scale * delay_derivative(motion, delay, dt)
            J = J[d.fit]
            if d.order:
                J -= J.mean(axis=0)        # the velocity's constant, fitted over the fitting samples
            w = 1.0 / (fit_scale(d) * math.sqrt(max(int(d.fit.sum()), 1)))
            # the weighted rows written into this stage's block of the whole Jacobian
            np.multiply(J, w * scales, out=whole[at:at + J.shape[0]])
            return True

        # the stages one after the other, each writing its own rows of one array. Not on the fits'
        # threads (recon.threads): a stage's pass is a few milliseconds, the stages are unequal
        # (the nonlinear one often several times the linear one) and the residual between two
        # Jacobians is serial, so side by side they cost 21 % more CPU and saved no wall time
        # (diagnose c02, 3 paired runs on 2 cores)
        whole = np.empty((rows, len(keys)))
        firsts = np.cumsum([0] + [int(d.fit.sum()) for d in stages[:-1]])
        done = [stage_columns(job) for job in zip(stages, firsts)]
        if any(ok is None for ok in done):
            return np.zeros((rows, len(keys)))
        return whole

    return jacobian


def _balanced(am, d) -> bool:
    """Whether rank.initial_for gives ``am`` its own z0 from the force balance (the start then moves
    with the baseline's parameters)."""
    s0, base = d.initial, d.start_model
    if am.baseline.alpha_m == 0.0 and s0[2] != 0.0:
        return False
    if base is None or base.alpha_m == 0.0 or am.baseline.alpha_m == 0.0 or am.baseline is base:
        return False
    y0, v0, _ = (float(v) for v in s0)
    with np.errstate(all="ignore"):
        dz = am.baseline.balance(float(d.u[0]), y0, v0, 0.0) - base.balance(float(d.u[0]), y0, v0, 0.0)
    return math.isfinite(dz)


def _balance_partial(model, name, u0: float, y0: float, v0: float, pe, re) -> float:
    """d/dtheta of model.balance(u0, y0, v0, 0) = g (u0 - offset) - c v0 - k y0 - fn(y0, v0)."""
    if isinstance(name, (int, np.integer)):
        return -(y0 ** int(pe[name]) * v0 ** int(re[name]))
    if name == "g":
        return u0 - (model.input_offset or 0.0)
    return {"c": -v0, "k": -y0}.get(name, 0.0)

"""Fast simulation of the identified SDOF hysteretic model (numba, RK4).

    y'' = g*u - c*y' - k*y - sum_j a_j y^p_j y'^r_j - z
    z'  = alpha*y' - gamma*|y'|*z - delta*y'*|z|

``u`` is sampled at the recording rate; between samples it is interpolated
linearly (RK4 half steps use the mid-point value). When the sampling is coarse
compared with the model's time scales, each sample interval is split into
``n_sub`` RK4 sub-steps. Zero initial conditions unless (y0, v0, z0) are given.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _rhs(y, v, z, u, g, c, k, alpha, gamma, delta, coef, p, r):
    fn = 0.0
    for j in range(coef.size):
        fn += coef[j] * y ** p[j] * v ** r[j]
    acc = g * u - c * v - k * y - fn - z
    dz = alpha * v - gamma * abs(v) * z - delta * v * abs(z)
    return v, acc, dz


@njit(cache=True)
def simulate_sdof(u, dt, n_sub, g, c, k, alpha, gamma, delta, coef, p, r, y0=0.0, v0=0.0, z0=0.0):
    n = u.size
    ys = np.zeros(n)
    vs = np.zeros(n)
    zs = np.zeros(n)
    y = y0
    v = v0
    z = z0
    ys[0] = y0
    vs[0] = v0
    zs[0] = z0
    h = dt / n_sub
    for i in range(n - 1):
        u0 = u[i]
        du = (u[i + 1] - u[i]) / n_sub
        for s in range(n_sub):
            ua = u0 + du * s
            um = ua + 0.5 * du
            ub = ua + du
            k1y, k1v, k1z = _rhs(y, v, z, ua, g, c, k, alpha, gamma, delta, coef, p, r)
            k2y, k2v, k2z = _rhs(y + 0.5 * h * k1y, v + 0.5 * h * k1v, z + 0.5 * h * k1z, um,
                                 g, c, k, alpha, gamma, delta, coef, p, r)
            k3y, k3v, k3z = _rhs(y + 0.5 * h * k2y, v + 0.5 * h * k2v, z + 0.5 * h * k2z, um,
                                 g, c, k, alpha, gamma, delta, coef, p, r)
            k4y, k4v, k4z = _rhs(y + h * k3y, v + h * k3v, z + h * k3z, ub,
                                 g, c, k, alpha, gamma, delta, coef, p, r)
            y += h / 6.0 * (k1y + 2 * k2y + 2 * k3y + k4y)
            v += h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
            z += h / 6.0 * (k1z + 2 * k2z + 2 * k3z + k4z)
        if not (math.isfinite(y) and math.isfinite(v) and math.isfinite(z)):
            ys[i + 1:] = np.nan
            vs[i + 1:] = np.nan
            zs[i + 1:] = np.nan
            return ys, vs, zs
        ys[i + 1] = y
        vs[i + 1] = v
        zs[i + 1] = z
    return ys, vs, zs


def substeps(dt: float, k_total: float, steps_per_period: int = 64) -> int:
    """RK4 sub-steps per sample so that a natural period gets ``steps_per_period`` steps."""
    if k_total <= 0:
        return 1
    period = 2 * math.pi / math.sqrt(k_total)
    return max(1, int(math.ceil(dt * steps_per_period / period)))

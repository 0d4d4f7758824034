"""Forward sensitivities of the plain SDOF model: the output-error fits' Jacobian in one pass.

The plain model (recon.simulation.rk4, no extras), per unit mass,

    y'' = g (u - u_off) - c y' - k y - sum_j a_j y^p_j y'^r_j - z
    z'  = alpha y' - gamma |y'| z - delta y' |z|

is integrated by RK4 together with its variational equations

    S' = (df/dx) S + df/dtheta,     S = dx/dtheta,  x = (y, y', z),

using the same four stages as the states, so S is the exact derivative of the discrete
simulation (to rounding): differentiating an explicit Runge-Kutta step gives the same stages
applied to the variational equations. One pass gives the states and every column, where a
forward-difference Jacobian needs one more simulation per parameter. The |.| are differentiated
on the side they are evaluated at, as a forward difference with a small step sees them.

A column's source df/dtheta is one of the features evaluated at each stage (``FEATURES``):
g multiplies the input, c the velocity, k the displacement, alpha/gamma/delta the three terms
of z', a_j its monomial, and the input offset enters as -g. Each column names its feature and
its equation (the acceleration's or z's), so the column loop has no branches: per step and
stage it costs a few multiply-adds per column, a fraction of a simulation.

The start (y0, y0', z0) may depend on theta (z0 balances the equation of motion at the first
sample for each trial parameter set, HystereticModel.start_z): its derivative is the initial
sensitivity S0.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from recon.simulation.powers import ipow
from recon.simulation.rk4 import cubic_weights

# the features a column's source is one of: index, equation (0: y'', 1: z')
FEATURES = {"g": (0, 0), "c": (1, 0), "k": (2, 0), "alpha": (3, 1), "gamma": (4, 1), "delta": (5, 1),
            "offset": (6, 0)}
N_FIXED = 7          # fn term j is feature N_FIXED + j, in the acceleration's equation


def column_codes(names: list) -> tuple[np.ndarray, np.ndarray]:
    """(feature index, equation) arrays for columns named as in ``FEATURES`` or by an int j (the
    j-th fn term of the kernel's coefficient arrays)."""
    fi = np.empty(len(names), np.int64)
    eq = np.empty(len(names), np.float64)
    for c, name in enumerate(names):
        if isinstance(name, (int, np.integer)):
            fi[c], eq[c] = N_FIXED + int(name), 0.0
        else:
            if name not in FEATURES:
                raise ValueError(f"sensitivity column {name!r}: not one of {sorted(FEATURES)} or an fn term index")
            fi[c], eq[c] = FEATURES[name][0], float(FEATURES[name][1])
    return fi, eq


@njit(cache=True, nogil=True, inline="always")
def _stage(y, v, z, u, g, c, k, alpha, gamma, delta, coef, p, r, F):
    """(acc, dz, a_y, a_v, dz_v, dz_z) at one RK stage; the features into F."""
    fn = 0.0
    fn_y = 0.0
    fn_v = 0.0
    for j in range(coef.size):
        mono = ipow(y, p[j]) * ipow(v, r[j])
        fn += coef[j] * mono
        F[N_FIXED + j] = -mono
        if p[j] > 0:
            fn_y += coef[j] * p[j] * ipow(y, p[j] - 1) * ipow(v, r[j])
        if r[j] > 0:
            fn_v += coef[j] * r[j] * ipow(y, p[j]) * ipow(v, r[j] - 1)
    av = abs(v)
    az = abs(z)
    sv = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)
    sz = 1.0 if z > 0.0 else (-1.0 if z < 0.0 else 0.0)
    acc = g * u - c * v - k * y - fn - z
    dz = alpha * v - gamma * av * z - delta * v * az
    F[0] = u
    F[1] = -v
    F[2] = -y
    F[3] = v
    F[4] = -av * z
    F[5] = -v * az
    F[6] = -g
    return acc, dz, -k - fn_y, -c - fn_v, alpha - gamma * sv * z - delta * az, -gamma * av - delta * v * sz


@njit(cache=True, nogil=True)
def simulate_plain_sensitivities(u, dt, n_sub, g, c, k, alpha, gamma, delta, coef, p, r, y0, v0, z0,
                                 fi, eq, S0, order):
    """States (y, y', z) as a (3, n) array and the sensitivities of y (``order`` 0) or y' (1) to
    the columns (fi, eq) of :func:`column_codes`, an (n, m) array, from the initial sensitivities
    S0 (3 x m: of y, y', z at the first sample). ``u`` is the input the model sees (any offset
    already taken out). NaN from the first non-finite step on."""
    n = u.size
    m = fi.size
    nf = N_FIXED + coef.size
    out = np.zeros((3, n))
    sens = np.zeros((n, m))
    F1 = np.zeros(nf)
    F2 = np.zeros(nf)
    F3 = np.zeros(nf)
    F4 = np.zeros(nf)
    s0 = np.empty(m)
    s1 = np.empty(m)
    s2 = np.empty(m)
    wa = np.empty(m)
    for col in range(m):
        s0[col] = S0[0, col]
        s1[col] = S0[1, col]
        s2[col] = S0[2, col]
        wa[col] = 1.0 - eq[col]
        sens[0, col] = S0[order, col]
    y = y0
    v = v0
    z = z0
    out[0, 0] = y0
    out[1, 0] = v0
    out[2, 0] = z0
    h = dt / n_sub
    W = cubic_weights(n_sub)
    for i in range(n - 1):
        um1 = u[i - 1] if i > 0 else 2.0 * u[0] - u[1]
        up2 = u[i + 2] if i + 2 < n else 2.0 * u[n - 1] - u[n - 2]
        for sub in range(n_sub):
            jw = 2 * sub
            ua = W[jw, 0] * um1 + W[jw, 1] * u[i] + W[jw, 2] * u[i + 1] + W[jw, 3] * up2
            um = W[jw + 1, 0] * um1 + W[jw + 1, 1] * u[i] + W[jw + 1, 2] * u[i + 1] + W[jw + 1, 3] * up2
            ue = W[jw + 2, 0] * um1 + W[jw + 2, 1] * u[i] + W[jw + 2, 2] * u[i + 1] + W[jw + 2, 3] * up2
            a1, z1, ay1, av1, zv1, zz1 = _stage(y, v, z, ua, g, c, k, alpha, gamma, delta, coef, p, r, F1)
            y2 = y + 0.5 * h * v
            v2 = v + 0.5 * h * a1
            zs2 = z + 0.5 * h * z1
            a2, z2, ay2, av2, zv2, zz2 = _stage(y2, v2, zs2, um, g, c, k, alpha, gamma, delta, coef, p, r, F2)
            y3 = y + 0.5 * h * v2
            v3 = v + 0.5 * h * a2
            zs3 = z + 0.5 * h * z2
            a3, z3, ay3, av3, zv3, zz3 = _stage(y3, v3, zs3, um, g, c, k, alpha, gamma, delta, coef, p, r, F3)
            y4 = y + h * v3
            v4 = v + h * a3
            zs4 = z + h * z3
            a4, z4, ay4, av4, zv4, zz4 = _stage(y4, v4, zs4, ue, g, c, k, alpha, gamma, delta, coef, p, r, F4)
            for col in range(m):
                f = fi[col]
                w_a = wa[col]
                w_z = 1.0 - w_a
                b0 = s0[col]
                b1 = s1[col]
                b2 = s2[col]
                x1 = F1[f]
                k10 = b1
                k11 = ay1 * b0 + av1 * b1 - b2 + w_a * x1
                k12 = zv1 * b1 + zz1 * b2 + w_z * x1
                t0 = b0 + 0.5 * h * k10
                t1 = b1 + 0.5 * h * k11
                t2 = b2 + 0.5 * h * k12
                x2 = F2[f]
                k20 = t1
                k21 = ay2 * t0 + av2 * t1 - t2 + w_a * x2
                k22 = zv2 * t1 + zz2 * t2 + w_z * x2
                t0 = b0 + 0.5 * h * k20
                t1 = b1 + 0.5 * h * k21
                t2 = b2 + 0.5 * h * k22
                x3 = F3[f]
                k30 = t1
                k31 = ay3 * t0 + av3 * t1 - t2 + w_a * x3
                k32 = zv3 * t1 + zz3 * t2 + w_z * x3
                t0 = b0 + h * k30
                t1 = b1 + h * k31
                t2 = b2 + h * k32
                x4 = F4[f]
                k40 = t1
                k41 = ay4 * t0 + av4 * t1 - t2 + w_a * x4
                k42 = zv4 * t1 + zz4 * t2 + w_z * x4
                s0[col] = b0 + h / 6.0 * (k10 + 2.0 * k20 + 2.0 * k30 + k40)
                s1[col] = b1 + h / 6.0 * (k11 + 2.0 * k21 + 2.0 * k31 + k41)
                s2[col] = b2 + h / 6.0 * (k12 + 2.0 * k22 + 2.0 * k32 + k42)
            y += h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v += h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            z += h / 6.0 * (z1 + 2.0 * z2 + 2.0 * z3 + z4)
        if not (math.isfinite(y) and math.isfinite(v) and math.isfinite(z)):
            out[:, i + 1:] = np.nan
            sens[i + 1:, :] = np.nan
            return out, sens
        out[0, i + 1] = y
        out[1, i + 1] = v
        out[2, i + 1] = z
        if order == 0:
            for col in range(m):
                sens[i + 1, col] = s0[col]
        else:
            for col in range(m):
                sens[i + 1, col] = s1[col]
    return out, sens

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
from recon.simulation.rk4 import (I_ALPHA, I_C, I_C2, I_DELTA, I_DRIFT, I_DRIVE2, I_G, I_GAMMA, I_GAP, I_GU2, I_K, I_KC,
                                  I_MU, I_SIDE, I_V0, I_W2, I_ZETA2, cubic_weights, substep_inputs)

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
def _fn_terms(y, v, coef, p, r, F, first):
    """(fn, dfn/dy, dfn/dy') of the fn terms sum_j coef_j y^p_j y'^r_j at one RK stage; each
    term's feature -y^p_j y'^r_j into F[first + j]. Each power is taken once (the same products
    as taken apart: the same bits)."""
    fn = 0.0
    fn_y = 0.0
    fn_v = 0.0
    for j in range(coef.size):
        yp = ipow(y, p[j])
        vr = ipow(v, r[j])
        mono = yp * vr
        fn += coef[j] * mono
        F[first + j] = -mono
        if p[j] > 0:
            fn_y += coef[j] * p[j] * ipow(y, p[j] - 1) * vr
        if r[j] > 0:
            fn_v += coef[j] * r[j] * yp * ipow(v, r[j] - 1)
    return fn, fn_y, fn_v


@njit(cache=True, nogil=True, inline="always")
def _stage(y, v, z, u, g, c, k, alpha, gamma, delta, coef, p, r, F):
    """(acc, dz, a_y, a_v, dz_v, dz_z) at one RK stage; the features into F."""
    fn, fn_y, fn_v = _fn_terms(y, v, coef, p, r, F, N_FIXED)
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
    G1 = np.empty(m)
    G2 = np.empty(m)
    G3 = np.empty(m)
    G4 = np.empty(m)
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
        for sub in range(n_sub):
            ua, um, ue = substep_inputs(u, i, sub, W)
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
            for col in range(m):       # the columns' sources, gathered first: the loop below has
                f = fi[col]            # no indirect reads and the compiler can vectorise it
                G1[col] = F1[f]
                G2[col] = F2[f]
                G3[col] = F3[f]
                G4[col] = F4[f]
            for col in range(m):
                w_a = wa[col]
                w_z = 1.0 - w_a
                b0 = s0[col]
                b1 = s1[col]
                b2 = s2[col]
                x1 = G1[col]
                k10 = b1
                k11 = ay1 * b0 + av1 * b1 - b2 + w_a * x1
                k12 = zv1 * b1 + zz1 * b2 + w_z * x1
                t0 = b0 + 0.5 * h * k10
                t1 = b1 + 0.5 * h * k11
                t2 = b2 + 0.5 * h * k12
                x2 = G2[col]
                k20 = t1
                k21 = ay2 * t0 + av2 * t1 - t2 + w_a * x2
                k22 = zv2 * t1 + zz2 * t2 + w_z * x2
                t0 = b0 + 0.5 * h * k20
                t1 = b1 + 0.5 * h * k21
                t2 = b2 + 0.5 * h * k22
                x3 = G3[col]
                k30 = t1
                k31 = ay3 * t0 + av3 * t1 - t2 + w_a * x3
                k32 = zv3 * t1 + zz3 * t2 + w_z * x3
                t0 = b0 + h * k30
                t1 = b1 + h * k31
                t2 = b2 + h * k32
                x4 = G4[col]
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


# ----------------------------------------------------------------------------- the extended model
# The same scheme for the extended kernel (recon.simulation.rk4.simulate_extended: friction,
# quadratic damping, contact, stiffness drift and a higher mode q beside the plain model), whose
# states are (y, y', z, q, q'). A column's source may act on three equations at once (the input
# gain drives both y'' and the higher mode), so each column names one feature per equation:
# (acceleration, z', q''), feature 0 being zero. The higher mode's drive holds -drive2 y'', so q''
# depends on the parameters also through y'': the kernel adds -drive2 times the acceleration's
# own variation, as it does for the states.
XF = {"zero": 0, "g": 1, "c": 2, "k": 3, "alpha": 4, "gamma": 5, "delta": 6, "mu": 7, "v0": 8, "c2": 9,
      "kc": 10, "gap": 11, "drift": 12, "g_q": 13, "w2": 14, "zeta2": 15, "drive2": 16}
XN_FIXED = len(XF)       # fn term j is feature XN_FIXED + j (in the acceleration's equation)
# the kernel slots a column may be taken by, and its feature in each equation (acc, z', q'')
X_COLUMNS = {"g": ("g", "zero", "g_q"), "c": ("c", "zero", "zero"), "k": ("k", "zero", "zero"),
             "alpha": ("zero", "alpha", "zero"), "gamma": ("zero", "gamma", "zero"),
             "delta": ("zero", "delta", "zero"), "mu": ("mu", "zero", "zero"), "v0": ("v0", "zero", "zero"),
             "c2": ("c2", "zero", "zero"), "kc": ("kc", "zero", "zero"), "gap": ("gap", "zero", "zero"),
             "drift": ("drift", "zero", "zero"), "w2": ("zero", "zero", "w2"),
             "zeta2": ("zero", "zero", "zeta2"), "drive2": ("zero", "zero", "drive2")}


def extended_column_codes(names: list) -> np.ndarray:
    """(m, 3) feature indices (acc, z', q'') of columns named as kernel slots in ``X_COLUMNS`` or
    by an int j (the j-th fn term)."""
    out = np.zeros((len(names), 3), np.int64)
    for c, name in enumerate(names):
        if isinstance(name, (int, np.integer)):
            out[c] = (XN_FIXED + int(name), 0, 0)
        elif name in X_COLUMNS:
            out[c] = [XF[f] for f in X_COLUMNS[name]]
        else:
            raise ValueError(f"sensitivity column {name!r}: not one of {sorted(X_COLUMNS)} or an fn term index")
    return out


@njit(cache=True, nogil=True, inline="always")
def _xstage(y, v, z, q, w, t, u, pg, pc, pk, palpha, pgamma, pdelta, pmu, pv0, pc2, pkc, pgap, pside, pdrift,
            pw2, pzeta2, pdrive2, pgu2,
            coef, p, r, force, friction, F):
    """(acc, dz, aq, a_y, a_v, dz_v, dz_z, aq_q, aq_w, aq_acc) at one RK stage of the extended
    model (recon.simulation.rk4._rhs), then its fixed features (XF) as a tuple; the fn terms'
    features into F. ``friction``: friction is on or a column needs its features (else they stay 0
    and no tanh is taken). The fixed features are returned as values, not stored into an array:
    stored, each of the 17 stores per stage is a write the compiler must assume may alias the
    kernel's other arrays, and the kernel ran 3.5 times slower (the same numbers)."""
    fn, fn_y, fn_v = _fn_terms(y, v, coef, p, r, F, XN_FIXED)
    f7 = 0.0
    f8 = 0.0
    g = pg
    k0 = pk
    kt = k0
    if pdrift != 0.0:
        kt = k0 * (1.0 + pdrift * t)
    gu = g * u
    acc = gu - pc * v - kt * y - fn - z
    a_y = -kt - fn_y
    a_v = -pc - fn_v
    f1 = u
    f2 = -v
    f3 = -(1.0 + pdrift * t) * y
    # friction: its features also where mu = 0 (a fit from mu = 0 moves it), with v0 as the caller
    # set it (the smoothing velocity friction would be simulated with)
    if friction:
        v0s = pv0
        th = math.tanh(v / v0s)
        f7 = -th
        f8 = pmu * (1.0 - th * th) * v / (v0s * v0s)
        if pmu != 0.0:
            acc -= pmu * th
            a_v -= pmu * (1.0 - th * th) / v0s
    if pc2 != 0.0:
        acc -= pc2 * v * abs(v)
        a_v -= 2.0 * pc2 * abs(v)
    f9 = -v * abs(v)
    f10 = 0.0
    f11 = 0.0
    d = pside * y - pgap
    if d > 0.0:
        f10 = -pside * d
        if pkc != 0.0:
            acc -= pside * pkc * d
            a_y -= pkc * pside * pside
            f11 = pside * pkc
    f12 = -k0 * t * y
    av = abs(v)
    az = abs(z)
    sv = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)
    sz = 1.0 if z > 0.0 else (-1.0 if z < 0.0 else 0.0)
    dz = palpha * v - pgamma * av * z - pdelta * v * az
    f4 = v
    f5 = -av * z
    f6 = -v * az
    aq = 0.0
    aq_q = 0.0
    aq_w = 0.0
    aq_acc = 0.0
    f13 = 0.0
    f14 = 0.0
    f15 = 0.0
    f16 = 0.0
    if pw2 > 0.0:
        drive = gu
        f13 = u
        if pdrive2 != 0.0:
            drive = pgu2 * gu - pdrive2 * acc
            aq_acc = -pdrive2
            f13 = pgu2 * u
        # d/d drive2 of the drive; under force excitation gu2 = 1 - drive2 moves with it
        f16 = -acc - (gu if force else 0.0)
        aq = drive - 2.0 * pzeta2 * pw2 * w - pw2 * pw2 * q
        aq_q = -pw2 * pw2
        aq_w = -2.0 * pzeta2 * pw2
        f14 = -2.0 * pzeta2 * w - 2.0 * pw2 * q
        f15 = -2.0 * pw2 * w
    return acc, dz, aq, a_y, a_v, palpha - pgamma * sv * z - pdelta * az, \
        -pgamma * av - pdelta * v * sz, aq_q, aq_w, aq_acc, \
        (0.0, f1, f2, f3, f4, f5, f6, f7, f8, f9, f10, f11, f12, f13, f14, f15, f16)


@njit(cache=True, nogil=True, inline="always")
def _pick(T, F, code):
    """Feature ``code`` of one stage: a fixed one from :func:`_xstage`'s tuple ``T``, an fn term's from ``F``."""
    if code < XN_FIXED:
        return T[code]
    return F[code]


@njit(cache=True, nogil=True)
def simulate_extended_sensitivities(u, t0, dt, n_sub, P, coef, p, r, y0, v0, z0, codes, S0, order, force):
    """:func:`recon.simulation.rk4.simulate_extended`'s states (5, n) and the sensitivities of
    y and q (``order`` 0) or of y' and q' (1) to the columns ``codes`` (extended_column_codes), two
    (n, m) arrays, from the initial sensitivities S0 (5 x m: of y, y', z, q, q'; the higher mode
    starts at rest, so its rows are 0). ``force``: force excitation (the higher mode's input share
    is 1 - drive2). NaN from the first non-finite step on."""
    n = u.size
    m = codes.shape[0]
    nf = XN_FIXED + coef.size
    out = np.zeros((5, n))
    sy = np.zeros((n, m))
    sq = np.zeros((n, m))
    F1 = np.zeros(nf)
    F2 = np.zeros(nf)
    F3 = np.zeros(nf)
    F4 = np.zeros(nf)
    s0 = np.empty(m)
    s1 = np.empty(m)
    s2 = np.empty(m)
    s3 = np.empty(m)
    s4 = np.empty(m)
    for col in range(m):
        s0[col] = S0[0, col]
        s1[col] = S0[1, col]
        s2[col] = S0[2, col]
        s3[col] = S0[3, col]
        s4[col] = S0[4, col]
        sy[0, col] = S0[order, col]
        sq[0, col] = S0[3 + order, col]
    fa_ = np.empty(m, np.int64)
    fz_ = np.empty(m, np.int64)
    fq_ = np.empty(m, np.int64)
    pg, pc, pk, palpha, pgamma, pdelta = P[I_G], P[I_C], P[I_K], P[I_ALPHA], P[I_GAMMA], P[I_DELTA]
    pmu, pv0, pc2, pkc, pgap, pside, pdrift = P[I_MU], P[I_V0], P[I_C2], P[I_KC], P[I_GAP], P[I_SIDE], P[I_DRIFT]
    pw2, pzeta2, pdrive2, pgu2 = P[I_W2], P[I_ZETA2], P[I_DRIVE2], P[I_GU2]
    friction = P[I_MU] != 0.0
    for col in range(m):
        fa_[col] = codes[col, 0]
        fz_[col] = codes[col, 1]
        fq_[col] = codes[col, 2]
        if codes[col, 0] == 7 or codes[col, 0] == 8:
            friction = True
    y = y0
    v = v0
    z = z0
    q = 0.0
    w = 0.0
    out[0, 0] = y0
    out[1, 0] = v0
    out[2, 0] = z0
    h = dt / n_sub
    mode = P[I_W2] > 0.0
    W = cubic_weights(n_sub)
    for i in range(n - 1):
        for sub in range(n_sub):
            ta = t0 + i * dt + sub * h
            tm = ta + 0.5 * h
            te = ta + h
            ua, um, ue = substep_inputs(u, i, sub, W)
            a1, z1, q1, ay1, av1, zv1, zz1, qq1, qw1, qc1, T1 = _xstage(y, v, z, q, w, ta, ua, pg, pc, pk, palpha, pgamma, pdelta, pmu, pv0, pc2, pkc, pgap, pside, pdrift, pw2, pzeta2, pdrive2, pgu2,
                coef, p, r, force,
                                                                    friction, F1)
            y2 = y + 0.5 * h * v
            v2 = v + 0.5 * h * a1
            zs2 = z + 0.5 * h * z1
            q2 = q + 0.5 * h * w
            w2 = w + 0.5 * h * q1
            a2, z2, qa2, ay2, av2, zv2, zz2, qq2, qw2, qc2, T2 = _xstage(y2, v2, zs2, q2, w2, tm, um, pg, pc, pk, palpha, pgamma, pdelta, pmu, pv0, pc2, pkc, pgap, pside, pdrift, pw2, pzeta2, pdrive2, pgu2,
                coef, p, r,
                                                                    force, friction, F2)
            y3 = y + 0.5 * h * v2
            v3 = v + 0.5 * h * a2
            zs3 = z + 0.5 * h * z2
            q3 = q + 0.5 * h * (w + 0.5 * h * q1)
            w3 = w + 0.5 * h * qa2
            a3, z3, qa3, ay3, av3, zv3, zz3, qq3, qw3, qc3, T3 = _xstage(y3, v3, zs3, q3, w3, tm, um, pg, pc, pk, palpha, pgamma, pdelta, pmu, pv0, pc2, pkc, pgap, pside, pdrift, pw2, pzeta2, pdrive2, pgu2,
                coef, p, r,
                                                                    force, friction, F3)
            y4 = y + h * v3
            v4 = v + h * a3
            zs4 = z + h * z3
            q4 = q + h * (w + 0.5 * h * qa2)
            w4 = w + h * qa3
            a4, z4, qa4, ay4, av4, zv4, zz4, qq4, qw4, qc4, T4 = _xstage(y4, v4, zs4, q4, w4, te, ue, pg, pc, pk, palpha, pgamma, pdelta, pmu, pv0, pc2, pkc, pgap, pside, pdrift, pw2, pzeta2, pdrive2, pgu2,
                coef, p, r,
                                                                    force, friction, F4)
            for col in range(m):
                fa = fa_[col]
                fz = fz_[col]
                b0 = s0[col]
                b1 = s1[col]
                b2 = s2[col]
                k10 = b1
                k11 = ay1 * b0 + av1 * b1 - b2 + _pick(T1, F1, fa)
                k12 = zv1 * b1 + zz1 * b2 + _pick(T1, F1, fz)
                t0_ = b0 + 0.5 * h * k10
                t1_ = b1 + 0.5 * h * k11
                t2_ = b2 + 0.5 * h * k12
                k20 = t1_
                k21 = ay2 * t0_ + av2 * t1_ - t2_ + _pick(T2, F2, fa)
                k22 = zv2 * t1_ + zz2 * t2_ + _pick(T2, F2, fz)
                t0_ = b0 + 0.5 * h * k20
                t1_ = b1 + 0.5 * h * k21
                t2_ = b2 + 0.5 * h * k22
                k30 = t1_
                k31 = ay3 * t0_ + av3 * t1_ - t2_ + _pick(T3, F3, fa)
                k32 = zv3 * t1_ + zz3 * t2_ + _pick(T3, F3, fz)
                t0_ = b0 + h * k30
                t1_ = b1 + h * k31
                t2_ = b2 + h * k32
                k40 = t1_
                k41 = ay4 * t0_ + av4 * t1_ - t2_ + _pick(T4, F4, fa)
                k42 = zv4 * t1_ + zz4 * t2_ + _pick(T4, F4, fz)
                s0[col] = b0 + h / 6.0 * (k10 + 2.0 * k20 + 2.0 * k30 + k40)
                s1[col] = b1 + h / 6.0 * (k11 + 2.0 * k21 + 2.0 * k31 + k41)
                s2[col] = b2 + h / 6.0 * (k12 + 2.0 * k22 + 2.0 * k32 + k42)
                if mode:   # the higher mode (its drive holds -drive2 y'': the k*1 terms)
                    fq = fq_[col]
                    b3 = s3[col]
                    b4 = s4[col]
                    k13 = b4
                    k14 = qq1 * b3 + qw1 * b4 + qc1 * k11 + _pick(T1, F1, fq)
                    t3_ = b3 + 0.5 * h * k13
                    t4_ = b4 + 0.5 * h * k14
                    k23 = t4_
                    k24 = qq2 * t3_ + qw2 * t4_ + qc2 * k21 + _pick(T2, F2, fq)
                    t3_ = b3 + 0.5 * h * k23
                    t4_ = b4 + 0.5 * h * k24
                    k33 = t4_
                    k34 = qq3 * t3_ + qw3 * t4_ + qc3 * k31 + _pick(T3, F3, fq)
                    t3_ = b3 + h * k33
                    t4_ = b4 + h * k34
                    k43 = t4_
                    k44 = qq4 * t3_ + qw4 * t4_ + qc4 * k41 + _pick(T4, F4, fq)
                    s3[col] = b3 + h / 6.0 * (k13 + 2.0 * k23 + 2.0 * k33 + k43)
                    s4[col] = b4 + h / 6.0 * (k14 + 2.0 * k24 + 2.0 * k34 + k44)
            y += h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v += h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            z += h / 6.0 * (z1 + 2.0 * z2 + 2.0 * z3 + z4)
            if mode:
                w2m = w + 0.5 * h * q1
                w3m = w + 0.5 * h * qa2
                w4m = w + h * qa3
                q += h / 6.0 * (w + 2.0 * w2m + 2.0 * w3m + w4m)
                w += h / 6.0 * (q1 + 2.0 * qa2 + 2.0 * qa3 + qa4)
        if not (math.isfinite(y) and math.isfinite(v) and math.isfinite(z) and math.isfinite(q)):
            out[:, i + 1:] = np.nan
            sy[i + 1:, :] = np.nan
            sq[i + 1:, :] = np.nan
            return out, sy, sq
        out[0, i + 1] = y
        out[1, i + 1] = v
        out[2, i + 1] = z
        out[3, i + 1] = q
        out[4, i + 1] = w
        if order == 0:
            for col in range(m):
                sy[i + 1, col] = s0[col]
                sq[i + 1, col] = s3[col]
        else:
            for col in range(m):
                sy[i + 1, col] = s1[col]
                sq[i + 1, col] = s4[col]
    return out, sy, sq

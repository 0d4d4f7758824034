"""The one RK4 integrator of the SDOF hysteretic model, with the optional extra physics.

Per unit mass (g = 1 and u = -x_base'' under base excitation, g = 1/m and u = F
under force excitation):

    y'' = g u - c y' - k (1 + drift t) y - fn(y, y') - z
          - mu tanh(y'/v0) - c2 y'|y'| - side kc max(side y - gap, 0)
    z'  = alpha y' - gamma |y'| z - delta y' |z|
    q'' = d - 2 zeta2 w2 q' - w2^2 q            (a higher mode, only when w2 > 0)

with the higher mode's drive d = g u when drive2 = 0 (a structural mode, driven as the first
one is) and, in general, d = gu2 g u - drive2 y'': a share drive2 of the measured point's
absolute acceleration drives it (drive2 = 1: a resonance riding on that point, such as a
sensor mount; under base excitation -(x_base'' + y'') = g u - y'', so gu2 = 1; under force
excitation gu2 = 1 - drive2).

Every extra is off when its parameter is 0; with all of them off the arithmetic is
exactly that of the plain model (the extras are subtracted after the plain terms).
:func:`simulate_sdof` is the plain model; the diagnosis's augmented models
(:mod:`recon.diagnosis.augmented`) pass the extras.

``u`` is sampled at the recording rate; between samples it is interpolated by
the 4-point cubic (Lagrange) through u[i-1], u[i], u[i+1], u[i+2] (linear
extrapolation supplies the points beyond the ends). Linear interpolation, used
before, loses (w dt)^2 / 8 of a tone at the mid-point: 0.9 % at 23 samples per
period. On an independent-generator record (f_n 49.5 Hz at 1150 Hz, issue 18) the
true model then simulated its own clean record at NRMSE 0.005 and the output-error
fit started at the truth ended 6.9 % off delta; with the cubic the record reproduces
to 0.00016. When the sampling is coarse compared with the model's time scales, each
sample interval is split into ``n_sub`` RK4 sub-steps. Zero initial conditions unless (y0, v0, z0) are given;
the higher mode always starts at rest.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

# the layout of the parameter vector P of :func:`simulate_extended`
P_NAMES = ("g", "c", "k", "alpha", "gamma", "delta", "mu", "v0", "c2", "kc", "gap", "side", "drift", "w2", "zeta2",
           "drive2", "gu2")


@njit(cache=True, nogil=True)
def _rhs(y, v, z, q, vq, t, u, P, coef, p, r):
    fn = 0.0
    for j in range(coef.size):
        fn += coef[j] * y ** p[j] * v ** r[j]
    k = P[2]
    if P[12] != 0.0:
        k = P[2] * (1.0 + P[12] * t)
    gu = P[0] * u
    acc = gu - P[1] * v - k * y - fn - z
    if P[6] != 0.0:
        acc -= P[6] * math.tanh(v / P[7])
    if P[8] != 0.0:
        acc -= P[8] * v * abs(v)
    if P[9] != 0.0:
        d = P[11] * y - P[10]
        if d > 0.0:
            acc -= P[11] * P[9] * d
    dz = P[3] * v - P[4] * abs(v) * z - P[5] * v * abs(z)
    aq = 0.0
    if P[13] > 0.0:
        drive = gu
        if P[15] != 0.0:
            drive = P[16] * gu - P[15] * acc
        aq = drive - 2.0 * P[14] * P[13] * vq - P[13] * P[13] * q
    return acc, dz, aq


@njit(cache=True, nogil=True)
def cubic_weights(n_sub):
    """Weights of u[i-1], u[i], u[i+1], u[i+2] at s = j / (2 n_sub), j = 0 .. 2 n_sub, of the
    interval [i, i+1]: the sub-steps' starts, mid-points and ends (4-point Lagrange)."""
    W = np.zeros((2 * n_sub + 1, 4))
    for j in range(2 * n_sub + 1):
        s = j / (2.0 * n_sub)
        W[j, 0] = -s * (s - 1.0) * (s - 2.0) / 6.0
        W[j, 1] = (s + 1.0) * (s - 1.0) * (s - 2.0) / 2.0
        W[j, 2] = -(s + 1.0) * s * (s - 2.0) / 2.0
        W[j, 3] = (s + 1.0) * s * (s - 1.0) / 6.0
    return W


@njit(cache=True, nogil=True)
def simulate_extended(u, t0, dt, n_sub, P, coef, p, r, y0, v0, z0):
    """States (y, y', z, q) as a (4, n) array; NaN from the first non-finite step on."""
    n = u.size
    out = np.zeros((4, n))
    y = y0
    v = v0
    z = z0
    out[0, 0] = y0
    out[1, 0] = v0
    out[2, 0] = z0
    q = 0.0
    w = 0.0
    h = dt / n_sub
    mode = P[13] > 0.0
    W = cubic_weights(n_sub)
    for i in range(n - 1):
        um1 = u[i - 1] if i > 0 else 2.0 * u[0] - u[1]
        up2 = u[i + 2] if i + 2 < n else 2.0 * u[n - 1] - u[n - 2]
        for sub in range(n_sub):
            ta = t0 + i * dt + sub * h
            j = 2 * sub
            ua = W[j, 0] * um1 + W[j, 1] * u[i] + W[j, 2] * u[i + 1] + W[j, 3] * up2
            um = W[j + 1, 0] * um1 + W[j + 1, 1] * u[i] + W[j + 1, 2] * u[i + 1] + W[j + 1, 3] * up2
            ue = W[j + 2, 0] * um1 + W[j + 2, 1] * u[i] + W[j + 2, 2] * u[i + 1] + W[j + 2, 3] * up2
            a1, z1, q1 = _rhs(y, v, z, q, w, ta, ua, P, coef, p, r)
            y2 = y + 0.5 * h * v
            v2 = v + 0.5 * h * a1
            zz2 = z + 0.5 * h * z1
            a2, z2, qa2 = _rhs(y2, v2, zz2, q + 0.5 * h * w, w + 0.5 * h * q1, ta + 0.5 * h, um, P, coef, p, r)
            y3 = y + 0.5 * h * v2
            v3 = v + 0.5 * h * a2
            zz3 = z + 0.5 * h * z2
            a3, z3, qa3 = _rhs(y3, v3, zz3, q + 0.5 * h * (w + 0.5 * h * q1), w + 0.5 * h * qa2, ta + 0.5 * h, um,
                               P, coef, p, r)
            y4 = y + h * v3
            v4 = v + h * a3
            zz4 = z + h * z3
            a4, z4, qa4 = _rhs(y4, v4, zz4, q + h * (w + 0.5 * h * qa2), w + h * qa3, ta + h, ue, P, coef, p, r)
            y += h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v += h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            z += h / 6.0 * (z1 + 2.0 * z2 + 2.0 * z3 + z4)
            if mode:   # the higher mode's own RK4 stages (q' = w, w' = aq)
                w2 = w + 0.5 * h * q1
                w3 = w + 0.5 * h * qa2
                w4 = w + h * qa3
                q += h / 6.0 * (w + 2.0 * w2 + 2.0 * w3 + w4)
                w += h / 6.0 * (q1 + 2.0 * qa2 + 2.0 * qa3 + qa4)
        if not (math.isfinite(y) and math.isfinite(v) and math.isfinite(z) and math.isfinite(q)):
            out[:, i + 1:] = np.nan
            return out
        out[0, i + 1] = y
        out[1, i + 1] = v
        out[2, i + 1] = z
        out[3, i + 1] = q
    return out


def simulate_sdof(u, dt, n_sub, g, c, k, alpha, gamma, delta, coef, p, r, y0=0.0, v0=0.0, z0=0.0):
    """The plain model (no extras): (y, y', z) arrays."""
    P = np.zeros(len(P_NAMES))
    P[:6] = (g, c, k, alpha, gamma, delta)
    P[7] = 1.0
    P[11] = 1.0
    out = simulate_extended(np.ascontiguousarray(u, float), 0.0, float(dt), int(n_sub), P, coef, p, r,
                            float(y0), float(v0), float(z0))
    return out[0], out[1], out[2]


def substeps(dt: float, k_total: float, steps_per_period: int = 64) -> int:
    """RK4 sub-steps per sample so that a natural period gets ``steps_per_period`` steps."""
    if k_total <= 0:
        return 1
    period = 2 * math.pi / math.sqrt(k_total)
    return max(1, int(math.ceil(dt * steps_per_period / period)))


# ----------------------------------------------------------------------------- sensitivities
# Forward sensitivities: the derivative of the simulated states with respect to chosen entries of
# theta = (P, coef), integrated with the states by the same RK4 stages. Differentiating an explicit
# Runge-Kutta step gives the same stages applied to the variational equations
#     S' = (df/dx) S + df/dtheta,
# so the sensitivities are the exact derivatives of the discrete simulation (up to rounding): one
# pass replaces the p + 1 simulations of a forward-difference Jacobian. The |.| and the contact's
# max(., 0) are differentiated on the side they are evaluated at, as a forward difference sees them.
N_P = len(P_NAMES)


@njit(cache=True, nogil=True)
def _rhs_partials(y, v, z, q, w, t, u, P, coef, p, r, cols, Ba, Bz, Bq):
    """The right side (acc, dz, aq) as :func:`_rhs` computes it, its partial derivatives with
    respect to the states (a_y, a_v, dz_v, dz_z, aq_q, aq_w, aq_acc: aq depends on the states also
    through acc) and, written into Ba, Bz, Bq, its partials with respect to theta[cols]."""
    fn = 0.0
    fn_y = 0.0
    fn_v = 0.0
    for j in range(coef.size):
        fn += coef[j] * y ** p[j] * v ** r[j]
        if p[j] > 0:
            fn_y += coef[j] * p[j] * y ** (p[j] - 1) * v ** r[j]
        if r[j] > 0:
            fn_v += coef[j] * r[j] * y ** p[j] * v ** (r[j] - 1)
    k = P[2]
    kt = 1.0
    if P[12] != 0.0:
        kt = 1.0 + P[12] * t
        k = P[2] * kt
    gu = P[0] * u
    acc = gu - P[1] * v - k * y - fn - z
    a_y = -k - fn_y
    a_v = -P[1] - fn_v
    th = 0.0
    sech2 = 0.0
    if P[6] != 0.0:
        th = math.tanh(v / P[7])
        acc -= P[6] * th
        sech2 = 1.0 - th * th
        a_v -= P[6] * sech2 / P[7]
    if P[8] != 0.0:
        acc -= P[8] * v * abs(v)
        a_v -= 2.0 * P[8] * abs(v)
    dc = P[11] * y - P[10]
    contact = P[9] != 0.0 and dc > 0.0
    if contact:
        acc -= P[11] * P[9] * dc
        a_y -= P[9] * P[11] * P[11]
    sv = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)
    sz = 1.0 if z > 0.0 else (-1.0 if z < 0.0 else 0.0)
    dz = P[3] * v - P[4] * abs(v) * z - P[5] * v * abs(z)
    dz_v = P[3] - P[4] * sv * z - P[5] * abs(z)
    dz_z = -P[4] * abs(v) - P[5] * v * sz
    aq = 0.0
    aq_q = 0.0
    aq_w = 0.0
    aq_acc = 0.0
    mode = P[13] > 0.0
    if mode:
        drive = gu
        if P[15] != 0.0:
            drive = P[16] * gu - P[15] * acc
            aq_acc = -P[15]
        aq = drive - 2.0 * P[14] * P[13] * w - P[13] * P[13] * q
        aq_q = -P[13] * P[13]
        aq_w = -2.0 * P[14] * P[13]
    for i in range(cols.size):
        c = cols[i]
        ba = 0.0
        bz = 0.0
        bq = 0.0
        if c >= N_P:
            j = c - N_P
            ba = -(y ** p[j] * v ** r[j])
        elif c == 0:
            ba = u
            if mode:
                bq = P[16] * u if P[15] != 0.0 else u
        elif c == 1:
            ba = -v
        elif c == 2:
            ba = -kt * y
        elif c == 3:
            bz = v
        elif c == 4:
            bz = -abs(v) * z
        elif c == 5:
            bz = -v * abs(z)
        elif c == 6:
            ba = -th if P[6] != 0.0 else -math.tanh(v / P[7])
        elif c == 7:
            if P[6] != 0.0:
                ba = P[6] * sech2 * v / (P[7] * P[7])
        elif c == 8:
            ba = -v * abs(v)
        elif c == 9:
            if dc > 0.0:
                ba = -P[11] * dc
        elif c == 10:
            if contact:
                ba = P[11] * P[9]
        elif c == 12:
            ba = -P[2] * t * y
        elif c == 13:
            if mode:
                bq = -2.0 * P[14] * w - 2.0 * P[13] * q
        elif c == 14:
            if mode:
                bq = -2.0 * P[13] * w
        elif c == 15:
            if mode:
                bq = -acc
        elif c == 16:
            if mode and P[15] != 0.0:
                bq = gu
        Ba[i] = ba
        Bz[i] = bz
        Bq[i] = bq
    return acc, dz, aq, a_y, a_v, dz_v, dz_z, aq_q, aq_w, aq_acc


@njit(cache=True, nogil=True)
def simulate_sensitivities(u, t0, dt, n_sub, P, coef, p, r, y0, v0, z0, cols, S0):
    """:func:`simulate_extended` and the sensitivities of y and q to theta[cols], theta = (P, coef),
    from the initial sensitivities S0 (5 x len(cols): of y, y', z, q, q' at the first sample).
    Returns (states (4, n), dy/dtheta (n, m), dq/dtheta (n, m)); NaN from the first non-finite step."""
    n = u.size
    m = cols.size
    out = np.zeros((4, n))
    Sy_out = np.zeros((n, m))
    Sq_out = np.zeros((n, m))
    y = y0
    v = v0
    z = z0
    out[0, 0] = y0
    out[1, 0] = v0
    out[2, 0] = z0
    q = 0.0
    w = 0.0
    S = S0.copy()          # rows: y, y', z, q, q'
    for c in range(m):
        Sy_out[0, c] = S[0, c]
        Sq_out[0, c] = S[3, c]
    K1 = np.zeros((5, m))
    K2 = np.zeros((5, m))
    K3 = np.zeros((5, m))
    K4 = np.zeros((5, m))
    T = np.zeros((5, m))
    Ba = np.zeros(m)
    Bz = np.zeros(m)
    Bq = np.zeros(m)
    h = dt / n_sub
    mode = P[13] > 0.0
    W = cubic_weights(n_sub)
    for i in range(n - 1):
        um1 = u[i - 1] if i > 0 else 2.0 * u[0] - u[1]
        up2 = u[i + 2] if i + 2 < n else 2.0 * u[n - 1] - u[n - 2]
        for sub in range(n_sub):
            ta = t0 + i * dt + sub * h
            j = 2 * sub
            ua = W[j, 0] * um1 + W[j, 1] * u[i] + W[j, 2] * u[i + 1] + W[j, 3] * up2
            um = W[j + 1, 0] * um1 + W[j + 1, 1] * u[i] + W[j + 1, 2] * u[i + 1] + W[j + 1, 3] * up2
            ue = W[j + 2, 0] * um1 + W[j + 2, 1] * u[i] + W[j + 2, 2] * u[i + 1] + W[j + 2, 3] * up2
            # stage 1
            a1, z1, q1, ay, av, zv, zz, qq, qw, qa = _rhs_partials(y, v, z, q, w, ta, ua, P, coef, p, r, cols,
                                                                   Ba, Bz, Bq)
            for c in range(m):
                K1[0, c] = S[1, c]
                K1[1, c] = ay * S[0, c] + av * S[1, c] - S[2, c] + Ba[c]
                K1[2, c] = zv * S[1, c] + zz * S[2, c] + Bz[c]
                K1[3, c] = S[4, c]
                K1[4, c] = qq * S[3, c] + qw * S[4, c] + qa * K1[1, c] + Bq[c]
                for e in range(5):
                    T[e, c] = S[e, c] + 0.5 * h * K1[e, c]
            # stage 2
            y2 = y + 0.5 * h * v
            v2 = v + 0.5 * h * a1
            zz2 = z + 0.5 * h * z1
            q2 = q + 0.5 * h * w
            w2_ = w + 0.5 * h * q1
            a2, z2, qa2, ay, av, zv, zz, qq, qw, qa = _rhs_partials(y2, v2, zz2, q2, w2_, ta + 0.5 * h, um, P, coef,
                                                                    p, r, cols, Ba, Bz, Bq)
            for c in range(m):
                K2[0, c] = T[1, c]
                K2[1, c] = ay * T[0, c] + av * T[1, c] - T[2, c] + Ba[c]
                K2[2, c] = zv * T[1, c] + zz * T[2, c] + Bz[c]
                K2[3, c] = T[4, c]
                K2[4, c] = qq * T[3, c] + qw * T[4, c] + qa * K2[1, c] + Bq[c]
            for c in range(m):
                for e in range(5):
                    T[e, c] = S[e, c] + 0.5 * h * K2[e, c]
            # stage 3
            y3 = y + 0.5 * h * v2
            v3 = v + 0.5 * h * a2
            zz3 = z + 0.5 * h * z2
            q3 = q + 0.5 * h * (w + 0.5 * h * q1)
            w3_ = w + 0.5 * h * qa2
            a3, z3, qa3, ay, av, zv, zz, qq, qw, qa = _rhs_partials(y3, v3, zz3, q3, w3_, ta + 0.5 * h, um, P, coef,
                                                                    p, r, cols, Ba, Bz, Bq)
            for c in range(m):
                K3[0, c] = T[1, c]
                K3[1, c] = ay * T[0, c] + av * T[1, c] - T[2, c] + Ba[c]
                K3[2, c] = zv * T[1, c] + zz * T[2, c] + Bz[c]
                K3[3, c] = T[4, c]
                K3[4, c] = qq * T[3, c] + qw * T[4, c] + qa * K3[1, c] + Bq[c]
            for c in range(m):
                for e in range(5):
                    T[e, c] = S[e, c] + h * K3[e, c]
            # stage 4
            y4 = y + h * v3
            v4 = v + h * a3
            zz4 = z + h * z3
            q4 = q + h * (w + 0.5 * h * qa2)
            w4_ = w + h * qa3
            a4, z4, qa4, ay, av, zv, zz, qq, qw, qa = _rhs_partials(y4, v4, zz4, q4, w4_, ta + h, ue, P, coef, p, r,
                                                                    cols, Ba, Bz, Bq)
            for c in range(m):
                K4[0, c] = T[1, c]
                K4[1, c] = ay * T[0, c] + av * T[1, c] - T[2, c] + Ba[c]
                K4[2, c] = zv * T[1, c] + zz * T[2, c] + Bz[c]
                K4[3, c] = T[4, c]
                K4[4, c] = qq * T[3, c] + qw * T[4, c] + qa * K4[1, c] + Bq[c]
            y += h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v += h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            z += h / 6.0 * (z1 + 2.0 * z2 + 2.0 * z3 + z4)
            if mode:
                w2 = w + 0.5 * h * q1
                w3 = w + 0.5 * h * qa2
                w4 = w + h * qa3
                q += h / 6.0 * (w + 2.0 * w2 + 2.0 * w3 + w4)
                w += h / 6.0 * (q1 + 2.0 * qa2 + 2.0 * qa3 + qa4)
            for c in range(m):
                for e in range(5):
                    S[e, c] += h / 6.0 * (K1[e, c] + 2.0 * K2[e, c] + 2.0 * K3[e, c] + K4[e, c])
        if not (math.isfinite(y) and math.isfinite(v) and math.isfinite(z) and math.isfinite(q)):
            out[:, i + 1:] = np.nan
            Sy_out[i + 1:, :] = np.nan
            Sq_out[i + 1:, :] = np.nan
            return out, Sy_out, Sq_out
        out[0, i + 1] = y
        out[1, i + 1] = v
        out[2, i + 1] = z
        out[3, i + 1] = q
        for c in range(m):
            Sy_out[i + 1, c] = S[0, c]
            Sq_out[i + 1, c] = S[3, c]
    return out, Sy_out, Sq_out

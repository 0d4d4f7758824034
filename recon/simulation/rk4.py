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
:func:`simulate_sdof` is the plain model (:func:`simulate_plain`, the same arithmetic
specialised); the diagnosis's augmented models (:mod:`recon.diagnosis.augmented`) pass the
extras through :func:`simulate_states`.

``u`` is sampled at the recording rate; between samples it is interpolated by
the 4-point cubic (Lagrange) through u[i-1], u[i], u[i+1], u[i+2] (linear
extrapolation supplies the points beyond the ends). Linear interpolation, used
before, loses (w dt)^2 / 8 of a tone at the mid-point: 0.9 % at 23 samples per
period. At so coarse a sampling (a 50 Hz mode at 1150 Hz) the true model then
simulates its own clean record at an NRMSE of about 0.005 and an output-error fit
started at the truth ends several per cent off delta; with the cubic the record
reproduces to about 0.0002. When the sampling is coarse compared with the model's time scales, each
sample interval is split into ``n_sub`` RK4 sub-steps. Zero initial conditions unless (y0, v0, z0) are given;
the higher mode always starts at rest.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from recon.simulation.powers import ipow

# the layout of the parameter vector P of :func:`simulate_extended`, the one place it is written:
# build P with :func:`kernel_parameters`, read a slot with its index below
P_NAMES = ("g", "c", "k", "alpha", "gamma", "delta", "mu", "v0", "c2", "kc", "gap", "side", "drift", "w2", "zeta2",
           "drive2", "gu2")
N_P = len(P_NAMES)
# one index per slot: module-level ints, which numba compiles as constants (P[I_MU] costs what a
# literal index does)
I_G = P_NAMES.index("g")
I_C = P_NAMES.index("c")
I_K = P_NAMES.index("k")
I_ALPHA = P_NAMES.index("alpha")
I_GAMMA = P_NAMES.index("gamma")
I_DELTA = P_NAMES.index("delta")
I_MU = P_NAMES.index("mu")
I_V0 = P_NAMES.index("v0")
I_C2 = P_NAMES.index("c2")
I_KC = P_NAMES.index("kc")
I_GAP = P_NAMES.index("gap")
I_SIDE = P_NAMES.index("side")
I_DRIFT = P_NAMES.index("drift")
I_W2 = P_NAMES.index("w2")
I_ZETA2 = P_NAMES.index("zeta2")
I_DRIVE2 = P_NAMES.index("drive2")
I_GU2 = P_NAMES.index("gu2")
P_INDEX = {name: i for i, name in enumerate(P_NAMES)}
assert len(P_INDEX) == N_P, "P_NAMES names a slot twice"


def kernel_parameters(**named: float) -> np.ndarray:
    """The parameter vector P of :func:`simulate_extended` from its slots by name (``P_NAMES``):
    v0 and side are 1 unless given, every other slot 0 (its effect off). An unknown name is a
    ValueError."""
    unknown = [name for name in named if name not in P_INDEX]
    if unknown:
        raise ValueError(f"kernel parameters: unknown slot(s) {', '.join(map(repr, unknown))} "
                         f"(known: {', '.join(P_NAMES)})")
    P = np.zeros(N_P)
    P[I_V0] = 1.0
    P[I_SIDE] = 1.0
    for name, value in named.items():
        P[P_INDEX[name]] = value
    return P


@njit(cache=True, nogil=True, inline="always")
def _rhs(y, v, z, q, vq, t, u, X, coef, p, r):
    """The right side; ``X`` is the tuple of P's slots in P_NAMES order, read once per simulation:
    scalars the compiler keeps in registers. Read from P at every stage (P may alias the output,
    as far as the compiler knows) the kernel took three times as long."""
    g, c, k0, alpha, gamma, delta, mu, v0, c2, kc, gap, side, drift, w2, zeta2, drive2, gu2 = X
    fn = 0.0
    for j in range(coef.size):
        fn += coef[j] * ipow(y, p[j]) * ipow(v, r[j])
    k = k0
    if drift != 0.0:
        k = k0 * (1.0 + drift * t)
    gu = g * u
    acc = gu - c * v - k * y - fn - z
    if mu != 0.0:
        acc -= mu * math.tanh(v / v0)
    if c2 != 0.0:
        acc -= c2 * v * abs(v)
    if kc != 0.0:
        d = side * y - gap
        if d > 0.0:
            acc -= side * kc * d
    dz = alpha * v - gamma * abs(v) * z - delta * v * abs(z)
    aq = 0.0
    if w2 > 0.0:
        drive = gu
        if drive2 != 0.0:
            drive = gu2 * gu - drive2 * acc
        aq = drive - 2.0 * zeta2 * w2 * vq - w2 * w2 * q
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


@njit(cache=True, nogil=True, inline="always")
def substep_inputs(u, i, sub, W):
    """The input at the start, mid-point and end of sub-step ``sub`` of interval [i, i+1]: the
    4-point cubic through u[i-1], u[i], u[i+1], u[i+2] (:func:`cubic_weights` ``W``), the points
    beyond the ends extrapolated linearly. Every RK4 kernel reads its input through this."""
    n = u.size
    um1 = u[i - 1] if i > 0 else 2.0 * u[0] - u[1]
    up2 = u[i + 2] if i + 2 < n else 2.0 * u[n - 1] - u[n - 2]
    j = 2 * sub
    ua = W[j, 0] * um1 + W[j, 1] * u[i] + W[j, 2] * u[i + 1] + W[j, 3] * up2
    um = W[j + 1, 0] * um1 + W[j + 1, 1] * u[i] + W[j + 1, 2] * u[i + 1] + W[j + 1, 3] * up2
    ue = W[j + 2, 0] * um1 + W[j + 2, 1] * u[i] + W[j + 2, 2] * u[i + 1] + W[j + 2, 3] * up2
    return ua, um, ue


@njit(cache=True, nogil=True)
def simulate_extended(u, t0, dt, n_sub, P, coef, p, r, y0, v0, z0):
    """States (y, y', z, q, q') as a (5, n) array; NaN from the first non-finite step on."""
    n = u.size
    out = np.zeros((5, n))
    y = y0
    v = v0
    z = z0
    out[0, 0] = y0
    out[1, 0] = v0
    out[2, 0] = z0
    q = 0.0
    w = 0.0
    h = dt / n_sub
    mode = P[I_W2] > 0.0
    W = cubic_weights(n_sub)
    X = (P[I_G], P[I_C], P[I_K], P[I_ALPHA], P[I_GAMMA], P[I_DELTA], P[I_MU], P[I_V0], P[I_C2], P[I_KC], P[I_GAP],
         P[I_SIDE], P[I_DRIFT], P[I_W2], P[I_ZETA2], P[I_DRIVE2], P[I_GU2])
    for i in range(n - 1):
        for sub in range(n_sub):
            ta = t0 + i * dt + sub * h
            ua, um, ue = substep_inputs(u, i, sub, W)
            a1, z1, q1 = _rhs(y, v, z, q, w, ta, ua, X, coef, p, r)
            y2 = y + 0.5 * h * v
            v2 = v + 0.5 * h * a1
            zz2 = z + 0.5 * h * z1
            a2, z2, qa2 = _rhs(y2, v2, zz2, q + 0.5 * h * w, w + 0.5 * h * q1, ta + 0.5 * h, um, X, coef, p, r)
            y3 = y + 0.5 * h * v2
            v3 = v + 0.5 * h * a2
            zz3 = z + 0.5 * h * z2
            a3, z3, qa3 = _rhs(y3, v3, zz3, q + 0.5 * h * (w + 0.5 * h * q1), w + 0.5 * h * qa2, ta + 0.5 * h, um,
                               X, coef, p, r)
            y4 = y + h * v3
            v4 = v + h * a3
            zz4 = z + h * z3
            a4, z4, qa4 = _rhs(y4, v4, zz4, q + h * (w + 0.5 * h * qa2), w + h * qa3, ta + h, ue, X, coef, p, r)
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
        out[4, i + 1] = w
    return out


@njit(cache=True, nogil=True, inline="always")
def _plain_rhs(y, v, z, u, g, c, k, alpha, gamma, delta, coef, p, r):
    fn = 0.0
    for j in range(coef.size):
        fn += coef[j] * ipow(y, p[j]) * ipow(v, r[j])
    acc = g * u - c * v - k * y - fn - z
    dz = alpha * v - gamma * abs(v) * z - delta * v * abs(z)
    return acc, dz


@njit(cache=True, nogil=True)
def simulate_plain(u, dt, n_sub, g, c, k, alpha, gamma, delta, coef, p, r, y0, v0, z0):
    """:func:`simulate_extended` with every extra off, specialised: the same arithmetic in the same
    order (the states agree to the bit), about three times faster, since no extra's switch is read
    inside the loop. States (y, y', z) as a (3, n) array; NaN from the first non-finite step on."""
    n = u.size
    out = np.zeros((3, n))
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
            a1, z1 = _plain_rhs(y, v, z, ua, g, c, k, alpha, gamma, delta, coef, p, r)
            y2 = y + 0.5 * h * v
            v2 = v + 0.5 * h * a1
            zz2 = z + 0.5 * h * z1
            a2, z2 = _plain_rhs(y2, v2, zz2, um, g, c, k, alpha, gamma, delta, coef, p, r)
            y3 = y + 0.5 * h * v2
            v3 = v + 0.5 * h * a2
            zz3 = z + 0.5 * h * z2
            a3, z3 = _plain_rhs(y3, v3, zz3, um, g, c, k, alpha, gamma, delta, coef, p, r)
            y4 = y + h * v3
            v4 = v + h * a3
            zz4 = z + h * z3
            a4, z4 = _plain_rhs(y4, v4, zz4, ue, g, c, k, alpha, gamma, delta, coef, p, r)
            y += h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v += h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            z += h / 6.0 * (z1 + 2.0 * z2 + 2.0 * z3 + z4)
        if not (math.isfinite(y) and math.isfinite(v) and math.isfinite(z)):
            out[:, i + 1:] = np.nan
            return out
        out[0, i + 1] = y
        out[1, i + 1] = v
        out[2, i + 1] = z
    return out


def kernel_input(a) -> np.ndarray:
    """``a`` as every kernel here takes its sampled input: C-contiguous float64, read-only (a view,
    not a copy). Numba types a read-only array apart from a writable one and compiles a kernel once
    per type; a stage's derived arrays are read-only (shakerlab.run_data.Stage.derived) and
    others are not, so passing them all one way keeps one compiled kernel each: half the compile
    time on a fresh install and half the machine code loaded."""
    a = np.ascontiguousarray(a, dtype=float)
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a


def extras_off(P: np.ndarray) -> bool:
    """Whether the parameter vector P switches every extra off (its model is the plain one)."""
    return bool(P[I_MU] == 0.0 and P[I_C2] == 0.0 and P[I_KC] == 0.0 and P[I_DRIFT] == 0.0 and not P[I_W2] > 0.0)


def simulate_states(u, t0, dt, n_sub, P, coef, p, r, y0, v0, z0) -> np.ndarray:
    """:func:`simulate_extended`'s (5, n) states, from :func:`simulate_plain` when P switches every
    extra off (the same numbers, to the bit)."""
    u = kernel_input(u)
    if not extras_off(P):
        return simulate_extended(u, t0, dt, n_sub, P, coef, p, r, y0, v0, z0)
    plain = simulate_plain(u, dt, n_sub, P[I_G], P[I_C], P[I_K], P[I_ALPHA], P[I_GAMMA], P[I_DELTA], coef, p, r,
                           y0, v0, z0)
    out = np.zeros((5, plain.shape[1]))
    out[:3] = plain
    out[3:, np.isnan(plain[0])] = np.nan          # as simulate_extended marks a diverged step
    return out


def simulate_sdof(u, dt, n_sub, g, c, k, alpha, gamma, delta, coef, p, r, y0=0.0, v0=0.0, z0=0.0):
    """The plain model (no extras): (y, y', z) arrays (:func:`simulate_plain`)."""
    out = simulate_plain(kernel_input(u), float(dt), int(n_sub), float(g), float(c), float(k),
                         float(alpha), float(gamma), float(delta), coef, p, r, float(y0), float(v0), float(z0))
    return out[0], out[1], out[2]


def substeps(dt: float, k_total: float, steps_per_period: int = 64) -> int:
    """RK4 sub-steps per sample so that a natural period gets ``steps_per_period`` steps."""
    if k_total <= 0:
        return 1
    period = 2 * math.pi / math.sqrt(k_total)
    return max(1, int(math.ceil(dt * steps_per_period / period)))

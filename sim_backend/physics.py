"""The numba integrator of the simulated rig: generator -> amplifier -> armature -> specimen.

Everything that changes per sample lives in small float arrays so one compiled
kernel, :func:`advance`, integrates any number of steps (fixed-step RK4, the
generator voltage and amplifier current held over each step) and writes the two
laser readings of every step.  The Python side (:mod:`sim_backend.world`) owns
the arrays and changes settings between calls.

Mechanics (x_b armature/base, y = x_tip - x_base, specimen mass m, armature M):
    r   = c y' + k(t) y + fn_m(y, y') + z + extras(y, y')          (per unit mass)
          extras: friction, quadratic damping, contact, a constant force f0; the effects'
          cubic stiffness and amplitude damping add to fn_m's y^3 and y^2*dy coefficients
    M x_b'' = K_f i - k_s x_b - c_s x_b' + m r                       (reaction of the specimen)
    y''     = -r - x_b''
    z'      = alpha y' - gamma |y'| z - delta y' |z|
    q''     = -2 zeta w q' - w^2 q - x_b''                          (optional higher mode)
Amplifier (current mode): i = enable * gain * g_m * v_gen, saturated so that the
output voltage R i + K_f x_b' stays within the rail (clip flag), muted by a
latched over-current / over-temperature / watchdog fault.  Coil heating:
T' = (R i^2 Rth - (T - T_amb)) / tau.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

# ---- parameter vector indices (P) -------------------------------------------------
P_DT, P_M, P_C, P_K, P_ALPHA, P_GAMMA, P_DELTA, P_A2, P_A3, P_B2 = range(10)
P_MA, P_KS, P_CS, P_KF, P_R = range(10, 15)
P_GM, P_RAIL, P_RTH, P_TAU, P_TAMB, P_TMAX = range(15, 21)
P_MU, P_C2, P_GAP, P_KC, P_DRIFT, P_W2, P_Z2, P_PHI2 = range(21, 29)
P_SCALE_B, P_SCALE_T, P_NOISE, P_SEED, P_VNOISE, P_TIP_ON_BASE = range(29, 35)
P_F0 = 35
N_P = 36
# the velocity readings' noise is a second counter-based stream: (seed, step + VELOCITY_STREAM), so the
# displacement readings (and their noise) are the same whether or not velocity is read
VELOCITY_STREAM = 1 << 60

# ---- state vector (X) --------------------------------------------------------------
X_XB, X_VB, X_Y, X_VY, X_Z, X_Q, X_VQ, X_T = range(8)
N_X = 8

# ---- generator vector (G) ----------------------------------------------------------
G_OUT, G_VPP, G_OFFS, G_FREQ, G_PHASE = range(5)
G_SWEEP, G_F0, G_F1, G_TSWEEP, G_TS = range(5, 10)
G_BURST, G_BURST_ACTIVE, G_BURST_LEFT = range(10, 13)
N_G = 13

# ---- amplifier vector (A) ----------------------------------------------------------
A_ENABLE, A_GAIN, A_LIMIT, A_OC, A_OT, A_CLIP, A_WD, A_I, A_V = range(9)
N_A = 9

TWO_PI = 2.0 * math.pi


@njit(cache=True)
def _splitmix(x):
    x = (x + np.uint64(0x9E3779B97F4A7C15)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    z = x
    z = ((z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    z = ((z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    return z ^ (z >> np.uint64(31))


@njit(cache=True)
def _gauss_pair(seed, step):
    """Counter-based pair of independent N(0,1) values for one step (Box-Muller on the two
    32-bit halves of one hash): the same (seed, step) always gives the same pair, whatever
    the chunking of the integration."""
    h = _splitmix(np.uint64(seed) * np.uint64(0x100000001B3) + np.uint64(step))
    u1 = (float(h >> np.uint64(32)) + 0.5) / 4294967296.0
    u2 = float(h & np.uint64(0xFFFFFFFF)) / 4294967296.0
    r = math.sqrt(-2.0 * math.log(u1))
    return r * math.cos(TWO_PI * u2), r * math.sin(TWO_PI * u2)


@njit(cache=True)
def _rates(P, s, i, t, out):
    xb = s[0]
    vb = s[1]
    y = s[2]
    vy = s[3]
    z = s[4]
    q = s[5]
    vq = s[6]
    k = P[P_K] * (1.0 + P[P_DRIFT] * t)
    r = P[P_C] * vy + k * y + P[P_A2] * y * y + P[P_A3] * y * y * y + P[P_B2] * y * y * vy + z
    if P[P_MU] > 0.0:
        # smooth sign: a velocity scale of 1e-4 m/s keeps RK4 stable at 10 kHz
        r += P[P_MU] * math.tanh(vy / 1e-4)
    if P[P_C2] != 0.0:
        r += P[P_C2] * vy * abs(vy)
    if P[P_KC] > 0.0 and y > P[P_GAP]:
        r += P[P_KC] * (y - P[P_GAP])
    if P[P_F0] != 0.0:
        r += P[P_F0]
    ab = (P[P_KF] * i - P[P_KS] * xb - P[P_CS] * vb + P[P_M] * r) / P[P_MA]
    out[0] = vb
    out[1] = ab
    out[2] = vy
    out[3] = -r - ab
    out[4] = P[P_ALPHA] * vy - P[P_GAMMA] * abs(vy) * z - P[P_DELTA] * vy * abs(z)
    if P[P_W2] > 0.0:
        out[5] = vq
        out[6] = -2.0 * P[P_Z2] * P[P_W2] * vq - P[P_W2] * P[P_W2] * q - ab
    else:
        out[5] = 0.0
        out[6] = 0.0


@njit(cache=True)
def _generator_voltage(G, dt):
    """Voltage for this step; advances the generator's phase/sweep/burst state by dt."""
    if G[G_OUT] == 0.0:
        return 0.0
    f = G[G_FREQ]
    if G[G_SWEEP] != 0.0:
        f = G[G_F0] + (G[G_F1] - G[G_F0]) * G[G_TS] / G[G_TSWEEP]
        G[G_TS] += dt
        if G[G_TS] >= G[G_TSWEEP]:
            G[G_TS] -= G[G_TSWEEP]
            G[G_PHASE] = 0.0
    if G[G_BURST] != 0.0:
        if G[G_BURST_ACTIVE] == 0.0:
            return G[G_OFFS]
        v = G[G_OFFS] + 0.5 * G[G_VPP] * math.sin(G[G_PHASE])
        dphi = TWO_PI * f * dt
        G[G_PHASE] += dphi
        G[G_BURST_LEFT] -= dphi
        if G[G_BURST_LEFT] <= 0.0:
            G[G_BURST_ACTIVE] = 0.0
            G[G_PHASE] = 0.0
        return v
    v = G[G_OFFS] + 0.5 * G[G_VPP] * math.sin(G[G_PHASE])
    G[G_PHASE] += TWO_PI * f * dt
    if G[G_PHASE] > TWO_PI:
        G[G_PHASE] -= TWO_PI * math.floor(G[G_PHASE] / TWO_PI)
    return v


@njit(cache=True)
def advance(P, X, G, A, step0, n, xb_out, xt_out):
    """Integrate n steps from global step index step0; write the sensor readings.

    xb_out/xt_out[j] are the base/tip laser readings at the start of step step0+j
    (noise and scale errors included, before range checks).  Returns nothing; X, G
    and A are updated in place.
    """
    _advance(P, X, G, A, step0, n, xb_out, xt_out, xb_out[:0], xt_out[:0], False)


@njit(cache=True)
def advance_with_velocity(P, X, G, A, step0, n, xb_out, xt_out, vb_out, vt_out):
    """:func:`advance`, also writing the base/tip velocity readings (a vibrometer's view of the
    same points: the base velocity and base + relative (+ higher-mode) velocity, the same scale
    errors, white noise ``P_VNOISE`` from its own stream). The displacement readings are exactly
    those of :func:`advance`."""
    _advance(P, X, G, A, step0, n, xb_out, xt_out, vb_out, vt_out, True)


@njit(cache=True)
def _advance(P, X, G, A, step0, n, xb_out, xt_out, vb_out, vt_out, with_velocity):
    dt = P[P_DT]
    k1 = np.empty(N_X - 1)
    k2 = np.empty(N_X - 1)
    k3 = np.empty(N_X - 1)
    k4 = np.empty(N_X - 1)
    tmp = np.empty(N_X - 1)
    seed = np.int64(P[P_SEED])
    for j in range(n):
        step = step0 + j
        t = step * dt
        # sensors sample the state at the start of the step
        xb = X[X_XB]
        xt = xb + (1.0 - P[P_TIP_ON_BASE]) * (X[X_Y] + P[P_PHI2] * X[X_Q])
        nb = 0.0
        nt = 0.0
        if P[P_NOISE] > 0.0:
            g0, g1 = _gauss_pair(seed, step)
            nb = P[P_NOISE] * g0
            nt = P[P_NOISE] * g1
        xb_out[j] = (1.0 + P[P_SCALE_B]) * xb + nb
        xt_out[j] = (1.0 + P[P_SCALE_T]) * xt + nt
        if with_velocity:
            vb = X[X_VB]
            vt = vb + (1.0 - P[P_TIP_ON_BASE]) * (X[X_VY] + P[P_PHI2] * X[X_VQ])
            mb = 0.0
            mt = 0.0
            if P[P_VNOISE] > 0.0:
                h0, h1 = _gauss_pair(seed, step + VELOCITY_STREAM)
                mb = P[P_VNOISE] * h0
                mt = P[P_VNOISE] * h1
            vb_out[j] = (1.0 + P[P_SCALE_B]) * vb + mb
            vt_out[j] = (1.0 + P[P_SCALE_T]) * vt + mt
        # generator -> amplifier
        v_gen = _generator_voltage(G, dt)
        muted = A[A_ENABLE] == 0.0 or A[A_OC] != 0.0 or A[A_OT] != 0.0 or A[A_WD] != 0.0
        i = 0.0
        if not muted:
            i = A[A_GAIN] * P[P_GM] * v_gen
            if abs(i) > A[A_LIMIT]:
                A[A_OC] = 1.0
                i = 0.0
            else:
                emf = P[P_KF] * X[X_VB]
                i_hi = (P[P_RAIL] - emf) / P[P_R]
                i_lo = (-P[P_RAIL] - emf) / P[P_R]
                if i > i_hi:
                    i = i_hi
                    A[A_CLIP] = 1.0
                elif i < i_lo:
                    i = i_lo
                    A[A_CLIP] = 1.0
        A[A_I] = i
        A[A_V] = P[P_R] * i + P[P_KF] * X[X_VB]
        # coil/output-stage heating (explicit Euler is ample for tau >> dt)
        X[X_T] += dt * (P[P_R] * i * i * P[P_RTH] - (X[X_T] - P[P_TAMB])) / P[P_TAU]
        if X[X_T] > P[P_TMAX]:
            A[A_OT] = 1.0
        # RK4 on the mechanical states
        _rates(P, X, i, t, k1)
        for m in range(N_X - 1):
            tmp[m] = X[m] + 0.5 * dt * k1[m]
        _rates(P, tmp, i, t + 0.5 * dt, k2)
        for m in range(N_X - 1):
            tmp[m] = X[m] + 0.5 * dt * k2[m]
        _rates(P, tmp, i, t + 0.5 * dt, k3)
        for m in range(N_X - 1):
            tmp[m] = X[m] + dt * k3[m]
        _rates(P, tmp, i, t + dt, k4)
        for m in range(N_X - 1):
            X[m] += dt / 6.0 * (k1[m] + 2.0 * k2[m] + 2.0 * k3[m] + k4[m])


def parameter_vector(cfg: dict, seed: int) -> np.ndarray:
    """Pack a validated configuration into the kernel's parameter vector."""
    sp, sh, amp, sen, fx = cfg["specimen"], cfg["shaker"], cfg["amplifier"], cfg["sensors"], cfg["effects"]
    P = np.zeros(N_P)
    P[P_DT] = 1.0 / cfg["clock"]["sample_rate"]
    P[P_M] = sp["mass"]
    P[P_C] = sp["c_m"]
    P[P_K] = sp["k_m"]
    P[P_ALPHA] = sp["alpha_m"]
    P[P_GAMMA] = sp["gamma"]
    P[P_DELTA] = sp["delta"]
    P[P_A2] = sp["fn_m"].get("y^2", 0.0)
    # an effect's term adds to the specimen's own (x + 0.0 == x: without the effect the kernel's input
    # is the specimen's coefficient, bit for bit)
    P[P_A3] = sp["fn_m"].get("y^3", 0.0) + fx["cubic_stiffness"]
    P[P_B2] = sp["fn_m"].get("y^2*dy", 0.0) + fx["amplitude_damping"]
    P[P_MA] = sh["armature_mass"]
    P[P_KS] = sh["suspension_stiffness"]
    P[P_CS] = sh["suspension_damping"]
    P[P_KF] = sh["force_constant"]
    P[P_R] = sh["coil_resistance"]
    P[P_GM] = amp["transconductance"]
    P[P_RAIL] = amp["rail_voltage"]
    P[P_RTH] = amp["thermal_resistance"]
    P[P_TAU] = amp["thermal_time_constant"]
    P[P_TAMB] = amp["ambient_temperature"]
    P[P_TMAX] = amp["max_temperature"]
    P[P_MU] = fx["coulomb_friction"]
    P[P_C2] = fx["quadratic_damping"]
    P[P_GAP] = fx["contact_gap"]
    P[P_KC] = fx["contact_stiffness"]
    P[P_DRIFT] = fx["stiffness_drift"]
    P[P_W2] = 2.0 * math.pi * fx["higher_mode_frequency"]
    P[P_Z2] = fx["higher_mode_damping"]
    P[P_PHI2] = fx["higher_mode_participation"] if fx["higher_mode_frequency"] > 0 else 0.0
    P[P_SCALE_B] = fx["base_scale_error"]
    P[P_SCALE_T] = fx["tip_scale_error"]
    P[P_NOISE] = sen["noise_std"]
    P[P_SEED] = float(seed % (2**52))
    P[P_VNOISE] = sen["velocity_noise_std"]
    P[P_TIP_ON_BASE] = sen["tip_on_base"]
    P[P_F0] = fx["offset"]
    return P

"""Ground-truth chain systems (multi-degree-of-freedom) and an MR-damper isolator.

Chain: masses x_1..x_n (x_1 at the free end), element i between x_i and x_(i+1),
element n between x_n and the fixed ground; y_i = x_i - x_(i+1), y_n = x_n.
Element force (absolute units, N):

    E_i = c_i y_i' + k_i y_i + fn_i(y_i, y_i') + z_i
    z_i' = alpha_i y_i' - gamma_i |y_i'| z_i - delta_i y_i' |z_i|     (alpha_i = 0: no hysteresis)
    m_i x_i'' = f_i - E_i + E_(i-1)                                    (E_0 = 0)

The truth integrates with its own RK4 (:func:`integrate_truth`, written apart from the
estimator's :mod:`recon.chain.model` integrator) on the half-step grid of the analytic
multisine forces (``fine`` steps per sample).

MR-damper isolator (SDOF, base excitation, per unit mass): the Spencer-Dyke
phenomenological model is stiff (its internal Bouc-Wen element has a large
exponent), so the isolator here uses the Bouc-Wen law with n = 2 inside the
damper plus a cubic restoring spring, a different hysteresis law than the
agent model's n = 1:

    y'' + c y' + k y + k3 y^3 + z = -x_base''
    z' = A y' - beta |y'| z |z| - g2 y' z^2                         (n = 2)

so z saturates at sqrt(A / (beta + g2)) with a rounder knee than n = 1.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from recon.chain.model import ChainModel, ChainRun, ChainStage, shifted_into
from recon.simulation.powers import ipow
from recon.testing.truth import Multisine
from shakerlab.run_data import BASE, Run, Stage


# ------------------------------------------------------------------ the truth's own integrator
@njit(cache=True)
def _truth_derivative(s, F, n, m, c, k, alpha, gamma, delta, coef, p, r, e):
    """d/dt of the state s = [x_1..x_n, v_1..v_n, z_1..z_n] under forces F."""
    ds = np.empty(3 * n)
    elem = np.empty(n)
    for i in range(n):
        y = s[i] - (s[i + 1] if i + 1 < n else 0.0)
        dy = s[n + i] - (s[n + i + 1] if i + 1 < n else 0.0)
        zi = s[2 * n + i]
        f = c[i] * dy + k[i] * y + zi
        for j in range(coef.size):
            if e[j] == i:
                f += coef[j] * ipow(y, p[j]) * ipow(dy, r[j])
        elem[i] = f
        ds[2 * n + i] = alpha[i] * dy - gamma[i] * abs(dy) * zi - delta[i] * dy * abs(zi)
    for i in range(n):
        ds[i] = s[n + i]
        ds[n + i] = (F[i] - elem[i] + (elem[i - 1] if i > 0 else 0.0)) / m[i]
    return ds


@njit(cache=True)
def _truth_integrate(F_half, h, every, m, c, k, alpha, gamma, delta, coef, p, r, e):
    n = m.size
    steps = (F_half.shape[1] - 1) // 2
    out = np.zeros((3 * n, steps // every + 1))
    s = np.zeros(3 * n)
    st = np.zeros(3 * n)
    # element by element (the same arithmetic, in the same order, as whole-array expressions, which
    # would compile numba's broadcasting checks and their error messages: seconds on a fresh install)
    hh = 0.5 * h
    h6 = h / 6.0
    for j in range(steps):
        f0 = F_half[:, 2 * j]
        fm = F_half[:, 2 * j + 1]
        d1 = _truth_derivative(s, f0, n, m, c, k, alpha, gamma, delta, coef, p, r, e)
        shifted_into(st, s, hh, d1)
        d2 = _truth_derivative(st, fm, n, m, c, k, alpha, gamma, delta, coef, p, r, e)
        shifted_into(st, s, hh, d2)
        d3 = _truth_derivative(st, fm, n, m, c, k, alpha, gamma, delta, coef, p, r, e)
        shifted_into(st, s, h, d3)
        d4 = _truth_derivative(st, F_half[:, 2 * j + 2], n, m, c, k, alpha, gamma, delta, coef, p, r, e)
        for i in range(3 * n):
            s[i] = s[i] + h6 * (d1[i] + 2.0 * d2[i] + 2.0 * d3[i] + d4[i])
        if (j + 1) % every == 0:
            for i in range(3 * n):
                out[i, (j + 1) // every] = s[i]
    return out


def integrate_truth(model: ChainModel, F_half: np.ndarray, h: float, every: int):
    """The truth's response (x, v, z), each (n, M // every + 1), to forces on the half-step grid."""
    out = _truth_integrate(np.ascontiguousarray(F_half, float), h, every, *model.arrays())
    n = model.n
    return out[:n], out[n:2 * n], out[2 * n:]


def chain_stage(name: str, model: ChainModel, signals: dict, fs: float, duration: float, snr_db, rng,
                fine: int = 8) -> ChainStage:
    """``signals``: mass index -> Multisine force. White noise per channel at ``snr_db``."""
    N = int(round(duration * fs)) + 1
    t = np.arange(N) / fs
    grid = np.arange(2 * (N - 1) * fine + 1) / (2 * fine * fs)
    F_half = np.zeros((model.n, grid.size))
    f = np.zeros((model.n, N))
    for i, sig in signals.items():
        F_half[i] = sig.value(grid)
        f[i] = sig.value(t)
    X, V, Z = integrate_truth(model, F_half, 1.0 / (fs * fine), fine)

    def noisy(a):
        if snr_db is None or not np.any(a):
            return a.copy()
        rms = np.sqrt(np.mean((a - a.mean()) ** 2))
        return a + rng.normal(0.0, rms / 10 ** (snr_db / 20), a.size)

    xs = np.vstack([noisy(a) for a in X])
    fs_ = np.vstack([noisy(a) for a in f])
    return ChainStage(name=name, t=t, x=xs, f=fs_, truth={"x": X, "v": V, "z": Z, "f": f})


def two_layer_truth() -> ChainModel:
    """Two masses; hysteresis and cubic stiffness in element 1, nonlinear damping in element 2."""
    return ChainModel(m=[1.0, 1.5], c=[3.0, 6.0], k=[4000.0, 12000.0], alpha=[5000.0, 0.0],
                      gamma=[500.0, 0.0], delta=[300.0, 0.0],
                      fn=[{"y^3": 2.0e8}, {"y^2*dy": 5.0e6}],
                      provenance={"source": "recon.testing.truth_mdof.two_layer_truth"})


def five_layer_truth() -> ChainModel:
    """The five-layer system of the paper's Appendix 3 with our own values: hysteresis in
    elements 1, 3, 5, c23 y2^2 y2' in element 2, k33 y3^3 in element 3, c43 y4^2 y4' in 4."""
    return ChainModel(m=[1.0, 1.5, 1.2, 1.0, 2.0], c=[3.0, 5.0, 4.0, 3.0, 6.0],
                      k=[4000.0, 15000.0, 6000.0, 12000.0, 8000.0],
                      alpha=[5000.0, 0.0, 6000.0, 0.0, 10000.0], gamma=[500.0, 0.0, 400.0, 0.0, 450.0],
                      delta=[300.0, 0.0, 250.0, 0.0, 300.0],
                      fn=[{}, {"y^2*dy": 6.0e6}, {"y^3": 2.0e8}, {"y^2*dy": 4.0e6}, {}],
                      provenance={"source": "recon.testing.truth_mdof.five_layer_truth"})


def chain_run(model: ChainModel, snr_db=80.0, fs: float = 2000.0, duration: float = 10.0, seed: int = 0,
              scale: float = 1.0):
    """Linear (small broadband forces), nonlinear (ramped multisine) and validation stages.
    Forces act on mass 1 and on the last mass, independent multisines."""
    rng = np.random.default_rng(seed)
    n = model.n
    fr = np.linspace(3.0, 45.0, 15)

    def ms(amp, ramp=0.0, freqs=fr):
        return Multisine(list(freqs), [amp] * len(freqs), list(rng.uniform(0, 2 * np.pi, len(freqs))), ramp=ramp)

    lin = {0: ms(0.02 * scale), n - 1: ms(0.02 * scale)}
    non = {0: ms(4.0 * scale, ramp=duration), n - 1: ms(4.0 * scale, ramp=duration)}
    vf = np.array([6.0, 11.0, 17.0, 26.0])
    val = {0: ms(2.5 * scale, freqs=vf), n - 1: ms(2.5 * scale, freqs=vf + 1.5)}
    stages = {name: chain_stage(name, model, sig, fs, duration, snr_db, rng)
              for name, sig in (("linear", lin), ("nonlinear", non), ("validation", val))}
    return ChainRun(stages=stages, source=f"truth:chain-{n}"), model


# ------------------------------------------------------------------ MR-damper isolator
@njit(cache=True)
def _mr_rk4(n, dt, fine, amp, omega, phase, ramp, c, k, k3, A, beta, g2):
    ys = np.zeros(n); zs = np.zeros(n)
    h = dt / fine
    y = 0.0; v = 0.0; z = 0.0
    t = 0.0

    def f(t, y, v, z):
        u = 0.0
        env = t / ramp if ramp > 0 else 1.0
        for i in range(amp.size):
            u += env * amp[i] * omega[i] ** 2 * np.sin(omega[i] * t + phase[i])
            if ramp > 0:
                u -= 2.0 * amp[i] * omega[i] / ramp * np.cos(omega[i] * t + phase[i])
        acc = u - c * v - k * y - k3 * y ** 3 - z
        dz = A * v - beta * abs(v) * z * abs(z) - g2 * v * z * z
        return v, acc, dz

    for i in range(n - 1):
        for _ in range(fine):
            k1 = f(t, y, v, z)
            k2 = f(t + 0.5 * h, y + 0.5 * h * k1[0], v + 0.5 * h * k1[1], z + 0.5 * h * k1[2])
            k3_ = f(t + 0.5 * h, y + 0.5 * h * k2[0], v + 0.5 * h * k2[1], z + 0.5 * h * k2[2])
            k4 = f(t + h, y + h * k3_[0], v + h * k3_[1], z + h * k3_[2])
            y += h / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3_[0] + k4[0])
            v += h / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3_[1] + k4[1])
            z += h / 6.0 * (k1[2] + 2 * k2[2] + 2 * k3_[2] + k4[2])
            t += h
        ys[i + 1] = y
        zs[i + 1] = z
    return ys, zs


MR_PARAMS = {"c": 4.0, "k": 3000.0, "k3": 3.0e8, "A": 6000.0, "beta": 250.0, "g2": 125.0}
"""MR isolator per unit mass: c [1/s], k [1/s^2], k3 [1/(m^2 s^2)], damper A [1/s^2],
beta, g2 [s^2/m^2] of the n = 2 Bouc-Wen law: z saturates at sqrt(A/(beta+g2)) = 4 m/s^2,
reached after y ~ 4/A = 0.7 mm."""


def mr_stage(name: str, signal: Multisine, fs: float, duration: float, snr_db, rng, fine: int = 16,
             params: dict | None = None) -> Stage:
    p = dict(MR_PARAMS, **(params or {}))
    n = int(round(duration * fs)) + 1
    t = np.arange(n) / fs
    a, w, ph = signal.arrays()
    y, z = _mr_rk4(n, 1.0 / fs, fine, a, w, ph, float(signal.ramp), p["c"], p["k"], p["k3"], p["A"],
                   p["beta"], p["g2"])
    xb = signal.value(t)

    def noisy(x):
        if snr_db is None:
            return x
        rms = np.sqrt(np.mean((x - x.mean()) ** 2))
        return x + rng.normal(0.0, rms / 10 ** (snr_db / 20), x.size)

    st = Stage(name=name, t=t, channels={"x_base": noisy(xb), "x_tip": noisy(xb + y)}, excitation=BASE)
    st.settings["truth"] = {"y": y, "z": z}
    return st


def mr_run(snr_db=80.0, fs: float = 2000.0, duration: float = 10.0, seed: int = 0) -> Run:
    """Linear (small, 5 Hz), nonlinear (ramped 6 + 9 + 13 Hz three-tone, y up to 1.8 mm)
    and two validation stages at other frequencies and amplitudes (7 Hz, y 0.4 mm, and a
    6 + 13 Hz two-tone, y 1.2 mm). A single ramped tone was tried first: the model it gave
    diverged on the two-tone stage."""
    rng = np.random.default_rng(seed)
    stages = {
        "linear": mr_stage("linear", Multisine([5.0], [2e-5]), fs, duration, snr_db, rng),
        "nonlinear": mr_stage("nonlinear", Multisine([6.0, 9.0, 13.0], [6e-4, 6e-4, 3e-4], [0.0, 1.0, 2.0],
                                                    ramp=duration), fs, duration, snr_db, rng),
        "validation": mr_stage("validation", Multisine([7.0], [1.0e-3]), fs, duration, snr_db, rng),
        "validation_2tone": mr_stage("validation_2tone", Multisine([6.0, 13.0], [6e-4, 3e-4], [0.0, 1.0]),
                                     fs, duration, snr_db, rng),
    }
    return Run(stages=stages, source="truth:mr-isolator")

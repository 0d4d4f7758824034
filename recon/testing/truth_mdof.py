"""Ground-truth chain systems (multi-degree-of-freedom) and an MR-damper isolator.

Chain: masses x_1..x_n (x_1 at the free end), element i between x_i and x_(i+1),
element n between x_n and the fixed ground; y_i = x_i - x_(i+1), y_n = x_n.
Element force (absolute units, N):

    E_i = c_i y_i' + k_i y_i + fn_i(y_i, y_i') + z_i
    z_i' = alpha_i y_i' - gamma_i |y_i'| z_i - delta_i y_i' |z_i|     (alpha_i = 0: no hysteresis)
    m_i x_i'' = f_i - E_i + E_(i-1)                                    (E_0 = 0)

The integrator (numba RK4) takes the forces on the half-step grid: the ground truth
evaluates the analytic multisine there (``fine`` steps per sample), the identified
model interpolates the recorded forces linearly.

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

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from recon.library import monomials
from recon.testing.truth import Multisine
from shakerlab.errors import UserFacingError
from shakerlab.run_data import BASE, Run, Stage


@dataclass
class ChainModel:
    """A chain of masses and hysteretic elements, absolute units (kg, N/m, N s/m, 1/m)."""

    m: list
    c: list
    k: list
    alpha: list
    gamma: list
    delta: list
    fn: list                     # per element: {monomial name: coefficient [N ...]}
    provenance: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.m)

    def hysteretic(self, i: int) -> bool:
        return self.alpha[i] != 0.0

    def layer(self, i: int) -> dict:
        """Element i per unit mass of mass i (the per-layer convention of recon.chain.estimator)."""
        mi = self.m[i]
        return {"c_m": self.c[i] / mi, "k_m": self.k[i] / mi, "alpha_m": self.alpha[i] / mi,
                "gamma": self.gamma[i], "delta": self.delta[i], "inv_m": 1.0 / mi,
                "fn_m": {k: v / mi for k, v in self.fn[i].items()},
                "mass_ratios": [self.m[j] / mi for j in range(i)], "hysteresis": self.hysteretic(i)}

    def arrays(self):
        coef, p, r, e = [], [], [], []
        for i, d in enumerate(self.fn):
            for name, a in d.items():
                pp, rr = monomials.parse(name)
                coef.append(a); p.append(pp); r.append(rr); e.append(i)
        f = lambda x, t=float: np.asarray(x, t)  # noqa: E731
        return (f(self.m), f(self.c), f(self.k), f(self.alpha), f(self.gamma), f(self.delta),
                f(coef), f(p, np.int64), f(r, np.int64), f(e, np.int64))

    def simulate(self, F_half: np.ndarray, h: float, every: int):
        """RK4 with step h; F_half (n, 2 M + 1) forces on the half-step grid of M steps.
        Returns x (n, M // every + 1), v, z sampled every ``every`` steps."""
        return _chain_rk4(np.ascontiguousarray(F_half, float), h, every, *self.arrays())

    def simulate_recorded(self, t: np.ndarray, forces: np.ndarray, n_sub: int = 8):
        """Response to recorded forces (n, N) sampled at t (linear interpolation), from rest."""
        dt = float(np.median(np.diff(t)))
        N = t.size
        grid = np.arange(2 * (N - 1) * n_sub + 1) / (2 * n_sub)
        F = np.vstack([np.interp(grid, np.arange(N), f) for f in forces])
        return self.simulate(F, dt / n_sub, n_sub)


@njit(cache=True)
def _chain_forces(x, v, z, m, c, k, alpha, gamma, delta, coef, p, r, e, out_a, out_z, F):
    n = m.size
    E = np.zeros(n)
    for i in range(n):
        if i < n - 1:
            y = x[i] - x[i + 1]
            dy = v[i] - v[i + 1]
        else:
            y = x[i]
            dy = v[i]
        E[i] = c[i] * dy + k[i] * y + z[i]
        out_z[i] = alpha[i] * dy - gamma[i] * abs(dy) * z[i] - delta[i] * dy * abs(z[i])
        for j in range(coef.size):
            if e[j] == i:
                E[i] += coef[j] * y ** p[j] * dy ** r[j]
    for i in range(n):
        prev = E[i - 1] if i > 0 else 0.0
        out_a[i] = (F[i] - E[i] + prev) / m[i]


@njit(cache=True)
def _chain_rk4(F_half, h, every, m, c, k, alpha, gamma, delta, coef, p, r, e):
    n = m.size
    M = (F_half.shape[1] - 1) // 2
    ns = M // every + 1
    X = np.zeros((n, ns))
    Vv = np.zeros((n, ns))
    Z = np.zeros((n, ns))
    x = np.zeros(n); v = np.zeros(n); z = np.zeros(n)
    a1 = np.zeros(n); a2 = np.zeros(n); a3 = np.zeros(n); a4 = np.zeros(n)
    w1 = np.zeros(n); w2 = np.zeros(n); w3 = np.zeros(n); w4 = np.zeros(n)
    for s in range(M):
        F0 = F_half[:, 2 * s]
        Fm = F_half[:, 2 * s + 1]
        F1 = F_half[:, 2 * s + 2]
        _chain_forces(x, v, z, m, c, k, alpha, gamma, delta, coef, p, r, e, a1, w1, F0)
        v1 = v.copy()
        _chain_forces(x + 0.5 * h * v1, v + 0.5 * h * a1, z + 0.5 * h * w1, m, c, k, alpha, gamma, delta,
                      coef, p, r, e, a2, w2, Fm)
        v2 = v + 0.5 * h * a1
        _chain_forces(x + 0.5 * h * v2, v + 0.5 * h * a2, z + 0.5 * h * w2, m, c, k, alpha, gamma, delta,
                      coef, p, r, e, a3, w3, Fm)
        v3 = v + 0.5 * h * a2
        _chain_forces(x + h * v3, v + h * a3, z + h * w3, m, c, k, alpha, gamma, delta,
                      coef, p, r, e, a4, w4, F1)
        v4 = v + h * a3
        x = x + h / 6.0 * (v1 + 2 * v2 + 2 * v3 + v4)
        v = v + h / 6.0 * (a1 + 2 * a2 + 2 * a3 + a4)
        z = z + h / 6.0 * (w1 + 2 * w2 + 2 * w3 + w4)
        if (s + 1) % every == 0:
            j = (s + 1) // every
            X[:, j] = x
            Vv[:, j] = v
            Z[:, j] = z
    return X, Vv, Z


# ------------------------------------------------------------------ recorded chains
@dataclass
class ChainStage:
    """One stage of a chain record: displacements x (n, N) [m] and forces f (n, N) [N]."""

    name: str
    t: np.ndarray
    x: np.ndarray
    f: np.ndarray
    truth: dict = field(default_factory=dict, repr=False)

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.t)))

    def y(self, i: int) -> np.ndarray:
        return self.x[i] - self.x[i + 1] if i < self.x.shape[0] - 1 else self.x[i]


@dataclass
class ChainRun:
    stages: dict
    source: str = ""

    def stage(self, name: str) -> ChainStage:

        if name not in self.stages:
            raise UserFacingError(f"{self.source or 'chain run'}: no stage {name!r} (stages: {', '.join(self.stages)})")
        return self.stages[name]


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
    X, V, Z = model.simulate(F_half, 1.0 / (fs * fine), fine)

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

"""Ground-truth systems with known parameters, sampled like a rig, with noise at a given SNR.

The integrator here is deliberately independent of :mod:`recon.simulation.rk4`: the
input is an analytic multisine evaluated exactly at every RK4 stage, on a fine
internal step (``fine`` steps per sample), and the result is sampled at ``fs``.
It also carries the optional extra effects that recon/diagnosis/concealed.py
hides in its recordings (friction, quadratic damping, a contact spring, a
stiffness drift, a second mode), all zero for the plain model.
Used by the tests and the benches to prove accuracy against known parameters.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from recon.model import HystereticModel
from recon.simulation.powers import ipow
from shakerlab.run_data import BASE, FORCE, Run, Stage

# the extra effects of :func:`integrate` (zero: the plain model), in the order of its P vector
EFFECT_PARAMS = ("mu", "c2", "kc", "gap", "drift", "w2", "zeta2")


@njit(cache=True)
def integrate(n, dt, fine, t0, amp, omega, phase, ramp, base, P, coef, p, r):
    """RK4 with ``fine`` internal steps per sample, the multisine input evaluated exactly at
    every stage; returns (y, y', z, q) at the n samples (from rest at t0).

    P = (g, c, k, alpha, gamma, delta, mu, c2, kc, gap, drift, w2, zeta2): the model per unit
    mass and optional extra effects (zero: absent): Coulomb friction mu tanh(y'/1e-4 m/s),
    quadratic damping c2 y'|y'|, a contact spring kc (y - gap) for y > gap, a stiffness drift
    k (1 + drift t) on the session clock t, and a second mode q (w2, zeta2) driven by g u."""
    g, c, k, alpha, gamma, delta, mu, c2, kc, gap, drift, w2, zeta2 = P
    ns = 5 if w2 > 0.0 else 3          # the second mode's states only when it is there

    def rhs(tt, x, out):
        # state derivative; x = (y, y', z, q, q')
        tl = tt - t0
        env = tl / ramp if ramp > 0 else 1.0
        u = 0.0
        for j in range(amp.size):
            u += env * amp[j] * np.sin(omega[j] * tl + phase[j])
            if base and ramp > 0:
                # x = (t/T) A sin(w t + ph):  -x'' = (t/T) A w^2 sin(.) - 2 (A w / T) cos(.)
                u -= 2.0 * amp[j] / (omega[j] * ramp) * np.cos(omega[j] * tl + phase[j])
        y = x[0]
        v = x[1]
        z = x[2]
        fn = 0.0
        for j in range(coef.size):
            fn += coef[j] * ipow(y, p[j]) * ipow(v, r[j])
        force = c * v + k * (1.0 + drift * tt) * y + fn + z
        if mu != 0.0:
            force += mu * np.tanh(v / 1e-4)
        if c2 != 0.0:
            force += c2 * v * abs(v)
        if kc > 0.0 and y > gap:
            force += kc * (y - gap)
        out[0] = v
        out[1] = g * u - force
        out[2] = alpha * v - gamma * abs(v) * z - delta * v * abs(z)
        if ns == 5:
            out[3] = x[4]
            out[4] = g * u - 2.0 * zeta2 * w2 * x[4] - w2 * w2 * x[3]

    res = np.zeros((4, n))
    s = np.zeros(5)
    tmp = np.zeros(5)
    h = dt / fine
    k1 = np.zeros(5)
    k2 = np.zeros(5)
    k3 = np.zeros(5)
    k4 = np.zeros(5)
    for i in range(n - 1):
        for f in range(fine):
            ta = t0 + i * dt + f * h
            rhs(ta, s, k1)
            for q in range(ns):
                tmp[q] = s[q] + 0.5 * h * k1[q]
            rhs(ta + 0.5 * h, tmp, k2)
            for q in range(ns):
                tmp[q] = s[q] + 0.5 * h * k2[q]
            rhs(ta + 0.5 * h, tmp, k3)
            for q in range(ns):
                tmp[q] = s[q] + h * k3[q]
            rhs(ta + h, tmp, k4)
            for q in range(ns):
                s[q] += h / 6.0 * (k1[q] + 2.0 * k2[q] + 2.0 * k3[q] + k4[q])
        res[0, i + 1] = s[0]
        res[1, i + 1] = s[1]
        res[2, i + 1] = s[2]
        res[3, i + 1] = s[3]
    return res


def model_params(model, extras: dict | None = None) -> np.ndarray:
    """The P vector of :func:`integrate` for ``model`` and optional extra effects."""
    extras = extras or {}
    unknown = set(extras) - set(EFFECT_PARAMS) - {"delay", "tip_scale", "phi2"}
    if unknown:
        raise ValueError(f"unknown effect parameters {sorted(unknown)}")
    return np.array([model.input_gain, model.c_m, model.k_m, model.alpha_m, model.gamma, model.delta,
                     *[float(extras.get(k, 0.0)) for k in EFFECT_PARAMS]], float)


@dataclass
class Multisine:
    """x(t) = env(t) sum_i amp_i sin(2 pi f_i t + phase_i) (base displacement [m] or force [N]).

    ``ramp`` > 0 makes the envelope a linear ramp env = t/ramp (an incremental-amplitude
    stage); 0 means constant amplitude."""

    freqs: list
    amps: list
    phases: list = field(default_factory=list)
    ramp: float = 0.0

    def __post_init__(self):
        if not self.phases:
            self.phases = [0.0] * len(self.freqs)

    def arrays(self):
        return (np.asarray(self.amps, float), 2 * np.pi * np.asarray(self.freqs, float),
                np.asarray(self.phases, float))

    def envelope(self, t):
        return t / self.ramp if self.ramp > 0 else np.ones_like(t)

    def value(self, t):
        a, w, ph = self.arrays()
        return self.envelope(t) * (np.sin(np.outer(t, w) + ph) @ a)

    def second_derivative(self, t):
        a, w, ph = self.arrays()
        out = -self.envelope(t) * (np.sin(np.outer(t, w) + ph) @ (a * w * w))
        if self.ramp > 0:
            out += 2.0 / self.ramp * (np.cos(np.outer(t, w) + ph) @ (a * w))
        return out


def sdof_truth(excitation: str = BASE) -> HystereticModel:
    """A shaker-like SDOF specimen: first resonance ~ 12-15 Hz, mm displacements,
    cubic stiffness y^3 and cubic damping y^2*y' (per unit mass)."""
    return HystereticModel(
        excitation=excitation, c_m=3.0, k_m=4000.0, alpha_m=5000.0, gamma=500.0, delta=300.0,
        fn_m={"y^3": 2.0e8, "y^2*dy": 3.0e6}, inv_m=2.0 if excitation == FORCE else None,
        provenance={"source": "recon.testing.truth.sdof_truth"},
    )


def simulate_truth(model: HystereticModel, signal: Multisine, fs: float, duration: float, fine: int = 16):
    """Exact-input integration of ``model`` under ``signal``; returns t, y, dy, z, u."""
    n = int(round(duration * fs)) + 1
    t = np.arange(n) / fs
    a, w, ph = signal.arrays()
    base = model.excitation == BASE
    amp = a * w * w if base else a     # u = -x_base'' or the force
    coef, p, r = model.fn_arrays()
    y, dy, z, _ = integrate(n, 1.0 / fs, fine, 0.0, amp, w, ph, float(signal.ramp), base, model_params(model),
                            coef, p, r)
    u = -signal.second_derivative(t) if base else signal.value(t)
    return t, y, dy, z, u


def make_stage(name: str, model: HystereticModel, signal: Multisine, fs: float, duration: float,
               snr_db: float | None, rng: np.random.Generator, fine: int = 16) -> Stage:
    """A recorded stage: channels as a rig writes them, white noise at ``snr_db`` per channel
    (noise rms = channel rms / 10^(snr/20)); ``snr_db=None`` for noise-free."""
    t, y, dy, z, u = simulate_truth(model, signal, fs, duration, fine)

    def noisy(x):
        if snr_db is None:
            return x
        rms = np.sqrt(np.mean((x - x.mean()) ** 2))
        return x + rng.normal(0.0, rms / 10 ** (snr_db / 20), x.size)

    if model.excitation == BASE:
        xb = signal.value(t)
        ch = {"x_base": noisy(xb), "x_tip": noisy(xb + y)}
    else:
        ch = {"force": noisy(signal.value(t)), "x": noisy(y)}
    st = Stage(name=name, t=t, channels=ch, excitation=model.excitation)
    st.settings["truth"] = {"y": y, "dy": dy, "z": z, "u": u}
    return st


def sdof_run(excitation: str = BASE, snr_db: float | None = 80.0, fs: float = 2000.0,
             duration: float = 10.0, seed: int = 0, model: HystereticModel | None = None) -> tuple[Run, HystereticModel]:
    """Linear (small, off resonance), nonlinear (large, near resonance) and validation stages."""
    model = model or sdof_truth(excitation)
    rng = np.random.default_rng(seed)
    if excitation == BASE:
        lin = Multisine([5.0], [4e-5])                       # single tone is fine: input gain is 1
        non = Multisine([12.5], [6.0e-4], ramp=duration)   # incremental amplitude near resonance
        val = Multisine([10.0, 17.0], [2.0e-4, 1.0e-4], [0.0, 1.0])
    else:
        fr = np.linspace(4.0, 30.0, 9)
        lin = Multisine(list(fr), [0.01] * fr.size, list(rng.uniform(0, 2 * np.pi, fr.size)))
        non = Multisine([12.5], [2.0], ramp=duration)
        val = Multisine([10.0, 17.0], [0.8, 0.4], [0.0, 1.0])
    stages = {
        "linear": make_stage("linear", model, lin, fs, duration, snr_db, rng),
        "nonlinear": make_stage("nonlinear", model, non, fs, duration, snr_db, rng),
        "validation": make_stage("validation", model, val, fs, duration, snr_db, rng),
    }
    return Run(stages=stages, source=f"truth:sdof-{excitation}"), model

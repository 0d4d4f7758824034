"""The chain model the chain estimator identifies: masses and hysteretic elements, its
integrator, and the recorded chain stages and runs it is fitted on.

Chain: masses x_1..x_n (x_1 at the free end), element i between x_i and x_(i+1),
element n between x_n and the fixed ground; y_i = x_i - x_(i+1), y_n = x_n.
Element force (absolute units, N):

    E_i = c_i y_i' + k_i y_i + fn_i(y_i, y_i') + z_i
    z_i' = alpha_i y_i' - gamma_i |y_i'| z_i - delta_i y_i' |z_i|     (alpha_i = 0: no hysteresis)
    m_i x_i'' = f_i - E_i + E_(i-1)                                    (E_0 = 0)

The integrator (numba RK4) takes the forces on the half-step grid; the identified model
interpolates the recorded forces linearly. The ground truths of
:mod:`recon.testing.truth_mdof` integrate with their own, separately written code, so a
fault in this integrator cannot hide in the tests.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from recon.library import monomials
from recon.simulation.powers import ipow
from shakerlab.errors import UserFacingError


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
                E[i] += coef[j] * ipow(y, p[j]) * ipow(dy, r[j])
    for i in range(n):
        prev = E[i - 1] if i > 0 else 0.0
        out_a[i] = (F[i] - E[i] + prev) / m[i]


@njit(cache=True, inline="always")
def shifted_into(out, base, step, slope):
    """out = base + step * slope, element by element (an RK4 trial state; no array expression: see
    _chain_rk4)."""
    for i in range(base.size):
        out[i] = base[i] + step * slope[i]


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
    v1 = np.zeros(n); v2 = np.zeros(n); v3 = np.zeros(n); v4 = np.zeros(n)
    xt = np.zeros(n); zt = np.zeros(n)
    # element by element (the same arithmetic, in the same order, as whole-array expressions; array
    # expressions would compile numba's broadcasting checks and their error messages, seconds of
    # compile time on a fresh install, and allocate at every step). Each stage's trial velocity is
    # also the next stage's slope of x (v2, v3, v4): made once, passed as the velocity
    hh = 0.5 * h
    h6 = h / 6.0
    for s in range(M):
        F0 = F_half[:, 2 * s]
        Fm = F_half[:, 2 * s + 1]
        F1 = F_half[:, 2 * s + 2]
        _chain_forces(x, v, z, m, c, k, alpha, gamma, delta, coef, p, r, e, a1, w1, F0)
        for i in range(n):
            v1[i] = v[i]
        shifted_into(xt, x, hh, v1)
        shifted_into(v2, v, hh, a1)
        shifted_into(zt, z, hh, w1)
        _chain_forces(xt, v2, zt, m, c, k, alpha, gamma, delta, coef, p, r, e, a2, w2, Fm)
        shifted_into(xt, x, hh, v2)
        shifted_into(v3, v, hh, a2)
        shifted_into(zt, z, hh, w2)
        _chain_forces(xt, v3, zt, m, c, k, alpha, gamma, delta, coef, p, r, e, a3, w3, Fm)
        shifted_into(xt, x, h, v3)
        shifted_into(v4, v, h, a3)
        shifted_into(zt, z, h, w3)
        _chain_forces(xt, v4, zt, m, c, k, alpha, gamma, delta, coef, p, r, e, a4, w4, F1)
        for i in range(n):
            x[i] = x[i] + h6 * (v1[i] + 2.0 * v2[i] + 2.0 * v3[i] + v4[i])
            v[i] = v[i] + h6 * (a1[i] + 2.0 * a2[i] + 2.0 * a3[i] + a4[i])
            z[i] = z[i] + h6 * (w1[i] + 2.0 * w2[i] + 2.0 * w3[i] + w4[i])
        if (s + 1) % every == 0:
            j = (s + 1) // every
            for i in range(n):
                X[i, j] = x[i]
                Vv[i, j] = v[i]
                Z[i, j] = z[i]
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

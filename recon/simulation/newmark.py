"""Newmark integration of the SDOF hysteretic model, compatible with the Bouc-Wen benchmark.

The model, per unit mass (the project's convention, see docs/method.md)::

    y'' + c y' + k y + fn(y, y') + z = b u
    z'  = alpha y' - gamma |y'| z - delta y' |z|

with ``fn = sum_j a_j y^p_j y'^r_j`` and ``b`` the input coefficient (1/m for
force excitation, 1 for base excitation).  The Bouc-Wen benchmark (Noel &
Schoukens 2016) generated its data with exactly this scheme (nu = 1): the
Newmark rules for y and y' with coefficients a = 1/2, b = 1/4 (trapezoidal, or
"average acceleration"), the same trapezoidal rule for z with c = 1/2, and a
Newton-Raphson correction of the two unknowns (y''(t+h), z(t+h)) per step.
Each step here is solved by Newton iteration to machine precision, so the
result does not depend on how the original implementation's predictor or
stopping rule worked.

:func:`newmark_integrate` takes the input already at the integration rate;
:func:`simulate_chain` reproduces the whole benchmark chain (upsample the
input, integrate, FIR-decimate the output back to the recording rate).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from recon.library import monomials
from recon.simulation import resampling
from recon.simulation.powers import ipow
from shakerlab.errors import UserFacingError

__all__ = ["NewmarkParameters", "newmark_integrate", "simulate_chain"]


@dataclass(frozen=True)
class NewmarkParameters:
    """Per-unit-mass parameters of the SDOF hysteretic model.

    ``fn`` maps monomial names ("y^2", "y*dy", "y^2*dy", ...; "dy" is y') to
    their coefficients.  ``b`` multiplies the input (1/m under force
    excitation).
    """

    c: float
    k: float
    alpha: float
    gamma: float
    delta: float
    b: float = 1.0
    fn: tuple = ()  # ((name, coefficient), ...) kept hashable

    NAMES = ("b", "c", "k", "alpha", "gamma", "delta")   # the scalar parameters, in the refinement's order

    @classmethod
    def from_benchmark(cls, m, c, k, alpha, beta_gamma, beta_delta):
        """From the benchmark's physical units (m [kg], c [Ns/m], k, alpha [N/m], beta*gamma, beta*delta [1/m])."""
        return cls(c=c / m, k=k / m, alpha=alpha / m, gamma=beta_gamma, delta=beta_delta, b=1.0 / m)

    def to_benchmark(self) -> dict:
        m = 1.0 / self.b
        return {"m": m, "c": self.c * m, "k": self.k * m, "alpha": self.alpha * m,
                "gamma": self.gamma, "delta": self.delta}

    @classmethod
    def from_model(cls, model):
        """From a HystereticModel (recon.model): c_m, k_m, alpha_m, gamma, delta, inv_m, fn_m."""
        inv_m = getattr(model, "inv_m", None)
        fn = tuple(sorted((getattr(model, "fn_m", None) or {}).items()))
        return cls(c=model.c_m, k=model.k_m, alpha=model.alpha_m, gamma=model.gamma,
                   delta=model.delta, b=1.0 if inv_m is None else inv_m, fn=fn)


@njit(cache=True, nogil=True)
def _fn_and_grad(y, v, coef, pe, re):
    f = 0.0
    dfy = 0.0
    dfv = 0.0
    for j in range(coef.size):
        p = pe[j]
        r = re[j]
        yp = ipow(y, p)
        vr = ipow(v, r)
        f += coef[j] * yp * vr
        if p > 0:
            dfy += coef[j] * p * ipow(y, p - 1) * vr
        if r > 0:
            dfv += coef[j] * r * yp * ipow(v, r - 1)
    return f, dfy, dfv


@njit(cache=True, nogil=True)
def _zdot(v, z, alpha, gamma, delta):
    return alpha * v - gamma * abs(v) * z - delta * v * abs(z)


@njit(cache=True, nogil=True)
def _integrate(u, h, c, k, alpha, gamma, delta, b, coef, pe, re, y0, v0, z0,
               na, nb, nc, tol, max_iter):
    n = u.size
    ys = np.empty(n)
    vs = np.empty(n)
    zs = np.empty(n)
    y = y0
    v = v0
    z = z0
    f, _, _ = _fn_and_grad(y, v, coef, pe, re)
    a = b * u[0] - c * v - k * y - f - z
    zd = _zdot(v, z, alpha, gamma, delta)
    ys[0] = y
    vs[0] = v
    zs[0] = z
    worst = 0
    for i in range(1, n):
        # predictor: y''(t+h) = 0, z'(t+h) = 0
        a1 = 0.0
        z1 = z + (1.0 - nc) * h * zd
        ui = b * u[i]
        it = 0
        while True:
            v1 = v + (1.0 - na) * h * a + na * h * a1
            y1 = y + h * v + (0.5 - nb) * h * h * a + nb * h * h * a1
            f1, dfy, dfv = _fn_and_grad(y1, v1, coef, pe, re)
            zd1 = _zdot(v1, z1, alpha, gamma, delta)
            r1 = a1 + c * v1 + k * y1 + f1 + z1 - ui
            r2 = z1 - z - h * ((1.0 - nc) * zd + nc * zd1)
            # Jacobian of (r1, r2) w.r.t. (a1, z1)
            sv = 1.0 if v1 > 0 else (-1.0 if v1 < 0 else 0.0)
            sz = 1.0 if z1 > 0 else (-1.0 if z1 < 0 else 0.0)
            dzd_dv = alpha - gamma * sv * z1 - delta * abs(z1)
            dzd_dz = -gamma * abs(v1) - delta * v1 * sz
            j11 = 1.0 + (c + dfv) * na * h + (k + dfy) * nb * h * h
            j12 = 1.0
            j21 = -h * nc * dzd_dv * na * h
            j22 = 1.0 - h * nc * dzd_dz
            det = j11 * j22 - j12 * j21
            da = (r1 * j22 - j12 * r2) / det
            dz = (j11 * r2 - j21 * r1) / det
            a1 -= da
            z1 -= dz
            it += 1
            if (abs(da) <= tol * (1.0 + abs(a1)) and abs(dz) <= tol * (1.0 + abs(z1))) or it >= max_iter:
                break
        if it > worst:
            worst = it
        v1 = v + (1.0 - na) * h * a + na * h * a1
        y1 = y + h * v + (0.5 - nb) * h * h * a + nb * h * h * a1
        zd = _zdot(v1, z1, alpha, gamma, delta)
        y = y1
        v = v1
        z = z1
        a = a1
        ys[i] = y
        vs[i] = v
        zs[i] = z
    return ys, vs, zs, worst


def newmark_integrate(params: NewmarkParameters, u, h: float, y0: float = 0.0, v0: float = 0.0,
                      z0: float = 0.0, a: float = 0.5, b: float = 0.25, c: float = 0.5,
                      tol: float = 1e-13, max_iter: int = 50):
    """Integrate the model for the input ``u`` sampled at step ``h``.

    Returns ``(y, dy, z)`` at the input's samples.  ``a, b`` are the Newmark
    coefficients, ``c`` the one of the z rule (benchmark: 0.5, 0.25, 0.5).
    """
    u = np.ascontiguousarray(u, dtype=float)
    if u.ndim != 1 or u.size < 2:
        raise UserFacingError(f"newmark_integrate: input must be a 1-D record of >= 2 samples, got {u.shape}")
    if not np.all(np.isfinite(u)):
        raise UserFacingError("newmark_integrate: input has non-finite samples")
    if not h > 0:
        raise UserFacingError(f"newmark_integrate: step h must be positive, got {h}")
    names = [n for n, _ in params.fn]
    coef = np.asarray([v for _, v in params.fn], dtype=float)
    pe, re = monomials.exponents(names)
    ys, vs, zs, worst = _integrate(u, float(h), float(params.c), float(params.k), float(params.alpha),
                                   float(params.gamma), float(params.delta), float(params.b), coef, pe, re,
                                   float(y0), float(v0), float(z0), float(a), float(b), float(c),
                                   float(tol), int(max_iter))
    if worst >= max_iter or not np.all(np.isfinite(ys)):
        raise FloatingPointError(
            f"newmark_integrate: Newton iterations did not converge (worst step used {worst} iterations); "
            "the parameters make the model unstable or the step is too coarse"
        )
    return ys, vs, zs


def simulate_chain(params: NewmarkParameters, u, fs: float, upsample: int = 20, periodic: bool = False,
                   n_warmup_periods: int = 0, n_tail_periods: int = 1, decimation_order: int = 30):
    """Simulate the benchmark's generation chain and return y at the recording rate.

    - ``periodic=False``: ``u`` is a record that starts from rest; the model
      starts from zero state at its first sample.  The input is upsampled by a
      polyphase FIR and extended by zeros at the end (``tail`` of 64 samples)
      so the decimation filter has no end effect on the returned samples.
    - ``periodic=True``: ``u`` holds whole periods of a periodic input (one or
      more).  It is interpolated exactly in the frequency domain, the model is
      simulated from zero state over ``n_warmup_periods`` extra periods, then
      the record, then ``n_tail_periods`` more (the benchmark simulated one
      extra period and dropped it to avoid the filter's end effect), and the
      samples aligned with ``u`` are returned.  With ``n_warmup_periods=0``
      the record itself starts from zero state (the benchmark's training
      data); with one or more warm-up periods the returned record is in
      steady state (the benchmark's multisine test).
    """
    u = np.asarray(u, dtype=float)
    n = u.size
    h = 1.0 / (fs * upsample)
    if periodic:
        u_up = resampling.upsample_periodic(u, upsample)
        reps = n_warmup_periods + 1 + n_tail_periods
        u_int = np.tile(u_up, reps)
        start = n_warmup_periods * n
    else:
        tail = 64
        u_up = resampling.upsample_polyphase(np.concatenate([u, np.zeros(tail)]), upsample)
        u_int = u_up
        start = 0
    y_int, _, _ = newmark_integrate(params, u_int, h)
    y = resampling.decimate_chain(y_int, upsample, decimation_order)
    return y[start : start + n]

"""The hysteretic state under an imposed motion (constitutive mode: the displacement is given).

When x(t) is imposed, only the Bouc-Wen state needs integrating, here with unit gain::

    w' = x' - gamma |x'| w - delta x' |w|          (z = alpha w obeys the library's law)
    u' = -eta (u - v)                               (a command's first-order lag, eta > 0 only)

x' and the command v are sampled at the recording rate and interpolated linearly (RK4 half
steps use the mid-point value). Each sample interval is split into ``n_sub`` RK4 sub-steps
(:func:`substeps`) so that the state moves by a small fraction of its range per sub-step.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _integrate(v, cmd, dt, n_sub, gamma, delta, eta, w0, u0):
    n = v.size
    w_out = np.empty(n)
    u_out = np.empty(n)
    w = w0
    u = u0
    w_out[0] = w
    u_out[0] = u
    h = dt / n_sub
    for i in range(n - 1):
        dv = (v[i + 1] - v[i]) / n_sub
        dc = (cmd[i + 1] - cmd[i]) / n_sub
        for s in range(n_sub):
            va = v[i] + dv * s
            vm = va + 0.5 * dv
            vb = va + dv
            ca = cmd[i] + dc * s
            cm = ca + 0.5 * dc
            cb = ca + dc
            k1 = va - gamma * abs(va) * w - delta * va * abs(w)
            l1 = -eta * (u - ca)
            w2 = w + 0.5 * h * k1
            k2 = vm - gamma * abs(vm) * w2 - delta * vm * abs(w2)
            l2 = -eta * (u + 0.5 * h * l1 - cm)
            w3 = w + 0.5 * h * k2
            k3 = vm - gamma * abs(vm) * w3 - delta * vm * abs(w3)
            l3 = -eta * (u + 0.5 * h * l2 - cm)
            w4 = w + h * k3
            k4 = vb - gamma * abs(vb) * w4 - delta * vb * abs(w4)
            l4 = -eta * (u + h * l3 - cb)
            w += h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            u += h / 6.0 * (l1 + 2.0 * l2 + 2.0 * l3 + l4)
        if not (math.isfinite(w) and math.isfinite(u)):
            w_out[i + 1:] = np.nan
            u_out[i + 1:] = np.nan
            return w_out, u_out
        w_out[i + 1] = w
        u_out[i + 1] = u
    return w_out, u_out


def substeps(dt: float, v, gamma: float, delta: float, eta: float = 0.0, per_unit: float = 0.05) -> int:
    """RK4 sub-steps per sample: the decay rate (|gamma| + |delta|) |x'| and eta times the
    sub-step stay below ``per_unit``; at most 64."""
    rate = (abs(gamma) + abs(delta)) * float(np.max(np.abs(v))) + abs(eta)
    return int(min(64, max(1, math.ceil(dt * rate / per_unit))))


def hysteretic_state(v, dt: float, gamma: float, delta: float, w0: float = 0.0, cmd=None, eta: float = 0.0,
                     u0: float | None = None, n_sub: int | None = None):
    """(w, u): the unit-gain Bouc-Wen state driven by the velocity ``v`` and the lagged command
    (u is None without ``cmd``). NaN from the first non-finite step on."""
    v = np.ascontiguousarray(v, float)
    c = np.zeros_like(v) if cmd is None else np.ascontiguousarray(cmd, float)
    e = float(eta) if cmd is not None else 0.0
    u_start = float(c[0] if u0 is None else u0)
    n = n_sub or substeps(dt, v, gamma, delta, e)
    w, u = _integrate(v, c, float(dt), int(n), float(gamma), float(delta), e, float(w0), u_start)
    return w, (u if cmd is not None else None)

"""Ground truth for constitutive mode: component tests with known hysteresis laws.

Like ``independent.py`` it shares no code with shakerlab: only numpy, scipy and the standard
library (``tests/test_constitutive.py`` asserts it). A component test imposes a displacement
x(t) and measures the force. The laws (SI units, the force in N)::

    F = c(u) x' + k x + sum_j b_j x^p_j x'^r_j + a(u) w + f0 + m x''
    w' = x' - gamma |x'| w - delta x' |w|                  (Bouc-Wen, n = 1, unit gain)
    c(u) = c + c1 u,   a(u) = alpha + alpha1 u,   u' = -eta (u - v(t))

With c1 = alpha1 = 0 the hysteretic force z = alpha w obeys
z' = alpha x' - gamma |x'| z - delta x' |z|. With a command v(t) (the coil voltage of an MR
damper) u is its first-order lag, and the damping and the hysteretic force (its initial
stiffness and its amplitude alpha/(gamma + delta) alike) scale with u.

Displacement histories (analytic, so x' and x'' are exact; each starts from rest with a
smooth ramp):

- ``quasi_static``: a slow sine (``f_qs``, 0.1 Hz by default) whose amplitude steps through
  several levels (rate-independent hysteresis, the inertia and viscous force small);
- ``sines``: a 0.5-2 Hz tone whose amplitude steps through several levels, plus a slower tone
  that moves the loops' centre (a friction-damper bench);
- ``random``: band-limited random displacement, a sum of many random-phase sines from 0.3 Hz
  to ``f_max`` (6 Hz by default; an MR damper under a white-noise displacement).

The command ``v`` (if the law has ``eta``) is a switched square signal with random levels and
dwell times. The ODE for (w, u) is integrated with ``solve_ivp`` (DOP853, tight tolerances)
piecewise between command switches, and sampled at ``fs``. Noise: independent white
Gaussian noise on each channel at the given SNR (rms of the signal over rms of the noise).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

HISTORIES = ("quasi_static", "sines", "random")


def mr_damper_law() -> dict:
    """A magnetorheological damper (force ~1 kN at 10 mm, 0.2 m/s); command in volts."""
    return {"c": 800.0, "k": 2.0e3, "alpha": 8.0e4, "gamma": 900.0, "delta": 300.0, "f0": 15.0,
            "fn": [], "c1": 2500.0, "alpha1": 2.0e5, "eta": 60.0, "m": 0.0}


def bouc_wen_law(fn: bool = False) -> dict:
    """A hysteretic isolator / bolted-joint law; with ``fn`` a cubic hardening and a nonlinear
    damping term."""
    law = {"c": 300.0, "k": 1.5e4, "alpha": 6.0e4, "gamma": 450.0, "delta": 150.0, "f0": -8.0, "fn": [],
           "c1": 0.0, "alpha1": 0.0, "eta": 0.0, "m": 0.0}
    if fn:
        law["fn"] = [(3, 0, 4.0e7), (2, 1, 2.0e7)]
    return law


def isolator_with_fixture(mass: float = 8.0) -> dict:
    """A Bouc-Wen isolator tested with a heavy moving fixture: F includes m x'' (use a random
    history with f_max of a few tens of Hz for the inertia to show)."""
    return dict(bouc_wen_law(), m=float(mass))


def isolator_with_end_stop(gap: float = 0.0075, kc: float = 2.0e5) -> dict:
    """The Bouc-Wen isolator hitting an end stop at |x| = gap (a physics the law's library lacks)."""
    return dict(bouc_wen_law(), contact=(float(kc), float(gap)))


def friction_law() -> dict:
    """Rate-independent friction-like hysteresis (quasi-static, no viscous term)."""
    return {"c": 0.0, "k": 5.0e3, "alpha": 1.2e5, "gamma": 1500.0, "delta": 500.0, "f0": 4.0,
            "fn": [(3, 0, 6.0e7)], "c1": 0.0, "alpha1": 0.0, "eta": 0.0, "m": 0.0}


def truth(law: dict) -> dict:
    """The law in shakerlab's names: c, k, alpha, gamma, delta, f0, fn {"y^3": ...}, c1, alpha1, eta."""
    def name(p, r):
        parts = ([("y" if p == 1 else f"y^{p}")] if p else []) + ([("dy" if r == 1 else f"dy^{r}")] if r else [])
        return "*".join(parts)
    out = {k: float(law[k]) for k in ("c", "k", "alpha", "gamma", "delta", "f0")}
    out["fn"] = {name(p, r): float(b) for p, r, b in law["fn"]}
    if law.get("eta"):
        out.update(c1=float(law["c1"]), alpha1=float(law["alpha1"]), eta=float(law["eta"]))
    if law.get("m"):
        out["mass"] = float(law["m"])
    if law.get("contact"):
        out["contact"] = {"kc": float(law["contact"][0]), "gap": float(law["contact"][1])}
    return out


# --------------------------------------------------------------------------- histories
def _ramp(t, T):
    """C2 ramp 0 -> 1 over [0, T] and its first two derivatives."""
    s = np.clip(t / T, 0.0, 1.0)
    r = s ** 3 * (10 - 15 * s + 6 * s * s)
    dr = np.where((t > 0) & (t < T), 30 * s * s * (1 - s) ** 2 / T, 0.0)
    ddr = np.where((t > 0) & (t < T), 60 * s * (1 - s) * (1 - 2 * s) / T ** 2, 0.0)
    return r, dr, ddr


def _ramp_scalar(t: float, T: float):
    if t <= 0.0:
        return 0.0, 0.0
    if t >= T:
        return 1.0, 0.0
    s = t / T
    return s ** 3 * (10 - 15 * s + 6 * s * s), 30 * s * s * (1 - s) ** 2 / T


class History:
    """x(t) = ramp(t) * sum_i A_i(t) sin(w_i t + phi_i), with piecewise-smooth amplitude levels."""

    def __init__(self, comps, ramp_s, duration, levels=None):
        self.A = np.array([c[0] for c in comps])
        self.w = np.array([c[1] for c in comps])
        self.phi = np.array([c[2] for c in comps])
        self.ramp_s = ramp_s
        self.duration = duration
        self.levels = levels    # None, or (times, gains): C2 transitions between gains

    def _gain(self, t):
        if self.levels is None:
            return np.ones_like(t), np.zeros_like(t), np.zeros_like(t)
        times, gains, T = self.levels
        g = np.full_like(t, gains[0])
        dg = np.zeros_like(t)
        ddg = np.zeros_like(t)
        for t0, g0, g1 in zip(times, gains[:-1], gains[1:]):
            r, dr, ddr = _ramp(t - t0, T)
            g = g + (g1 - g0) * r
            dg = dg + (g1 - g0) * dr
            ddg = ddg + (g1 - g0) * ddr
        return g, dg, ddg

    def velocity(self, t: float) -> float:
        """x'(t) at one time (the ODE's right side: plain floats, no array overhead)."""
        ph = self.w * t + self.phi
        s = float(np.sin(ph) @ self.A)
        ds = float(np.cos(ph) @ (self.A * self.w))
        r, dr = _ramp_scalar(t, self.ramp_s)
        g, dg = 1.0, 0.0
        if self.levels is not None:
            times, gains, T = self.levels
            g = gains[0]
            for t0, g0, g1 in zip(times, gains[:-1], gains[1:]):
                q, dq = _ramp_scalar(t - t0, T)
                g += (g1 - g0) * q
                dg += (g1 - g0) * dq
        return (dr * g + r * dg) * s + r * g * ds

    def __call__(self, t):
        """x, x', x'' at times t."""
        t = np.atleast_1d(np.asarray(t, float))
        ph = np.outer(t, self.w) + self.phi
        s = np.sin(ph) @ self.A
        ds = np.cos(ph) @ (self.A * self.w)
        dds = -np.sin(ph) @ (self.A * self.w ** 2)
        r, dr, ddr = _ramp(t, self.ramp_s)
        g, dg, ddg = self._gain(t)
        e, de, dde = r * g, dr * g + r * dg, ddr * g + 2 * dr * dg + r * ddg
        return e * s, de * s + e * ds, dde * s + 2 * de * ds + e * dds


def history(kind: str, rng, amplitude: float, duration: float, f_max: float = 6.0, f_qs: float = 0.1) -> History:
    if kind == "quasi_static":
        f = f_qs
        levels = (np.arange(1, 4) * duration / 4, [0.35, 0.6, 0.8, 1.0], 0.5 / f)
        return History([(amplitude, 2 * math.pi * f, 0.0)], 1.0 / f, duration, levels)
    if kind == "sines":
        n = 4
        fs_ = rng.uniform(0.5, 2.0, n)
        gains = rng.uniform(0.4, 1.0, n)
        gains[-1] = 1.0
        # a carrier at the mean drawn frequency whose amplitude steps through the drawn levels,
        # plus a slower tone, so that the loops are not all centred on x = 0
        f = float(np.mean(fs_))
        times = np.arange(1, n) * duration / n
        return History([(amplitude * 0.85, 2 * math.pi * f, 0.0),
                        (amplitude * 0.15, 2 * math.pi * f * 0.37, 1.0)],
                       1.5 / f, duration, (times, list(gains), 1.0 / f))
    if kind == "random":
        n = 40
        f = np.geomspace(0.3, f_max, n)
        A = f ** -1.0
        A = A / np.sqrt(0.5 * np.sum(A ** 2))        # unit rms
        comps = [(amplitude / 2.2 * a, 2 * math.pi * fi, p) for a, fi, p in
                 zip(A, f * rng.uniform(0.97, 1.03, n), rng.uniform(0, 2 * math.pi, n))]
        return History(comps, 1.0, duration)
    raise ValueError(f"history must be one of {HISTORIES}, got {kind!r}")


def command(rng, duration: float, levels=(0.0, 0.5, 1.0, 1.5, 2.0), dwell=(0.4, 1.5)):
    """A switched command: (switch times, levels), piecewise constant from 0 s."""
    times, vals = [0.0], [float(rng.choice(levels))]
    while times[-1] < duration:
        times.append(times[-1] + float(rng.uniform(*dwell)))
        nxt = float(rng.choice([v for v in levels if v != vals[-1]]))
        vals.append(nxt)
    return np.array(times), np.array(vals)


# --------------------------------------------------------------------------- integration
def simulate(law: dict, kind: str, fs: float | None = None, duration: float | None = None, amplitude: float = 0.01,
             seed: int = 0, f_max: float = 6.0, f_qs: float = 0.1) -> dict:
    """A noise-free component test: {"t", "x", "v", "force", ["cmd"], "z", "truth", "law", "history"}."""
    rng = np.random.default_rng(seed)
    duration = duration or (40.0 if kind == "quasi_static" else 12.0)
    fs = fs or (250.0 if kind == "quasi_static" else 1000.0)
    hist = history(kind, rng, amplitude, duration, f_max, f_qs)
    t = np.arange(int(round(duration * fs))) / fs
    mr = bool(law.get("eta"))
    if mr:
        sw, lv = command(rng, duration)
    else:
        sw, lv = np.array([0.0]), np.array([0.0])
    gam, dlt, eta = law["gamma"], law["delta"], law.get("eta", 0.0)

    def rhs(tt, s, v):
        xd = hist.velocity(tt)
        w, u = s
        return [xd - gam * abs(xd) * w - dlt * xd * abs(w), -eta * (u - v)]

    w = np.empty_like(t)
    u = np.empty_like(t)
    state = [0.0, float(lv[0])]
    bounds = list(sw) + [duration + 1.0]
    for i, v in enumerate(lv):
        a, b = bounds[i], min(bounds[i + 1], duration)
        if a >= duration:
            break
        sel = (t >= a) & (t < b) if i + 1 < len(lv) and bounds[i + 1] < duration else (t >= a)
        te = t[sel]
        sol = solve_ivp(rhs, (a, b), state, method="DOP853", rtol=1e-9, atol=1e-12, args=(float(v),),
                        dense_output=True)
        if te.size:
            vals = sol.sol(te)
            w[sel], u[sel] = vals[0], vals[1]
        state = list(sol.y[:, -1])
    x, xd, xdd = hist(t)
    cmd_t = lv[np.searchsorted(sw, t, side="right") - 1]
    c = law["c"] + law.get("c1", 0.0) * u
    a = law["alpha"] + law.get("alpha1", 0.0) * u
    fn = np.zeros_like(t)
    for p, r, b in law["fn"]:
        fn += b * x ** p * xd ** r
    z = a * w
    force = c * xd + law["k"] * x + fn + z + law["f0"] + law.get("m", 0.0) * xdd
    if law.get("contact"):         # an end stop: extra stiffness beyond a gap (not in the library)
        kc, gap = law["contact"]
        force = force + kc * np.sign(x) * np.maximum(np.abs(x) - gap, 0.0)
    out = {"t": t, "x": x, "v": xd, "force": force, "z": z, "u": u, "truth": truth(law), "law": dict(law),
           "history": kind}
    if mr:
        out["cmd"] = cmd_t
    return out


def add_noise(rec: dict, snr_db: float | None, seed: int) -> dict:
    """White Gaussian noise on x, v, force (and cmd) at ``snr_db`` (None: noise-free copy)."""
    out = dict(rec)
    if snr_db is None:
        return out
    rng = np.random.default_rng(10_000 + seed)
    for k in ("x", "v", "force", "cmd"):
        if k in rec:
            s = rec[k]
            rms = float(np.sqrt(np.mean((s - s.mean()) ** 2)))
            out[k] = s + rng.normal(0.0, rms * 10 ** (-snr_db / 20), s.size)
    out["snr_db"] = snr_db
    return out


def component_test(law: dict, kind: str, snr_db: float | None = 60.0, seed: int = 0, **kw) -> dict:
    """Fit and held-out records of one law: {"fit": rec, "validation": rec, "truth": ...}; the
    held-out record is another draw of the same kind of history."""
    fit = add_noise(simulate(law, kind, seed=seed, **kw), snr_db, seed)
    val = add_noise(simulate(law, kind, seed=seed + 7919, **kw), snr_db, seed + 7919)
    return {"fit": fit, "validation": val, "truth": truth(law)}


def write_csv(rec: dict, path, velocity: bool = False) -> None:
    """A constitutive CSV ``t,x,force[,v][,cmd]`` (full precision)."""
    cols = ["t", "x", "force"] + (["v"] if velocity else []) + (["cmd"] if "cmd" in rec else [])
    data = np.column_stack([rec[c] for c in cols])
    np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.12g")

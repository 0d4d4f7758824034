"""A second, independent generator of shaker-rig recordings (issues 13 and 18).

It shares no code with shakerlab: it imports only numpy, scipy and the standard library
(``tests/test_independent_generator.py`` asserts it), integrates its own equations with
``scipy.integrate.solve_ivp`` and returns plain dicts of arrays. The benches convert them
to shakerlab runs (``recon/testing/runs.py``).

Physics (SI units, not per unit mass). Base excitation, relative coordinate y = x_tip - x_base::

    m y'' + c y' + k (1 + r t_session) y + k2 y^2 + k3 y^3 + z + F_extra(y, y') - F0 = -m x_b''
    z' = alpha y' - gamma |y'| z - delta y' |z|          (z a force [N], Bouc-Wen n = 1)
    q'' + 2 zeta2 w2 q' + w2^2 q = -(1 - d2) x_b'' - d2 a_tip   (a second mode, seen by the tip sensor)

(d2 = 0: a structural mode driven by the base; d2 = 1: a resonance riding on the tip, driven by
its absolute acceleration a_tip = x_b'' + y''. Force excitation: (1 - d2) F/m - d2 y''.)

    F_extra = Fc tanh(y'/v_eps) + c2 y'|y'| + b2 y^2 y' + kc max(s y - gap, 0) s

Recorded: x_base = x_b(t), x_tip = (1 + e) (x_b + y + phi2 q) evaluated at t - tau
(a late tip channel is sampled from the dense solution, not interpolated from samples).
Force excitation: the right side is F(t), y = x, channels ``force`` and ``x``.

The truth is reported per unit mass with the parameter names of shakerlab's model JSON:
c_m = c/m, k_m = k/m, alpha_m = alpha/m, gamma, delta, fn_m {"y^2": k2/m, "y^3": k3/m}
(and inv_m = 1/m under force excitation). The small-amplitude natural frequency is
f_n = sqrt((k + alpha)/m) / 2 pi.

Protocols (every stage ramps up from rest and back down with C2-smooth ramps; a 1 s
unrecorded settle separates stages, the state carries through it; stage times run on
one session clock):

- ``paper``: one tone per stage: ``linear`` (~0.5 f_n, small), ``nonlinear`` (~0.9 f_n,
  large), ``validation`` (~0.75-0.82 f_n, another amplitude);
- ``rig``: the stage structure of rig/base_target_protocol.toml, amplitudes scaled to the
  system: ``linear`` (0.563 f_n), ``resonance_search`` (stepped sine, 12 geometric steps
  0.42-2.1 f_n then 5 refine steps, 1.5 s each), ``nonlinear`` (0.88 f_res, levels x1.5
  from 1/20 of the top level, 1.5 s dwell, then 0.75 s windows until two in a row agree on the
  complex gain of y to 0.5 %, at most 20 s more, as the rig's settle_tolerance does; from the
  second level on, as the rig judges, raising
  stops when, over the last 0.75 s, the harmonic distortion of y passes 1.2 %, the gain changed
  by 45 % or the loop loss factor by 200 % from the first level; then a 4 s hold),
  ``validation`` (0.7 f_res at 0.75 of the final level);
- ``sweep``: log chirps (``linear`` small 0.3-2 f_n, ``nonlinear`` large 0.6-1.4 f_n up,
  ``validation`` 1.4-0.6 f_n down);
- ``multisine``: random-phase multisines over 0.4-2 f_n, flat in base acceleration.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

PROTOCOLS = ("paper", "rig", "sweep", "multisine")
# concealed effects: physics the paper's model lacks ...
PHYSICAL_EFFECTS = ("coulomb_friction", "quadratic_damping", "channel_delay", "higher_mode", "parameter_drift",
                    "sensor_scale", "contact_stiffness", "offset")
# ... and model terms a given baseline lacks (the recording states the baseline without them)
STRUCTURAL_EFFECTS = ("cubic_stiffness", "quadratic_stiffness", "hysteresis")
# physics added after the diagnosis stress benchmark fixed its effect cycle on the two lists above
# (recon/testing/stress.py): damping that grows with the amplitude, as micro-slip in a bolted joint
MORE_PHYSICAL_EFFECTS = ("amplitude_damping",)
EFFECTS = ("none",) + PHYSICAL_EFFECTS + STRUCTURAL_EFFECTS + MORE_PHYSICAL_EFFECTS
SETTLE_S = 1.0
QUANTITIES = ("displacement", "velocity", "acceleration")    # how the response may be recorded (add_noise)
# the rig protocol's nonlinear levels are judged once steady: two 0.75 s windows in a row agree on
# the complex gain of y over the base to SETTLE_TOLERANCE, waiting at most SETTLE_MAX_S more
SETTLE_TOLERANCE = 0.005
SETTLE_MAX_S = 20.0
_TWO_PI = 2 * math.pi


# --------------------------------------------------------------------------- systems
def random_system(rng, hysteresis: bool | None = True, quadratic: bool | None = None, cubic: bool | None = None,
                  fn_range=(5.0, 60.0)) -> dict:
    """A random TMP-like SDOF (physical units). ``None`` for a flag: drawn at random.

    Scales: f_n log-uniform in ``fn_range``; damping ratio 0.5-3 %; the design amplitude
    Y (peak relative displacement of the nonlinear stage) 0.5-5 mm x sqrt(10 Hz / f_n);
    Bouc-Wen alpha 20-60 % of the small-amplitude stiffness, lambda = gamma + delta =
    1-4 / Y, split with both positive or delta negative (gamma > 0 always: see below); k2 = +-(3-15 %) K / Y;
    k3 = (5-30 %) K / Y^2."""
    m = float(math.exp(rng.uniform(math.log(0.05), math.log(0.5))))
    f_n = float(math.exp(rng.uniform(math.log(fn_range[0]), math.log(fn_range[1]))))
    K = m * (2 * math.pi * f_n) ** 2
    zeta = float(rng.uniform(0.005, 0.03))
    Y = float(math.exp(rng.uniform(math.log(0.5e-3), math.log(5e-3))) * math.sqrt(10.0 / f_n))
    hysteresis = bool(rng.random() < 0.75) if hysteresis is None else hysteresis
    quadratic = bool(rng.random() < 0.5) if quadratic is None else quadratic
    cubic = bool(rng.random() < 0.5) if cubic is None else cubic
    sys_ = {"m": m, "c": 2 * zeta * math.sqrt(K * m), "k": K, "alpha": 0.0, "gamma": 0.0, "delta": 0.0,
            "k2": 0.0, "k3": 0.0, "f_n": f_n, "zeta": zeta, "Y": Y, "bw_kind": "none"}
    if hysteresis:
        a = float(rng.uniform(0.2, 0.6)) * K
        lam = float(rng.uniform(1.0, 4.0)) / Y
        # gamma < 0 is left out: with gamma + delta > 0 the unloading slope alpha + (gamma - delta) z
        # turns negative before z reaches alpha / (gamma + delta) and z then grows without bound
        if rng.random() < 0.65:
            kind, rho = "gamma>0,delta>0", rng.uniform(0.05, 0.95)
        else:
            kind, rho = "delta<0", rng.uniform(-0.6, -0.05)
        sys_.update(alpha=a, k=K - a, gamma=float((1 - rho) * lam), delta=float(rho * lam), bw_kind=kind)
    if cubic:
        sys_["k3"] = float(rng.uniform(0.05, 0.3)) * K / Y ** 2
    if quadratic:
        sys_["k2"] = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.03, 0.15)) * K / Y
        if not cubic:
            # without a cubic term a quadratic spring lets the mass escape beyond y = k / |k2|
            # (k: the stiffness left once the hysteresis saturates): keep that beyond 12 Y
            sys_["k2"] = math.copysign(min(abs(sys_["k2"]), sys_["k"] / (12 * Y)), sys_["k2"])
    return sys_


def corner_system(rng, fn_range=(18.0, 32.0)) -> dict:
    """A system of the corner issue 76 names: a Bouc-Wen law with negative delta beside a
    hardening cubic spring and damping that grows with the amplitude (y^2 y'), f_n near 24 Hz.

    The scales are :func:`random_system`'s; what is fixed is the corner: the law's delta / gamma
    is -0.15 to -0.4 (gamma 400 /m, delta -100 /m on a design amplitude of 2.5-10 mm: lambda Y =
    (gamma + delta) Y in 0.75-3), the cubic stiffens the spring by 5-30 % at Y, and b2 dissipates
    10-40 % of the viscous damping's energy per cycle at Y."""
    s = random_system(rng, hysteresis=False, quadratic=False, cubic=True, fn_range=fn_range)
    K, Y = s["k"], s["Y"]
    a = float(rng.uniform(0.2, 0.6)) * K
    ratio = float(rng.uniform(-0.4, -0.15))           # delta / gamma
    lam = float(rng.uniform(0.75, 3.0)) / Y           # gamma + delta
    gamma = lam / (1.0 + ratio)
    s.update(alpha=a, k=K - a, gamma=float(gamma), delta=float(ratio * gamma), bw_kind="delta<0",
             b2=float(rng.uniform(0.1, 0.4)) * 4 * s["c"] / Y ** 2)
    return s


def truth_per_unit_mass(s: dict, excitation: str = "base") -> dict:
    """The system in shakerlab's per-unit-mass names (model JSON ``parameters``)."""
    m = s["m"]
    fn = {}
    if s["k2"]:
        fn["y^2"] = s["k2"] / m
    if s["k3"]:
        fn["y^3"] = s["k3"] / m
    if s.get("b2"):
        fn["y^2*dy"] = s["b2"] / m
    out = {"c_m": s["c"] / m, "k_m": s["k"] / m, "alpha_m": s["alpha"] / m, "gamma": s["gamma"],
           "delta": s["delta"], "fn_m": fn}
    if excitation == "force":
        out["inv_m"] = 1.0 / m
    return out


# --------------------------------------------------------------------------- drives
def _ramp(s):
    """C2-smooth step 0 -> 1 on [0, 1] and its first two derivatives (in s)."""
    s = np.clip(s, 0.0, 1.0)
    tp = 2 * math.pi
    return s - np.sin(tp * s) / tp, 1 - np.cos(tp * s), tp * np.sin(tp * s)


class Segment:
    """One smooth piece of a drive: envelope e0 -> e1 (C2 ramp over the segment, or constant)
    times a carrier sum_k A_k sin(theta_k(t)).

    carrier: ("tones", omegas, amps, phases) with theta = omega (t - t0) + phase, or
    ("chirp", f0, f1, phase) a logarithmic chirp from f0 to f1 over the segment."""

    def __init__(self, t0, t1, e0, e1, carrier, t_ref=None, T_ref=None):
        self.t0, self.t1, self.e0, self.e1, self.carrier = float(t0), float(t1), float(e0), float(e1), carrier
        # the carrier's own time origin and length (a stage cut into ramp pieces shares one carrier)
        self.t_ref = self.t0 if t_ref is None else float(t_ref)
        self.T_ref = self.t1 - self.t0 if T_ref is None else float(T_ref)

    def envelope(self, t):
        T = self.t1 - self.t0
        if self.e0 == self.e1:
            return self.e0 + 0 * t, 0 * t, 0 * t
        S, dS, ddS = _ramp((t - self.t0) / T)
        d = self.e1 - self.e0
        return self.e0 + d * S, d * dS / T, d * ddS / T ** 2

    def carrier_values(self, t):
        kind = self.carrier[0]
        tl = t - self.t_ref
        if kind == "tones":
            _, w, A, ph = self.carrier
            th = np.multiply.outer(tl, w) + ph
            s, c = np.sin(th), np.cos(th)
            return s @ A, c @ (A * w), -(s @ (A * w ** 2))
        _, f0, f1, ph = self.carrier
        L = math.log(f1 / f0) / self.T_ref
        ex = np.exp(L * tl)                 # each function value taken once (the same values)
        f = f0 * ex
        th = 2 * math.pi * f0 * (ex - 1) / L + ph
        w, dw = 2 * math.pi * f, 2 * math.pi * f * L
        sn, cs = np.sin(th), np.cos(th)
        return sn, w * cs, dw * cs - w ** 2 * sn

    def end_phase(self):
        """Phase of each carrier component at t1 (to continue a tone phase-continuously)."""
        T = self.t1 - self.t_ref
        if self.carrier[0] == "tones":
            return self.carrier[1] * T + self.carrier[3]
        _, f0, f1, ph = self.carrier
        return 2 * math.pi * f0 * (f1 / f0 - 1) * T / math.log(f1 / f0) + ph

    def accel(self, t: float) -> float:
        """x''(t) for a scalar t (the integrator's fast path: plain floats for one component).

        The right side calls it at every stage of every step, so the segment's constants are
        taken apart once (:meth:`_accel_constants`); the arithmetic is the same, operation for
        operation, as it was inline (the recordings are the same to the bit: issue 70)."""
        try:
            ramp, T, e0, d, dtp, T2, tone = self._acc
        except AttributeError:
            ramp, T, e0, d, dtp, T2, tone = self._acc = self._accel_constants()
        if ramp:
            sc = min(max((t - self.t0) / T, 0.0), 1.0)
            sn_r = math.sin(_TWO_PI * sc)
            e = e0 + d * (sc - sn_r / _TWO_PI)
            de = d * (1 - math.cos(_TWO_PI * sc)) / T
            dde = dtp * sn_r / T2
        else:
            e, de, dde = e0, 0.0, 0.0
        if tone is not None:
            w, A, ph, t_ref, Aw, mAww = tone
            th = w * (t - t_ref) + ph
            sn = math.sin(th)
            s, ds, dds = A * sn, Aw * math.cos(th), mAww * sn
        elif self.carrier[0] == "tones":
            c = self.carrier
            if not hasattr(self, "_M"):     # (s, s', s'') = Im(M exp(i theta)), one product per call
                self._M = np.array([c[2], 1j * c[2] * c[1], -c[2] * c[1] ** 2], complex)
            s, ds, dds = (self._M @ np.exp(1j * (c[1] * (t - self.t_ref) + c[3]))).imag
        else:
            s, ds, dds = (float(v) for v in self.carrier_values(np.float64(t)))
        return dde * s + 2 * de * ds + e * dds

    def _accel_constants(self):
        """(ramp?, T, e0, e1 - e0, (e1 - e0) 2 pi, T^2, tone) for :meth:`accel`; tone: (w, A, phase,
        t_ref, A w, -A w w) as floats for a single-tone carrier, else None."""
        T = self.t1 - self.t0
        d = self.e1 - self.e0
        c = self.carrier
        tone = None
        if c[0] == "tones" and c[1].size == 1:
            w, A = float(c[1][0]), float(c[2][0])
            tone = (w, A, float(c[3][0]), self.t_ref, A * w, -A * w * w)
        return self.e0 != self.e1, T, self.e0, d, d * _TWO_PI, T ** 2, tone

    def __call__(self, t):
        """(x, x', x'') of the drive at t (scalar or array)."""
        e, de, dde = self.envelope(t)
        s, ds, dds = self.carrier_values(t)
        return e * s, de * s + e * ds, dde * s + 2 * de * ds + e * dds


def _tone(w, phase=0.0):
    return ("tones", np.array([w], float), np.array([1.0]), np.array([phase], float))


def ramped_tone(t0, f, amp, hold, ramp, phase=0.0):
    """Segments of one tone: ramp up over ``ramp`` s, hold ``hold`` s, ramp down."""
    w = 2 * math.pi * f
    out = [Segment(t0, t0 + ramp, 0.0, amp, _tone(w, phase))]
    for e0, e1, T in ((amp, amp, hold), (amp, 0.0, ramp)):
        prev = out[-1]
        out.append(Segment(prev.t1, prev.t1 + T, e0, e1, _tone(w, float(prev.end_phase()[0]))))
    return out


def _continue(prev, t1, e0, e1, w):
    return Segment(prev.t1, t1, e0, e1, _tone(w, float(np.atleast_1d(prev.end_phase())[0])))


GLIDE_PERIODS = 2.0


def _glide(prev, f1):
    """From ``prev``'s tone to ``f1`` Hz: a logarithmic frequency glide over GLIDE_PERIODS periods of
    the lower frequency, at ``prev``'s final level. A phase-continuous step in frequency keeps the
    base displacement continuous but makes its velocity jump (A w cos theta with a new w): the
    recorded base then has an impulse in its second derivative that the structure, driven by each
    tone's own smooth x'', never felt (its relative velocity stayed continuous, so the tip's
    absolute velocity jumped instead), so that even the truth, noise-free, would not simulate such a
    stage from the recorded base to the noise floor. Inside the glide x'' = A (w' cos theta - w^2 sin
    theta) carries the change of speed."""
    f0 = float(prev.carrier[1][0]) / (2 * math.pi)
    T = GLIDE_PERIODS / min(f0, f1)
    return Segment(prev.t1, prev.t1 + T, prev.e1, prev.e1, ("chirp", f0, float(f1), float(prev.end_phase()[0])))


# --------------------------------------------------------------------------- integration
def _rhs_factory(s: dict, eff: dict, excitation: str, seg: Segment):
    m, c, k, alpha, gamma, delta, k2, k3 = (s["m"], s["c"], s["k"], s["alpha"], s["gamma"], s["delta"],
                                            s["k2"], s["k3"])
    Fc, v_eps, c2 = eff.get("Fc", 0.0), eff.get("v_eps", 1.0), eff.get("c2", 0.0)
    b2 = eff.get("b2", 0.0) + s.get("b2", 0.0)       # the effect's and the system's own y^2 y' damping
    kc, gap, side = eff.get("kc", 0.0), eff.get("gap", 0.0), eff.get("side", 1.0)
    rate, F0 = eff.get("drift_rate", 0.0), eff.get("F0", 0.0)
    w2, zeta2, d2 = eff.get("w2", 0.0), eff.get("zeta2", 0.0), eff.get("drive2", 0.0)
    base = excitation == "base"
    accel = seg.accel

    def rhs(t, x):
        # plain floats (x.tolist(), float(t)): the same IEEE arithmetic as on numpy scalars, without
        # their overhead (the recordings are the same to the bit: issue 70)
        y, v, z, q, qd = x.tolist()
        t = float(t)
        u = -accel(t) if base else float(seg(t)[0]) / m     # input per unit mass
        f = c * v + k * (1.0 + rate * t) * y + k2 * y * y + k3 * y * y * y + z - F0
        if Fc:
            f += Fc * math.tanh(v / v_eps)
        if c2:
            f += c2 * v * abs(v)
        if b2:
            f += b2 * y * y * v
        if kc:
            p = side * y - gap
            if p > 0:
                f += kc * p * side
        dz = alpha * v - gamma * abs(v) * z - delta * v * abs(z)
        ydd = u - f / m
        drive = u
        if d2:
            a_tip = -u + ydd if base else ydd        # the tip's absolute acceleration (base: x_b'' = -u)
            drive = (1.0 - d2) * u - d2 * a_tip
        dqd = drive - 2 * zeta2 * w2 * qd - w2 * w2 * q if w2 else 0.0
        return [v, ydd, dz, qd if w2 else 0.0, dqd]

    return rhs


def _integrate(s, eff, excitation, segs, x0, f_max):
    """Integrate segment by segment; returns the list of dense solutions and the final state."""
    sols = []
    x = np.asarray(x0, float)
    scale = np.array([s["Y"], s["Y"] * 2 * math.pi * s["f_n"], max(s["alpha"], s["k"]) * s["Y"] + 1e-12,
                      s["Y"], s["Y"] * 2 * math.pi * s["f_n"]])
    for seg in segs:
        if seg.t1 <= seg.t0:
            continue
        sol = solve_ivp(_rhs_factory(s, eff, excitation, seg), (seg.t0, seg.t1), x, method="DOP853",
                        rtol=1e-7, atol=1e-10 * scale, dense_output=True, max_step=1.0 / (5 * f_max))
        if not sol.success:
            raise FloatingPointError(f"solve_ivp failed at t = {sol.t[-1]:.4g} s: {sol.message}")
        sols.append(sol)
        x = sol.y[:, -1]
    return sols, x


def _dense(sol, t):
    """``sol.sol(t)`` (states (5, n) at the times t, a 1-D array) in one vectorised pass.

    scipy's OdeSolution finds each time's step and calls that step's DOP853 interpolant on the
    times in it, one Python call per step (tens of thousands per stage); here every time takes
    its step the same way (searchsorted on the step times, the same side) and the interpolant's
    arithmetic runs on all times at once, operation for operation as Dop853DenseOutput._call_impl
    does it (each time's value on its own: the same values to the bit, issue 70). Anything but a
    solution of DOP853 steps goes to scipy."""
    ode = sol.sol
    packed = getattr(sol, "_packed", None)
    if packed is None:
        ip = ode.interpolants
        if not (ode.ascending and ip and all(type(i).__name__ == "Dop853DenseOutput" for i in ip)):
            return ode(t)
        packed = sol._packed = (np.array([i.F for i in ip]), np.array([i.t_old for i in ip]),
                                np.array([i.h for i in ip]), np.array([i.y_old for i in ip]))
    F, t_old, h, y_old = packed
    seg = np.searchsorted(ode.ts_sorted, t, side=ode.side) - 1
    np.clip(seg, 0, ode.n_segments - 1, out=seg)
    x = ((t - t_old[seg]) / h[seg])[:, None]
    y = np.zeros((t.size, y_old.shape[1]))
    for i in range(F.shape[1]):          # Dop853DenseOutput._call_impl: reversed(F), x and 1 - x in turn
        y += F[seg, F.shape[1] - 1 - i]
        if i % 2 == 0:
            y *= x
        else:
            y *= 1 - x
    y += y_old[seg]
    return y.T


def _evaluate(segs, sols, t, drive=True):
    """States (5, n) and drive (x, x', x'') at times t (zero state and drive before the stage);
    ``drive=False``: the states only (the drive None)."""
    st = np.zeros((5, t.size))
    dr = np.zeros((3, t.size)) if drive else None
    for seg, sol in zip([g for g in segs if g.t1 > g.t0], sols):
        sel = (t >= seg.t0) & (t <= seg.t1)
        if sel.any():
            st[:, sel] = _dense(sol, t[sel])
            if drive:
                dr[:, sel] = np.array(seg(t[sel]))
    return st, dr


def _harmonics(t, y, f, n=5):
    """Amplitudes of harmonics 1..n of f in y (least squares with a constant)."""
    w = 2 * math.pi * f
    cols = [np.ones_like(t)] + [g(h * w * t) for h in range(1, n + 1) for g in (np.sin, np.cos)]
    coef = np.linalg.lstsq(np.column_stack(cols), y, rcond=None)[0]
    return np.hypot(coef[1::2], coef[2::2])


def _complex_gain(t, y, xb, f):
    """Fundamental of y over that of the base motion xb, as complex amplitudes (least squares with
    a constant)."""
    w = 2 * math.pi * f
    a = np.column_stack([np.ones_like(t), np.cos(w * t), np.sin(w * t)])
    cy = np.linalg.lstsq(a, y, rcond=None)[0]
    cb = np.linalg.lstsq(a, xb, rcond=None)[0]
    return complex(cy[1], -cy[2]) / complex(cb[1], -cb[2])


def _loss_factor(t, st, dr, f, exc):
    """Loss factor of the loop over the whole periods at the end of a window, as the rig's level
    analysis defines it: energy per cycle of r against y over pi |R_1| |Y_1|, with r = -x_tip''
    (base excitation) or the force (force excitation); evaluated on the true states."""
    dt = float(t[1] - t[0])
    cycles = math.floor((t[-1] - t[0]) * f)
    if cycles < 1:
        return 0.0
    n = int(round(cycles / f / dt))
    y, dy = st[0][-n:], st[1][-n:]
    r = -(dr[2] + np.gradient(st[1], dt)) if exc == "base" else dr[0]
    r = r[-n:]
    energy = float(np.sum(r * dy) * dt) / cycles
    r1, y1 = _harmonics(t[-n:], r, f, 1)[0], _harmonics(t[-n:], y, f, 1)[0]
    return energy / max(math.pi * r1 * y1, 1e-300)


# --------------------------------------------------------------------------- effects
def effect_parameters(effect: str, strength: float, s: dict, rng, peaks=None) -> dict:
    """The effect's physical parameters at ``strength`` x its nominal scale (relative to the
    system: its stiffness K, design amplitude Y, damping c, natural frequency)."""
    K, Y, wn = s["k"] + s["alpha"], s["Y"], 2 * math.pi * s["f_n"]
    sg = float(rng.choice([-1.0, 1.0]))
    if effect == "none":
        return {}
    if effect == "coulomb_friction":          # 0.3 % of the elastic force at Y
        return {"Fc": 0.003 * strength * K * Y, "v_eps": 1e-3 * wn * Y}
    if effect == "quadratic_damping":         # 40 % of the viscous dissipation per cycle at Y, 0.9 f_n
        return {"c2": 0.4 * strength * 3 * math.pi * s["c"] / (8 * 0.9 * wn * Y)}
    if effect == "amplitude_damping":         # 40 % of the viscous dissipation per cycle at Y (any frequency)
        return {"b2": 0.4 * strength * 4 * s["c"] / Y ** 2}
    if effect == "channel_delay":             # 0.4 % of the natural period
        return {"tau": 0.004 * strength / s["f_n"]}
    if effect == "higher_mode":
        lo, hi = s.get("_mode_ratio", (2.5, 3.5))
        return {"w2": float(rng.uniform(lo, hi)) * wn, "zeta2": float(rng.uniform(0.01, 0.03)),
                "phi2": 0.25 * strength}
    if effect == "parameter_drift":           # 0.05 %/s of session time, either sign
        return {"drift_rate": sg * 5e-4 * strength}
    if effect == "sensor_scale":
        return {"tip_scale": sg * 0.02 * strength}
    if effect == "contact_stiffness":
        side = sg
        peak = Y if peaks is None else peaks[0 if side > 0 else 1]
        return {"kc": 0.2 * strength * K, "side": side, "gap": float(rng.uniform(0.55, 0.75)) * peak}
    if effect == "offset":                    # static offset 5 % of Y
        return {"F0": sg * 0.05 * strength * K * Y}
    raise ValueError(f"unknown effect {effect!r} (known: {', '.join(EFFECTS)})")


def apply_structural(effect: str, strength: float, s: dict, rng) -> tuple[dict, dict]:
    """(system with the term, system of the baseline without it) for the structural effects."""
    s = dict(s)
    K, Y = s["k"] + s["alpha"], s["Y"]
    if effect == "cubic_stiffness":
        s["k3"] = 0.15 * strength * K / Y ** 2
        b = dict(s, k3=0.0)
    elif effect == "quadratic_stiffness":
        s["k2"] = float(rng.choice([-1.0, 1.0])) * 0.1 * strength * K / Y
        b = dict(s, k2=0.0)
    elif effect == "hysteresis":
        a = 0.15 * strength * K
        lam = float(rng.uniform(1.5, 3.0)) / Y
        s.update(alpha=a, k=K - a, gamma=0.6 * lam, delta=0.4 * lam, bw_kind="gamma>0,delta>0")
        b = dict(s, alpha=0.0, gamma=0.0, delta=0.0, k=K)
    else:
        raise ValueError(effect)
    return s, b


# --------------------------------------------------------------------------- protocols
def _gain(s, f):
    """Linear relative-displacement gain |Y/X_b| (base) or |Y/F| (force) at f."""
    K = s["k"] + s["alpha"]
    w = 2 * math.pi * f
    H = 1.0 / (K - s["m"] * w ** 2 + 1j * s["c"] * w)
    return abs(s["m"] * w ** 2 * H) if s.get("_excitation", "base") == "base" else abs(H)


def _durations(f, periods, lo, hi):
    return float(np.clip(periods / f, lo, hi))


class _Sim:
    """Runs the stages of one recording on one session clock, carrying the state."""

    def __init__(self, s, eff, excitation, fs, f_max):
        self.s, self.eff, self.exc, self.fs, self.f_max = s, eff, excitation, fs, f_max
        self.t = 0.0
        self.x = np.zeros(5)
        if eff.get("F0"):                     # start at the static equilibrium of the offset force
            y = eff["F0"] / s["k"]
            for _ in range(50):
                g = s["k"] * y + s["k2"] * y * y + s["k3"] * y ** 3 - eff["F0"]
                y -= g / (s["k"] + 2 * s["k2"] * y + 3 * s["k3"] * y * y)
            self.x[0] = y
        self.stages = {}

    def probe(self, segs_fn, measure=lambda t, y: float(np.max(np.abs(y)))):
        """Simulate a trial stage from the current state without keeping it; returns measure(t, y)."""
        segs = segs_fn(self.t)
        try:
            sols, _ = _integrate(self.s, self.eff, self.exc, segs, self.x, self.f_max)
        except FloatingPointError:      # the trial diverged: None (the caller lowers the drive)
            return None
        t = np.arange(segs[0].t0, segs[-1].t1, 1.0 / self.fs)
        st, _ = _evaluate(segs, sols, t, drive=False)
        return measure(t, st[0])

    def record(self, name, segs, excitation_desc, solved=None):
        """Record a stage (``solved``: its (solutions, final state) when already integrated)."""
        sols, x_end = solved or _integrate(self.s, self.eff, self.exc, segs, self.x, self.f_max)
        t0, t1 = segs[0].t0, segs[-1].t1
        t = t0 + np.arange(int(math.floor((t1 - t0) * self.fs)) + 1) / self.fs
        st, dr = _evaluate(segs, sols, t)
        tau = self.eff.get("tau", 0.0)
        st_tip = st
        if tau:
            st_tip, dr_tip = _evaluate(segs, sols, t - tau)
            st_tip[0, t - tau < t0] = self.x[0]     # before the stage: the state it started from
        else:
            dr_tip = dr
        phi2, e = self.eff.get("phi2", 0.0), self.eff.get("tip_scale", 0.0)
        disp = st_tip[0] + phi2 * st_tip[3]
        vel = st_tip[1] + phi2 * st_tip[4]
        # the response's acceleration: a central difference of the dense solution (h = 1e-4 / fs: the
        # DOP853 interpolant is smooth within a step, so the difference is exact to ~1e-8 relative)
        # At the stage's ends the difference is one-sided, inside the stage: the solution does not
        # continue past them (a central difference there straddled the settle before the stage and
        # read tens of thousands of m/s^2 at the first sample)
        h = 1e-4 / self.fs
        tt = np.clip(t - tau, t0 + h, t1 - h)
        # (the drive is not needed there: states only, both sides in one pass; the dense output is
        # evaluated point by point, so the values are those of two passes)
        spm, _ = _evaluate(segs, sols, np.concatenate([tt + h, tt - h]), drive=False)
        sp, sm = spm[:, :t.size], spm[:, t.size:]
        acc = ((sp[1] + phi2 * sp[4]) - (sm[1] + phi2 * sm[4])) / (2 * h)
        if self.exc == "base":
            ch = {"x_base": dr[0], "x_tip": (1 + e) * (dr_tip[0] + disp)}
            # the tip's absolute velocity and acceleration, for a recording made with a vibrometer or an
            # accelerometer (add_noise quantity)
            ch["v_tip"] = (1 + e) * (dr_tip[1] + vel)
            ch["a_tip"] = (1 + e) * (dr_tip[2] + acc)
        else:
            ch = {"force": dr[0], "x": (1 + e) * disp, "v": (1 + e) * vel, "a": (1 + e) * acc}
        self.stages[name] = {"t": t, **ch, "excitation": self.exc, "description": excitation_desc,
                             "truth_states": {"y": st[0], "dy": st[1], "z": st[2]}}
        self.x = x_end
        # unrecorded settle: free motion, no drive
        rest = [Segment(t1, t1 + SETTLE_S, 0.0, 0.0, _tone(1.0))]
        _, self.x = _integrate(self.s, self.eff, self.exc, rest, self.x, self.f_max)
        self.t = t1 + SETTLE_S
        return st[0]


def _calibrate(sim, f, Y, amp0, ramp_periods=5, periods=40):
    """Drive amplitude at f giving a peak relative displacement of about Y (one trial tone from
    the current state, rescaled once). Returns (amplitude, (peak+, peak-) expected)."""
    hold = periods / f
    ramp = ramp_periods / f

    def meas(t, y):
        tail = y[(t >= t[0] + ramp + 0.5 * hold) & (t <= t[0] + ramp + hold)]
        return float(np.max(tail)), float(-np.min(tail))

    pk = sim.probe(lambda t0: ramped_tone(t0, f, amp0, hold, ramp), meas)
    if pk is None:
        return 0.2 * amp0, (Y, Y)
    scale = float(np.clip(Y / max(max(pk), 1e-15), 0.2, 5.0))
    return amp0 * scale, (pk[0] * scale, pk[1] * scale)


def _paper(sim, s, rng):
    fn, Y = s["f_n"], s["Y"]
    f_lin, f_nl, f_val = (fn * rng.uniform(0.45, 0.55), fn * rng.uniform(0.86, 0.94), fn * rng.uniform(0.72, 0.82))
    amp_nl, peaks = _calibrate(sim, f_nl, Y, Y / _gain(s, f_nl))
    y_lin = Y * rng.uniform(0.01, 0.05)
    amp_lin = y_lin / _gain(s, f_lin)
    amp_val = amp_nl * rng.uniform(0.8, 1.3)
    desc = {}
    for name, f, a, periods, lo, hi in (("linear", f_lin, amp_lin, 40, 3, 10), ("nonlinear", f_nl, amp_nl, 80, 4, 12),
                                        ("validation", f_val, amp_val, 50, 3, 10)):
        hold, ramp = _durations(f, periods, lo, hi), _durations(f, 5, 0.3, 2.0)
        sim.record(name, ramped_tone(sim.t, f, a, hold, ramp, rng.uniform(0, 2 * math.pi)),
                   {"kind": "tone", "f_hz": f, "amplitude": a, "hold_s": hold, "ramp_s": ramp})
        desc[name] = f
    return peaks


def _paper_above(sim, s, rng):
    """The paper's protocol (one tone per stage) with its validation stage driven above the
    resonance (1.15-1.35 f_n), at a drive whose linear response is 0.15-0.5 of the nonlinear
    stage's design amplitude Y: off resonance a validation stage moves less than the nonlinear
    one, and a hardening system driven harder there can jump to its upper branch (a record the
    fitting stages say nothing about)."""
    fn, Y = s["f_n"], s["Y"]
    f_lin, f_nl, f_val = (fn * rng.uniform(0.45, 0.55), fn * rng.uniform(0.86, 0.94), fn * rng.uniform(1.15, 1.35))
    amp_nl, peaks = _calibrate(sim, f_nl, Y, Y / _gain(s, f_nl))
    amp_lin = Y * rng.uniform(0.01, 0.05) / _gain(s, f_lin)
    amp_val = Y * rng.uniform(0.15, 0.5) / _gain(s, f_val)
    for name, f, a, periods, lo, hi in (("linear", f_lin, amp_lin, 40, 3, 10), ("nonlinear", f_nl, amp_nl, 80, 4, 12),
                                        ("validation", f_val, amp_val, 50, 3, 10)):
        hold, ramp = _durations(f, periods, lo, hi), _durations(f, 5, 0.3, 2.0)
        sim.record(name, ramped_tone(sim.t, f, a, hold, ramp, rng.uniform(0, 2 * math.pi)),
                   {"kind": "tone", "f_hz": f, "amplitude": a, "hold_s": hold, "ramp_s": ramp})
    return peaks


def _rig(sim, s, rng):
    """The stage structure of rig/base_target_protocol.toml (specimen at 14.2 Hz there)."""
    fn, Y = s["f_n"], s["Y"]
    # top level: the amplitude that brings y to ~1.5 Y at 0.88 f_res
    fr_grid = np.linspace(0.7 * fn, 1.3 * fn, 2001)
    f_res = float(fr_grid[np.argmax([abs(1 + _gain(s, f)) if sim.exc == "base" else _gain(s, f)
                                     for f in fr_grid])])
    f_nl = 0.88 * f_res
    top, _ = _calibrate(sim, f_nl, 1.5 * Y, 1.5 * Y / _gain(s, f_nl))
    rate = top / 6.0                       # the ramp takes ~6 s from zero to the top level
    # linear stage: 8/14.2 f_n at top/16, 4 s
    f_lin = 8.0 / 14.2 * fn
    a = top / 16
    sim.record("linear", ramped_tone(sim.t, f_lin, a, 4.0, max(a / rate, 2 / f_lin)),
               {"kind": "tone", "f_hz": f_lin, "amplitude": a, "hold_s": 4.0})
    # resonance search: stepped sine at top/160, 1.5 s per frequency, phase-continuous
    coarse = np.geomspace(6.0 / 14.2 * fn, 30.0 / 14.2 * fn, 12)
    g = [abs(1 + _gain(s, f)) if sim.exc == "base" else _gain(s, f) for f in coarse]
    i = int(np.argmax(g))
    lo_, hi_ = coarse[max(i - 1, 0)], coarse[min(i + 1, 11)]
    freqs = list(coarse) + list(np.linspace(lo_, hi_, 7)[1:-1])
    a = top / 160
    segs = [Segment(sim.t, sim.t + max(a / rate, 2 / freqs[0]), 0.0, a, _tone(2 * math.pi * freqs[0]))]
    for j, f in enumerate(freqs):
        if j and not math.isclose(f, freqs[j - 1]):
            segs.append(_glide(segs[-1], f))     # velocity-continuous: a shaker cannot jump in speed
        segs.append(_continue(segs[-1], segs[-1].t1 + 1.5, a, a, 2 * math.pi * f))
    segs.append(_continue(segs[-1], segs[-1].t1 + max(a / rate, 2 / freqs[-1]), a, 0.0, 2 * math.pi * freqs[-1]))
    sim.record("resonance_search", segs, {"kind": "stepped_sine", "f_hz": [float(f) for f in freqs], "amplitude": a,
                                          "glide_periods": GLIDE_PERIODS})
    # nonlinear: levels x1.5 from top/20, dwell 1.5 s, decide on the last 0.75 s, hold 4 s
    w = 2 * math.pi * f_nl
    level, levels, reason = top / 20, [], "max level"
    t0 = sim.t
    segs = [Segment(t0, t0 + max(level / rate, 2 / f_nl), 0.0, level, _tone(w))]
    sols, x = _integrate(sim.s, sim.eff, sim.exc, segs, sim.x, sim.f_max)
    g0 = l0 = None
    while True:
        segs.append(_continue(segs[-1], segs[-1].t1 + 1.5, level, level, w))
        new_sols, x = _integrate(sim.s, sim.eff, sim.exc, segs[-1:], x, sim.f_max)
        sols += new_sols
        # settle (settle_tolerance 0.005, settle_max_s 20 in the rig's protocol): more 0.75 s windows
        # until two in a row give the same complex gain of y over the base to 0.5 %
        t_an = np.arange(segs[-1].t1 - 1.5, segs[-1].t1 - 0.75, 1.0 / sim.fs)
        st, dr = _evaluate(segs[-1:], new_sols, t_an)
        g_prev = _complex_gain(t_an, st[0], dr[0], f_nl) if sim.exc == "base" else None
        extra = 0.0
        while True:
            t_an = np.arange(segs[-1].t1 - 0.75, segs[-1].t1, 1.0 / sim.fs)
            st, dr = _evaluate(segs[-1:], new_sols, t_an)
            if g_prev is None:
                break
            g = _complex_gain(t_an, st[0], dr[0], f_nl)
            if abs(g - g_prev) <= SETTLE_TOLERANCE * abs(g) or extra + 0.75 > SETTLE_MAX_S:
                break
            g_prev, extra = g, extra + 0.75
            segs.append(_continue(segs[-1], segs[-1].t1 + 0.75, level, level, w))
            new_sols, x = _integrate(sim.s, sim.eff, sim.exc, segs[-1:], x, sim.f_max)
            sols += new_sols
        hy, hb = _harmonics(t_an, st[0], f_nl), _harmonics(t_an, dr[0], f_nl)
        thd = float(np.sqrt(np.sum(hy[1:] ** 2)) / hy[0])
        gain = float(hy[0] / hb[0])
        loss = _loss_factor(t_an, st, dr, f_nl, sim.exc)
        g0, l0 = (gain, loss) if g0 is None else (g0, l0)
        levels.append({"amplitude": level, "thd": thd, "gain": gain, "loss_factor": loss, "settle_extra_s": extra})
        # the first level is the reference: like rig/plans.py, the criteria are judged from the second on
        if len(levels) > 1:
            if thd > 0.012:
                reason = "thd"
                break
            if abs(gain / g0 - 1) > 0.45:
                reason = "gain change"
                break
            if l0 > 0 and abs(loss / l0 - 1) > 2.0:
                reason = "loss change"
                break
        if level * 1.5 > top * 1.0001:
            break
        new = level * 1.5
        segs.append(_continue(segs[-1], segs[-1].t1 + max((new - level) / rate, 2 / f_nl), level, new, w))
        new_sols, x = _integrate(sim.s, sim.eff, sim.exc, segs[-1:], x, sim.f_max)
        sols += new_sols
        level = new
    tail = [_continue(segs[-1], segs[-1].t1 + 4.0, level, level, w)]
    tail.append(_continue(tail[-1], tail[-1].t1 + max(level / rate, 2 / f_nl), level, 0.0, w))
    new_sols, x = _integrate(sim.s, sim.eff, sim.exc, tail, x, sim.f_max)
    segs += tail
    sols += new_sols
    sim.record("nonlinear", segs, {"kind": "stepped_levels", "f_hz": f_nl, "levels": levels, "stop": reason},
               solved=(sols, x))
    f_val = 0.7 * f_res
    a = 0.75 * level
    sim.record("validation", ramped_tone(sim.t, f_val, a, 4.0, max(a / rate, 2 / f_val)),
               {"kind": "tone", "f_hz": f_val, "amplitude": a, "hold_s": 4.0})
    # the peaks the nonlinear stage reached, not the top level's: the raising stops where the
    # response distorts or its gain or loss changes, often well below the top (a contact gap placed
    # by the top level's peak is then often not reached: a record without its effect)
    y = sim.stages["nonlinear"]["truth_states"]["y"]
    return float(np.max(y)), float(-np.min(y))


def _chirp_stage(t0, f0, f1, amp, T, ramp, phase):
    # envelope ramps on the chirp's ends; the carrier is one chirp over the whole stage
    c = ("chirp", f0, f1, phase)

    def piece(a, b, e0, e1):
        return Segment(a, b, e0, e1, c, t_ref=t0, T_ref=T)
    return [piece(t0, t0 + ramp, 0.0, amp), piece(t0 + ramp, t0 + T - ramp, amp, amp),
            piece(t0 + T - ramp, t0 + T, amp, 0.0)]


def _scale_to_peak(sim, make, amp0, Y, lo=0.6, hi=1.6):
    """Amplitude for which the stage ``make(t0, amp)`` peaks at ~Y (at most one rescale)."""
    for _ in range(3):
        pk = sim.probe(lambda t0: make(t0, amp0))
        if pk is not None:
            break
        amp0 *= 0.3                    # the trial diverged: lower the drive and try again
    else:
        return amp0
    if lo * Y <= pk <= hi * Y:
        return amp0
    return amp0 * float(np.clip(Y / max(pk, 1e-15), 0.1, 10.0))


def _sweep(sim, s, rng):
    fn, Y = s["f_n"], s["Y"]
    peaks = (Y, Y)
    T_lin, T_nl, T_val = (_durations(fn, 120, 6, 15), _durations(fn, 160, 8, 20), _durations(fn, 120, 6, 15))
    a_nl0, peaks = _calibrate(sim, 0.9 * fn, Y, Y / _gain(s, 0.9 * fn))
    mk_nl = lambda t0, a: _chirp_stage(t0, 0.6 * fn, 1.4 * fn, a, T_nl, 0.5, 0.0)  # noqa: E731
    a_nl = _scale_to_peak(sim, mk_nl, 0.7 * a_nl0, 1.2 * Y)
    a_lin = 0.04 * Y / (1.0 / (2 * s["zeta"]))
    for name, segs, d in (
            ("linear", _chirp_stage(sim.t, 0.3 * fn, 2.0 * fn, a_lin, T_lin, 0.5, 0.0), (0.3, 2.0, a_lin)),
            ("nonlinear", None, (0.6, 1.4, a_nl)),
            ("validation", None, (1.4, 0.6, 0.8 * a_nl))):
        if segs is None:
            T = T_nl if name == "nonlinear" else T_val
            segs = _chirp_stage(sim.t, d[0] * fn, d[1] * fn, d[2], T, 0.5, rng.uniform(0, 2 * math.pi))
        sim.record(name, segs, {"kind": "log_chirp", "f0_hz": d[0] * fn, "f1_hz": d[1] * fn, "amplitude": d[2]})
    return peaks


def _multisine(sim, s, rng):
    fn, Y = s["f_n"], s["Y"]
    Tp = float(np.clip(20.0 / fn, 1.0, 4.0))            # period: lines every 1/Tp Hz
    lines = np.arange(math.ceil(0.4 * fn * Tp), math.floor(2.0 * fn * Tp) + 1) / Tp
    w = 2 * math.pi * lines
    amps = 1.0 / w ** 2 if sim.exc == "base" else np.ones_like(w)
    amps = amps / np.sqrt(np.sum(amps ** 2 / 2))        # unit rms carrier

    def make(t0, a, n_per, ph):
        T = n_per * Tp
        c = ("tones", w, amps, ph)
        r = 0.5 * Tp

        def piece(p, q, e0, e1):
            return Segment(p, q, e0, e1, c, t_ref=t0, T_ref=T)
        return [piece(t0, t0 + r, 0.0, a), piece(t0 + r, t0 + T - r, a, a), piece(t0 + T - r, t0 + T, a, 0.0)]

    n_per = int(np.clip(math.ceil(6.0 / Tp), 3, 6))
    ph_nl = rng.uniform(0, 2 * math.pi, w.size)
    a_lin0 = 0.04 * Y / (1.0 / (2 * s["zeta"]) * float(np.max(amps)) * 3)
    rms_unit_y = float(np.sqrt(np.sum((amps * np.array([_gain(s, f) for f in lines])) ** 2 / 2)))
    a_nl = _scale_to_peak(sim, lambda t0, a: make(t0, a, 2, ph_nl), Y / (3.5 * rms_unit_y), Y)
    peaks = (Y, Y)
    for name, a in (("linear", 0.03 * a_nl), ("nonlinear", a_nl), ("validation", 0.8 * a_nl)):
        ph = ph_nl if name == "nonlinear" else rng.uniform(0, 2 * math.pi, w.size)
        sim.record(name, make(sim.t, a, n_per, ph), {"kind": "multisine", "f_lo_hz": float(lines[0]),
                                                     "f_hi_hz": float(lines[-1]), "lines": int(w.size),
                                                     "period_s": Tp, "periods": n_per, "rms_amplitude": a})
    del a_lin0
    return peaks


_PROTOCOL_FNS = {"paper": _paper, "rig": _rig, "sweep": _sweep, "multisine": _multisine}
# protocols outside the random draws (PROTOCOLS), for a corner's recordings
MORE_PROTOCOLS = ("paper_above",)
_PROTOCOL_FNS["paper_above"] = _paper_above


# --------------------------------------------------------------------------- recordings
def simulate_tone(system: dict, f: float, amplitude: float, hold_s: float, fs: float = 2000.0,
                  excitation: str = "base") -> dict:
    """One ramped tone from rest (ramps of 5 periods): {"t", "x_base", "x_tip"} (or "force",
    "x"), "hold": (start, end) of the full-amplitude part. For checks of the integrator."""
    s = dict(system, _excitation=excitation)
    sim = _Sim(s, {}, excitation, fs, max(2.0 * s["f_n"], f))
    sim.record("tone", ramped_tone(0.0, f, amplitude, hold_s, 5.0 / f), {"kind": "tone", "f_hz": f})
    out = dict(sim.stages["tone"])
    out["hold"] = (5.0 / f, 5.0 / f + hold_s)
    return out


def simulate(system: dict, protocol: str = "paper", fs: float = 2000.0, effect: str = "none",
             strength: float = 1.0, excitation: str = "base", seed: int = 0, mode_drive: float = 0.0,
             mode_ratio: tuple | None = None, also: tuple = ()) -> dict:
    """A noise-free recording (plain dict). ``seed`` draws the protocol's random choices and
    the effect's sign, side and gap. ``mode_drive`` (effect higher_mode): the share d2 of the
    tip's absolute acceleration in the second mode's drive (see the module docstring);
    ``mode_ratio``: the range of the second mode's frequency over f_n (default 2.5-3.5).
    ``also``: further (effect, strength) pairs concealed together with ``effect`` (two effects at
    once), each a physical effect other than the contact (whose gap is calibrated on its own);
    their signs are drawn apart from ``effect``'s, so ``effect`` keeps the values it has alone (a
    contact's gap excepted: it is placed on the peaks the motion reaches with the further effects on)."""
    if protocol not in PROTOCOLS + MORE_PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r} (known: {', '.join(PROTOCOLS + MORE_PROTOCOLS)})")
    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r} (known: {', '.join(EFFECTS)})")
    rng = np.random.default_rng(seed)
    s = dict(system, _excitation=excitation)
    if mode_ratio is not None:
        s["_mode_ratio"] = tuple(mode_ratio)
    baseline = None
    if effect in STRUCTURAL_EFFECTS:
        s, baseline = apply_structural(effect, strength, s, rng)
    eff = {} if effect in STRUCTURAL_EFFECTS else effect_parameters(effect, strength, s, rng)
    if effect == "higher_mode" and mode_drive:
        eff["drive2"] = float(mode_drive)
    others = {}     # the further effects' parameters
    for other, other_strength in also:
        if other not in PHYSICAL_EFFECTS or other in (effect, "contact_stiffness"):
            raise ValueError(f"a second concealed effect must be another physical effect than the contact, "
                             f"got {other!r}")
        others.update(effect_parameters(other, float(other_strength), s, np.random.default_rng([seed, 31])))
    eff.update(others)
    f_max = max(2.0 * s["f_n"], eff.get("w2", 0.0) / (2 * math.pi))   # highest drive / mode frequency
    sim = _Sim(s, {k: v for k, v in eff.items() if k not in ("kc",)}, excitation, fs, f_max)
    if effect == "contact_stiffness":
        # the gap is placed relative to the clean nonlinear-stage peak on its side: calibrate
        # the protocol without the contact first
        # (with the further effects of ``also`` on: they stay in the recording, and the gap is placed
        # on the peaks the motion reaches with them)
        probe_sim = _Sim(s, dict(others), excitation, fs, f_max)
        peaks = _PROTOCOL_FNS[protocol](probe_sim, s, np.random.default_rng(seed))
        eff = {**others, **effect_parameters(effect, strength, s, np.random.default_rng(seed + 7), peaks)}
        sim = _Sim(s, eff, excitation, fs, f_max)
    _PROTOCOL_FNS[protocol](sim, s, rng)
    rec = {"generator": "recon.testing.independent", "excitation": excitation, "fs": float(fs),
           "protocol": protocol, "stages": sim.stages, "system": {k: v for k, v in s.items() if not k.startswith("_")},
           "truth": truth_per_unit_mass(s, excitation), "effect": effect, "strength": float(strength),
           "effect_parameters": eff, "snr_db": None, "seed": int(seed),
           **({"also": [[str(e), float(x)] for e, x in also]} if also else {})}
    if baseline is not None:
        rec["baseline"] = truth_per_unit_mass(baseline, excitation)
    return rec


def add_noise(rec: dict, snr_db: float | None, seed: int, quantisation: float | None = None,
              quantity: str = "displacement", flicker_share: float = 0.5, noise_std: float | None = None,
              stage_snr_db: dict | None = None) -> dict:
    """A copy with white sensor noise at ``snr_db`` of each channel's rms (per stage) and an
    optional quantisation step ``quantisation`` (as a fraction of the noise std).
    ``noise_std`` (in the channel's unit) in place of ``snr_db``: one noise level for every channel
    and stage, as a sensor's own resolution (sub-micron on a laser displacement sensor).
    ``stage_snr_db``: {stage: SNR [dB]} in place of ``snr_db`` for the stages it names (a stage recorded
    noisier than the others, as a linear stage whose small motion sits near the sensor's floor); the
    draws are taken in the same order, so the stages it does not name get the noise they get without it.

    ``quantity``: how the response (x_tip, or x under force excitation) is recorded: "displacement",
    "velocity" (a laser vibrometer: v_tip, v) or "acceleration" (a_tip, a; white noise), at ``snr_db``
    of its own rms. A velocity channel's
    noise has a low-frequency part, as a vibrometer's has (demodulator and speckle noise rising as 1/f
    below a few Hz): ``flicker_share`` of the noise power is 1/f noise (a power spectrum falling as 1/f
    from the record's lowest bin to Nyquist, no DC), the rest white; the total stays at ``snr_db``.
    Displacement records are unchanged (the same draws as before the option existed)."""
    if quantity not in QUANTITIES:
        raise ValueError(f"unknown quantity {quantity!r} (known: {', '.join(QUANTITIES)})")
    rng = np.random.default_rng(seed)
    flicker_rng = np.random.default_rng([seed, 1])
    out = dict(rec, stages={}, snr_db=snr_db, noise_seed=int(seed), quantisation=quantisation, quantity=quantity,
               **({"noise_std": float(noise_std)} if noise_std is not None else {}),
               **({"stage_snr_db": {k: float(v) for k, v in stage_snr_db.items()}} if stage_snr_db else {}))
    response = "x_tip" if rec["excitation"] == "base" else "x"
    velocity = "v" + response[1:]
    recorded = {"displacement": response, "velocity": velocity, "acceleration": "a" + response[1:]}[quantity]
    for name, st in rec["stages"].items():
        new = {k: v for k, v in st.items() if k not in (response, velocity, "a" + response[1:]) or k == recorded}
        chans = ("x_base", "x_tip") if rec["excitation"] == "base" else ("force", "x")
        chans = tuple(recorded if c == response else c for c in chans)
        snr = stage_snr_db[name] if stage_snr_db and name in stage_snr_db else snr_db
        for ch in chans:
            x = st[ch]
            if snr is not None or noise_std is not None:
                sd = (float(noise_std) if noise_std is not None
                      else float(np.sqrt(np.mean(x ** 2))) / 10 ** (snr / 20))
                if ch == velocity:
                    x = (x + rng.normal(0.0, sd * math.sqrt(1.0 - flicker_share), x.size)
                         + flicker_noise(flicker_rng, x.size, sd * math.sqrt(flicker_share)))
                else:
                    x = x + rng.normal(0.0, sd, x.size)
                if quantisation:
                    q = quantisation * sd
                    x = q * np.round(x / q)
            new[ch] = x
        out["stages"][name] = new
    return out


def flicker_noise(rng, n: int, rms: float) -> np.ndarray:
    """1/f (pink) noise of ``rms``: white Gaussian spectrum shaped by 1/sqrt(f), no DC."""
    spec = rng.normal(size=n // 2 + 1) + 1j * rng.normal(size=n // 2 + 1)
    k = np.arange(n // 2 + 1, dtype=float)
    spec[0] = 0.0
    spec[1:] /= np.sqrt(k[1:])
    x = np.fft.irfft(spec, n)
    return x * (rms / max(float(np.std(x)), 1e-300))


def random_recording(seed: int, snr_db: float | None = None, protocol: str | None = None,
                     effect: str | None = None, strength: float | None = None, fs: float | None = None,
                     hysteresis: bool | None = True, effects=EFFECTS, noise_seed: int | None = None) -> dict:
    """One random recording: system, protocol, fs (log-uniform 1-10 kHz), SNR (uniform 40-80 dB),
    effect and strength (0.3-1.5) drawn from ``seed`` unless given."""
    rng = np.random.default_rng([seed, 20260])
    system = random_system(rng, hysteresis=hysteresis)
    protocol = protocol or str(rng.choice(PROTOCOLS))
    fs = fs or float(np.round(math.exp(rng.uniform(math.log(1000.0), math.log(10000.0)))))
    effect = effect or str(rng.choice(list(effects)))
    strength = float(rng.uniform(0.3, 1.5)) if strength is None else strength
    snr = float(rng.uniform(40.0, 80.0)) if snr_db is None else snr_db
    quant = float(rng.uniform(0.2, 1.0)) if rng.random() < 0.5 else None
    rec = simulate(system, protocol, fs, effect, strength, seed=seed)
    rec["system_seed"] = int(seed)
    return add_noise(rec, snr, seed if noise_seed is None else noise_seed, quant)

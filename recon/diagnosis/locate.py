"""Where the model and the recording disagree: time, frequency, state plane, channel.

Two residuals per stage:
- the simulation residual r = y_rec - y_sim (output error);
- the equation residual e = g u - y'' - c y' - k y - fn(y, y') - z  (the part of the
  restoring force the model leaves unexplained), with y', y'' from Savitzky-Golay
  derivatives of the recording and z integrated from the measured y'.
Each finding is {kind, stage, region, size, ...}; ``size`` is relative (rms of the
residual part over rms of the recorded y, or over rms of the restoring force).
The Billings-Voon correlation tests (95 % bands +-1.96/sqrt(N)) run on the
equation residual decimated to roughly independent samples.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from recon.diagnosis.settings import DEFAULTS, DiagnosisSettings
from recon.simulation.rk4 import kernel_input
from recon.signals import stage_signals
from recon.welch import welch
from shakerlab.run_data import BASE

UNITS = {
    "time": "rms of the simulation residual / rms(y) (trend: change of that over the stage)",
    "frequency": "rms of the simulation residual in the band / rms(y)",
    "channel": "rms of the residual part explained by the channel / rms(y)",
    "state": "mean unexplained restoring force / rms restoring force",
    "correlation": "largest |normalised correlation| outside the 95 % band (the band is band_95)",
    "diverged": "the simulation diverged",
}
QUADRANTS = {1: "AB (y>0, y'>0)", 2: "BC (y>0, y'<0)", 3: "CD (y<0, y'<0)", 4: "DA (y<0, y'>0)"}


def _quadrant(y, dy):
    q = np.where(y >= 0, np.where(dy >= 0, 1, 2), np.where(dy < 0, 3, 4))
    return q


def z_from_velocity(model, dy, dt):
    """Bouc-Wen z driven by the measured velocity (RK2 on the samples).

    A step where the law is stiff (decay rate lam = gamma |y'| + delta y' sign(z) with lam dt > 1,
    where RK2 is inaccurate and beyond 2 unstable) is taken exactly for the step's mean velocity:
    z' = alpha y' - lam z is then linear. A reconstructed baseline with a tiny alpha and a large
    gamma can reach lam dt >> 1; RK2 then grows z without bound, and that sets the scale of every
    candidate's start and interval."""
    a, g, d = model.alpha_m, model.gamma, model.delta
    if a == 0.0:
        return np.zeros_like(dy)
    return _z_steps(np.ascontiguousarray(dy, dtype=float), float(dt), float(a), float(g), float(d))


@njit(cache=True)
def _z_steps(dy, dt, a, g, d):
    """The loop of :func:`z_from_velocity` (numba: a Python loop over the samples can take a tenth
    of a hysteretic record's diagnosis)."""
    z = np.zeros_like(dy)
    zi = 0.0
    for i in range(dy.size - 1):
        v0, v1 = dy[i], dy[i + 1]
        vm = 0.5 * (v0 + v1)
        lam = g * abs(vm) + d * vm * (1.0 if zi >= 0.0 else -1.0)
        if lam * dt > 1.0:
            zeq = a * vm / lam
            zi = zeq + (zi - zeq) * math.exp(-lam * dt)
        else:
            k1 = a * v0 - g * abs(v0) * zi - d * v0 * abs(zi)
            zp = zi + dt * k1
            k2 = a * v1 - g * abs(v1) * zp - d * v1 * abs(zp)
            zi = zi + 0.5 * dt * (k1 + k2)
        z[i + 1] = zi
    return z


def stage_derivatives(run, data) -> dict:
    """Per stage: (t, y, y', y'', u) from the stage signals (recon.signals: Savitzky-Golay
    derivatives of the measured quantity), edges trimmed; u is the model input of the fit data."""
    out = {}
    for d in data:
        st = run.stage(d.name)
        sig = stage_signals(st, deriv=2, for_regression=False)
        h = (st.t.size - sig.t.size) // 2
        sl = slice(h, st.t.size - h)
        y, dy, ddy = sig.y
        out[d.name] = (d.t[sl], y, dy, ddy, d.u[sl], float(np.median(np.diff(st.t))))
    return out


def model_force(am, t, y, dy, dt):
    """Restoring force per unit mass of the (augmented) model along the measured motion."""
    m = am.baseline
    z = z_from_velocity(m, dy, dt)
    f = m.c_m * dy + m.k_m * (1.0 + am.get("drift") * t) * y + m.fn(y, dy) + z
    if am.get("mu"):
        f = f + am.get("mu") * np.tanh(dy / (am.get("v0") or 1e-4))
    if am.get("c2"):
        f = f + am.get("c2") * dy * np.abs(dy)
    if am.get("kc"):
        s = 1.0 if am.get("side") >= 0 else -1.0
        f = f + s * am.get("kc") * np.maximum(s * y - am.get("gap"), 0.0)
    return f


def equation_residual(am, derivs):
    """(y, y', e, u, restoring-force rms) for one stage's derivatives."""
    t, y, dy, ddy, u, dt = derivs
    f = model_force(am, t, y, dy, dt)
    e = am.baseline.input_gain * u - ddy - f
    r = f + ddy
    if not np.all(np.isfinite(r)):
        # the model's force overflows along the recorded path (a Bouc-Wen law too stiff for the
        # measured y'): the scale is taken from the measurements, g u - y'' (the force per unit mass)
        r = am.baseline.input_gain * u - ddy
    return y, dy, e, u, float(np.sqrt(np.mean(r ** 2))) or 1.0


def _peaks(freqs, power, floor, n=5, ratio=10.0):
    idx = np.flatnonzero(power > ratio * floor)
    out = []
    for i in idx:
        lo, hi = max(i - 1, 0), min(i + 2, power.size)
        if power[i] == power[lo:hi].max():
            out.append((float(freqs[i]), float(power[i] / floor)))
    out.sort(key=lambda x: -x[1])
    return out[:n]


def billings_voon(e, u, max_lag=20):
    """Billings-Voon correlation tests; returns {test: fraction of lags outside the 95 % band, band}.
    A correlation at lag k is a mean over n - k products: the lags go up to a quarter of the samples
    (at most ``max_lag``); a residual too short for two lags gets no test (only ``band_95`` and ``n``)."""
    e = np.asarray(e, float)
    u = np.asarray(u, float)
    n = e.size
    max_lag = min(int(max_lag), n // 4)
    if max_lag < 2:
        return {"band_95": float("nan"), "n": n}
    e = (e - e.mean()) / (e.std() or 1.0)
    u = (u - u.mean()) / (u.std() or 1.0)
    band = 1.96 / math.sqrt(n)

    def xc(a, b, lags):
        a = (a - a.mean()) / (a.std() or 1.0)
        b = (b - b.mean()) / (b.std() or 1.0)
        return np.array([np.mean(a[: n - k] * b[k:]) if k >= 0 else np.mean(a[-k:] * b[: n + k]) for k in lags])

    pos = range(1, max_lag + 1)
    allk = range(0, max_lag + 1)
    u2 = u ** 2 - np.mean(u ** 2)
    tests = {
        "phi_ee": xc(e, e, pos),
        "phi_ue": xc(u, e, allk),
        "phi_e_eu": xc(e, e[:] * np.r_[0.0, u[:-1]], allk),
        "phi_u2_e": xc(u2, e, allk),
        "phi_u2_e2": xc(u2, e ** 2 - np.mean(e ** 2), allk),
    }
    return {k: {"outside_95": float(np.mean(np.abs(v) > band)), "max_abs": float(np.max(np.abs(v)))}
            for k, v in tests.items()} | {"band_95": band, "n": n}


def bilinear_biquad(b, a, dt):
    """The digital filter (num, den) that the bilinear (Tustin) transform s = (2/dt)(z-1)/(z+1) makes
    of the analog H(s) = (b0 s^2 + b1 s + b2) / (s^2 + a1 s + a2), ``b`` = (b0, b1, b2),
    ``a`` = (a1, a2); den[0] = 1. What scipy.signal.cont2discrete(method="bilinear") gives, to
    rounding, written out so that the diagnosis does not import scipy.signal (about 0.4 CPU-s)."""
    K = 2.0 / dt
    b0, b1, b2 = (float(v) for v in b)
    a1, a2 = (float(v) for v in a)
    K2 = K * K
    d0 = K2 + a1 * K + a2
    num = np.array([b0 * K2 + b1 * K + b2, 2.0 * (b2 - b0 * K2), b0 * K2 - b1 * K + b2]) / d0
    den = np.array([1.0, 2.0 * (a2 - K2) / d0, (K2 - a1 * K + a2) / d0])
    return num, den


@njit(cache=True)
def _biquad(num, den, x):
    """y of den[0..2] * y = num[0..2] * x (den[0] = 1), from rest: scipy.signal.lfilter's transposed
    direct form II for one second-order section."""
    y = np.empty_like(x)
    s1 = 0.0
    s2 = 0.0
    for i in range(x.size):
        xi = x[i]
        yi = num[0] * xi + s1
        s1 = num[1] * xi - den[1] * yi + s2
        s2 = num[2] * xi - den[2] * yi
        y[i] = yi
    return y


def mode_response(u, dt, w, zeta, g=1.0):
    """q of q'' + 2 zeta w q' + w^2 q = g u (bilinear discretisation, from rest)."""
    num, den = bilinear_biquad((0.0, 0.0, g), (2 * zeta * w, w * w), dt)
    return _biquad(num, den, kernel_input(u))


def mode_response_to_motion(y, dt, w, zeta):
    """q of q'' + 2 zeta w q' + w^2 q = -y'' from the displacement y itself (the transfer
    -s^2 / (s^2 + 2 zeta w s + w^2), bilinear, from rest): y is not differentiated."""
    num, den = bilinear_biquad((-1.0, 0.0, 0.0), (2 * zeta * w, w * w), dt)
    return _biquad(num, den, kernel_input(y))


def scan_modes(data, residuals, gain, f_lo, f_hi, n=40, zeta=0.02, motions=None, base=True):
    """Frequencies at which an extra mode's response best explains the output residual
    (linear regression over the fitting samples): ``(input_scan, point_scan)``, each a list of
    (f, explained share, phi), best first.

    ``input_scan`` is for a mode driven by the input. ``point_scan`` (None without ``motions``,
    the model's output per stage: y, or y' for a velocity record, whose regressors are then q') is for a mode driven by the measured point's absolute
    acceleration (augmented.py, drive2 = 1): under base excitation by g u - y'', under force
    excitation by -y''. Both come from one pass: the input-driven response is computed once per
    frequency and stage."""
    scans = ([], [] if motions is not None else None)
    for f in np.geomspace(f_lo, f_hi, n):
        w = 2 * math.pi * f
        acc = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]   # num, den, tot per scan
        for i, (d, r) in enumerate(zip(data, residuals)):
            if not d.fit.any() or not np.all(np.isfinite(r)):
                continue
            q_in = mode_response(d.u, d.dt, w, zeta, gain)
            if d.order:          # a velocity record reads the mode's q' (augmented.py)
                q_in = np.gradient(q_in, d.dt)
            rr = r[d.fit]
            regressors = [(0, q_in)]
            if motions is not None and np.all(np.isfinite(motions[i])):
                q = mode_response_to_motion(motions[i], d.dt, w, zeta)
                regressors.append((1, q + q_in if base else q))
            for k, q in regressors:
                q = q[d.fit]
                acc[k][0] += float(q @ rr)
                acc[k][1] += float(q @ q)
                acc[k][2] += float(rr @ rr)
        for out, (num, den, tot) in zip(scans, acc):
            if out is not None and den > 0 and tot > 0:
                out.append((float(f), num * num / den / tot, num / den))
    for out in scans:
        if out is not None:
            out.sort(key=lambda x: -x[1])
    return scans


def locate(am, run, data, sims, derivs=None, settings: DiagnosisSettings = DEFAULTS) -> tuple[list[dict], dict]:
    """Findings for the model ``am`` (simulations ``sims`` per stage) and a context for the catalog
    (``settings``: how many pieces a stage is cut into in time, where an input's band ends)."""
    findings = []
    bv_all = {}
    derivs = derivs or stage_derivatives(run, data)
    y_fit = np.concatenate([d.displacement[d.fit] for d in data if d.fit.any()])
    m = am.baseline
    f_res = math.sqrt(max(m.K_m, 1.0)) / (2 * math.pi)
    mode_freqs = []
    acc_parts, v_parts = [], []
    for d, ys in zip(data, sims):
        st = run.stage(d.name)
        r = d.y - ys
        if not np.all(np.isfinite(r)):
            findings.append({"kind": "diverged", "stage": d.name, "region": {}, "size": float("inf")})
            continue
        noise_rel = d.noise / d.rms
        # ---- time: segments and trend
        seg = np.array_split(r, int(settings.time_segments))
        tseg = np.array_split(d.t, int(settings.time_segments))
        rms = np.array([np.sqrt(np.mean(s ** 2)) for s in seg]) / d.rms
        tc = np.array([s.mean() for s in tseg])
        slope = np.polyfit(tc - tc.mean(), rms, 1)[0] * (tc[-1] - tc[0]) if rms.size > 2 else 0.0
        worst = int(np.argmax(rms))
        if rms[worst] > 3 * noise_rel:
            findings.append({"kind": "time_segment", "stage": d.name,
                             "region": {"t_from": float(tseg[worst][0]), "t_to": float(tseg[worst][-1])},
                             "size": float(rms[worst]), "median_segment": float(np.median(rms))})
        if abs(slope) > 0.5 * np.median(rms) and np.max(rms) > 3 * noise_rel:
            findings.append({"kind": "time_trend", "stage": d.name,
                             "region": {"t_from": float(d.t[0]), "t_to": float(d.t[-1])},
                             "size": float(slope), "meaning": "residual rms grows (>0) or shrinks over the stage"})
        # ---- frequency: residual spectrum, harmonics, resonance
        nper = min(1024, r.size)
        fq, pr = welch(r, fs=st.fs, nperseg=nper)
        _, py = welch(d.y, fs=st.fs, nperseg=nper)
        floor = max(float(np.median(pr[pr.size // 2:])), (d.noise ** 2) * 2 / st.fs)
        uin = st.channels["x_base"] if st.excitation == BASE else st.channels["force"]
        _, pu = welch(uin, fs=st.fs, nperseg=nper)
        ufloor = float(np.median(pu[pu.size // 2:])) or 1e-300
        exc_lines = [f for f, _ in _peaks(fq, pu, ufloor, n=8, ratio=100.0)]
        for f, snr in _peaks(fq, pr, floor):
            at_input = any(abs(f - fe) <= 2 * st.fs / nper for fe in exc_lines)
            harm = [k for fe in exc_lines[:2] for k in (2, 3, 4, 5) if abs(f - k * fe) <= 2 * st.fs / nper]
            kind = "harmonic" if harm and not at_input else ("band_at_input" if at_input else "resonance")
            size = float(np.sqrt(np.sum(pr[max(0, np.searchsorted(fq, f) - 2): np.searchsorted(fq, f) + 3])
                                 * (fq[1] - fq[0])) / d.rms)
            findings.append({"kind": f"frequency_{kind}", "stage": d.name, "region": {"frequency_hz": f},
                             "size": size, "above_floor": snr, **({"harmonic_of": harm} if harm else {})})
            if kind == "resonance" and f > 1.3 * f_res:
                mode_freqs.append(f)
        # ---- per channel (base excitation): feedthrough of a channel and a time skew
        if st.excitation == BASE:
            xb = d.x_in          # the base channel in the recorded quantity
            dyr = np.gradient(d.y, d.dt)
            A = np.column_stack([xb, dyr * d.dt])
            coef, *_ = np.linalg.lstsq(A, r, rcond=None)
            for j, (name, meaning) in enumerate((("x_base", "scale error (feedthrough of a channel)"),
                                                 ("x_tip'", "time skew between the channels"))):
                part = float(np.sqrt(np.mean((A[:, j] * coef[j]) ** 2)) / d.rms)
                if part > 2 * noise_rel:
                    findings.append({"kind": "channel", "stage": d.name, "region": {"channel": name},
                                     "size": part, "coefficient": float(coef[j]), "meaning": meaning})
        # ---- state plane: equation residual by cluster, near y' = 0, beyond a displacement
        y, dy, e, u, frms = equation_residual(am, derivs[d.name])
        acc_parts.append(frms)
        v_parts.append(float(np.sqrt(np.mean(dy ** 2))))
        q = _quadrant(y, dy)
        for qi, qname in QUADRANTS.items():
            sel = q == qi
            if sel.sum() > 20:
                mean = float(e[sel].mean())
                se = float(e[sel].std() / math.sqrt(max(sel.sum() / 10.0, 1.0)))
                if abs(mean) > 3 * se and abs(mean) > 0.005 * frms:
                    findings.append({"kind": "state_cluster", "stage": d.name, "region": {"cluster": qname},
                                     "size": abs(mean) / frms, "mean_residual": mean})
        vmax = np.max(np.abs(dy))
        near = np.abs(dy) < 0.15 * vmax
        if near.sum() > 20:
            jump = float(e[near & (dy > 0)].mean() - e[near & (dy < 0)].mean()) if (near & (dy > 0)).any() and (near & (dy < 0)).any() else 0.0
            far = float(e[~near & (dy > 0)].mean() - e[~near & (dy < 0)].mean()) if (~near & (dy > 0)).any() and (~near & (dy < 0)).any() else 0.0
            if abs(jump) > 0.01 * frms:
                findings.append({"kind": "state_near_zero_velocity", "stage": d.name,
                                 "region": {"abs_dy_below": float(0.15 * vmax)}, "size": abs(jump) / frms,
                                 "jump_across_dy0": jump, "jump_at_high_speed": far})
        for side, nm in ((1, "y_beyond_pos"), (-1, "y_beyond_neg")):
            ymax = np.max(side * y)
            if ymax <= 0:
                continue
            beyond = side * y > 0.7 * ymax
            mid = np.abs(y) < 0.3 * np.max(np.abs(y))
            if beyond.sum() > 20 and mid.sum() > 20:
                diff = float(e[beyond].mean() - e[mid].mean())
                se = float(e[beyond].std() / math.sqrt(max(beyond.sum() / 10.0, 1.0)))
                if abs(diff) > 3 * se and abs(diff) > 0.01 * frms:
                    findings.append({"kind": "state_beyond_displacement", "stage": d.name,
                                     "region": {"y_side": side, "beyond_m": float(0.7 * ymax * side)},
                                     "size": abs(diff) / frms, "mean_residual": diff})
        # ---- Billings-Voon on decimated equation residual
        step = max(1, int(round(st.fs / (8 * max(f_res, 1.0)))))
        bv = billings_voon(e[::step], u[::step])
        bv_all[d.name] = bv
        bad = [k for k, v in bv.items() if isinstance(v, dict) and v["outside_95"] > 0.1]
        if bad:
            findings.append({"kind": "correlation_tests", "stage": d.name, "region": {"tests_failed": bad},
                             "size": float(max(bv[k]["max_abs"] for k in bad))})
    y_all = np.concatenate([d.displacement for d in data])
    ctx = {
        "y_max_pos": float(max(np.max(y_fit), 1e-12)), "y_max_neg": float(max(-np.min(y_fit), 1e-12)),
        "y_rms": float(np.sqrt(np.mean(y_all ** 2))),
        "v_rms": float(np.mean(v_parts)) if v_parts else 1e-3,
        "v_rms_min": float(np.min(v_parts)) if v_parts else 1e-3,
        "acc_rms": float(np.mean(acc_parts)) if acc_parts else 1.0,
        "u_rms": float(np.sqrt(np.mean(np.concatenate([d.u for d in data]) ** 2))) or 1.0,
        "dt": data[0].dt, "t_end": float(max(d.t[-1] for d in data)),
        "f_res": f_res, "billings_voon": bv_all,
    }
    nyq = 0.5 / data[0].dt
    defaults = [f for f in (2.5 * f_res, 4.0 * f_res, 6.0 * f_res) if f < 0.4 * nyq]
    seen = []
    for f in mode_freqs + defaults:
        if all(abs(f - s) > 0.1 * s for s in seen):
            seen.append(f)
    ctx["mode_freqs"] = seen[:2]
    # scan for an extra mode explaining the output residual (regression on q(w), zeta = 0.02)
    res = [d.y - ys for d, ys in zip(data, sims)]
    scan, scan_p = scan_modes(data, res, m.input_gain, 1.3 * f_res, 0.4 * nyq, motions=sims,
                              base=run.excitation == BASE)
    picked = []
    for f, share, phi in scan:
        if all(abs(f - p) > 0.08 * p for p, _ in picked):
            picked.append((f, phi))
        if len(picked) == 2:
            break
    # a mode above the band the input excites answers it quasi-statically (q = g u / w^2: a feedthrough
    # of the input, no peak in the residual) and the scan, which looks for its resonance, does not
    # find it, and fits from the scan's peaks near the band's top stay there: one start twice above
    # the top of the fitting stages' input band (the frequency below which settings.band_power of
    # the input's power lies)
    tops = []
    for d in data:
        if d.fit.any() and d.u.size > 16 and np.all(np.isfinite(d.u)):
            fq, pu = welch(d.u, fs=1.0 / d.dt, nperseg=min(4096, d.u.size))
            if np.sum(pu) > 0:
                top = np.searchsorted(np.cumsum(pu) / np.sum(pu), settings.band_power)
                tops.append(float(fq[min(top, fq.size - 1)]))
    if tops:
        ctx["mode_start_above_band"] = float(min(max(2.0 * max(tops), 1.3 * f_res), 0.4 * nyq))
    ctx["mode_scan"] = [{"frequency_hz": f, "explained_share": sh} for f, sh, _ in scan[:3]]
    ctx["mode_starts"] = picked + [(f, 0.0) for f in ctx["mode_freqs"]]
    # scan_p: the same scan for a resonance riding on the measured point (driven by its absolute
    # acceleration, as a mount resonance under the specimen is, which the input-driven scan does
    # not find)
    ctx["mode_scan_point"] = [{"frequency_hz": f, "explained_share": sh} for f, sh, _ in scan_p[:3]]
    ctx["mode_starts_point"] = [(f, phi) for f, _, phi in scan_p[:1]]
    for f in findings:
        f.setdefault("size_unit", UNITS.get(f["kind"].split("_")[0], "relative"))
    # located sizes first (largest first); the correlation tests (a correlation, another unit) last
    findings.sort(key=lambda f: (f["kind"] == "correlation_tests",
                                 -(f["size"] if math.isfinite(f["size"]) else 1e9)))
    return findings, ctx

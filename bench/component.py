"""Constitutive mode against a plain yardstick on the same held-out component tests (issue 16).

Run:  python bench/component.py [--seeds 3] [--snr 40 60 80]

Data: recon.testing.component_tests (the independent truth): per case a fitted record and a
held-out record of the same kind of displacement history, white noise on every channel at
the given SNR. Cases: Bouc-Wen under a random displacement, Bouc-Wen with fn terms under
sine tests, rate-independent friction with a cubic term under a quasi-static loop, an MR
damper under a random displacement with a switched coil command (coil lag eta, force
offset).

Printed per case and SNR (median over seeds; worst in brackets): the largest parameter error
of the identified law, the held-out force NRMSE, the fit time; and the yardstick's held-out
NRMSE: a linear-plus-Coulomb law F = c x' + k x + Fc tanh(x'/v0) + f0 fitted by least
squares on the same fitted record (v0 chosen on a grid, x' a Savitzky-Golay derivative), with the command as
F += (c1 x' + Fc1 tanh(x'/v0)) v for the MR damper (the command without its lag).
The times exclude numba's first compilation (one warm-up fit first). Last column: how many of
the 95 % intervals (recon.constitutive.output_error.intervals) hold the true value, over the
seeds and parameters.
"""
from __future__ import annotations

import argparse
import os
import time

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
from scipy.signal import savgol_filter  # noqa: E402

from recon.constitutive.estimator import reconstruct_constitutive  # noqa: E402
from recon.constitutive.output_error import intervals  # noqa: E402
from recon.constitutive.signals import component_signals  # noqa: E402
from recon.testing import component_tests as ct  # noqa: E402
from recon.validation import nrmse  # noqa: E402
from shakerlab.modes import COMMAND_CHANNEL, CONSTITUTIVE  # noqa: E402
from shakerlab.run_data import Run, Stage  # noqa: E402

CASES = {
    "bouc-wen, random x": (lambda: ct.bouc_wen_law(), "random"),
    "bouc-wen + fn, sines": (lambda: ct.bouc_wen_law(True), "sines"),
    "friction + y^3, quasi-static": (ct.friction_law, "quasi_static"),
    "MR damper, switched cmd": (ct.mr_damper_law, "random"),
}


def stage(name, rec):
    ch = {"x": rec["x"], "force": rec["force"]}
    if "cmd" in rec:
        ch[COMMAND_CHANNEL] = rec["cmd"]
    return Stage(name, rec["t"], ch, excitation="force")


def yardstick(fit, val):
    """Held-out NRMSE of the linear-plus-Coulomb law (velocity: a cubic Savitzky-Golay derivative
    of x over 1/20 s, so that the yardstick is not judged on its noise)."""
    def cols(rec, v0):
        dt = rec["t"][1] - rec["t"][0]
        v = savgol_filter(rec["x"], 2 * int(0.025 / dt) + 1, 3, deriv=1, delta=dt)
        c = [v, rec["x"], np.tanh(v / v0), np.ones_like(v)]
        if "cmd" in rec:
            c += [rec["cmd"] * v, rec["cmd"] * np.tanh(v / v0)]
        return np.column_stack(c)

    vs = np.std(fit["v"]) if "v" in fit else np.std(np.gradient(fit["x"], fit["t"]))
    best = None
    for v0 in vs * np.geomspace(1e-3, 1.0, 13):
        A = cols(fit, v0)
        coef, *_ = np.linalg.lstsq(A, fit["force"], rcond=None)
        e = nrmse(A @ coef, fit["force"])
        if best is None or e < best[0]:
            best = (e, v0, coef)
    _, v0, coef = best
    return nrmse(cols(val, v0) @ coef, val["force"])


def flat(truth):
    out = {k: v for k, v in truth.items() if k != "fn"}
    out.update({f"fn:{k}": v for k, v in truth["fn"].items()})
    return out


def max_error(law, truth, fit):
    p = law.parameters()
    errs = {}
    for k, v in truth.items():
        if k == "fn":
            for t, b in v.items():
                errs[f"fn:{t}"] = abs(p["fn"].get(t, 0.0) - b) / abs(b)
        elif v:
            errs[k] = abs(p.get(k, 0.0) - v) / abs(v)
        elif k == "c":   # no viscous force in the truth: the identified one against the force
            errs[k] = abs(p["c"]) * np.std(fit["v"]) / np.std(fit["force"])
    extra = sorted(set(p["fn"]) - set(truth["fn"]))
    worst = max(errs, key=errs.get)
    return errs[worst], worst, extra


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--snr", type=float, nargs="+", default=[40.0, 60.0, 80.0])
    args = ap.parse_args()
    warm = ct.component_test(ct.bouc_wen_law(), "random", 60.0, 99)
    reconstruct_constitutive(Run({"nonlinear": stage("nonlinear", warm["fit"])}, attrs={"mode": CONSTITUTIVE}))
    print(f"{'case':30s} {'SNR':>4s} | {'max param err %':>22s} {'worst':>8s} | {'held-out NRMSE %':>17s} "
          f"{'time s':>11s} | {'yardstick NRMSE %':>17s} | 95 % intervals holding the truth")
    for name, (make, kind) in CASES.items():
        for snr in args.snr:
            rows = []
            for seed in range(args.seeds):
                case = ct.component_test(make(), kind, snr, seed)
                run = Run({"nonlinear": stage("nonlinear", case["fit"]),
                           "validation": stage("validation", case["validation"])}, attrs={"mode": CONSTITUTIVE})
                t0 = time.perf_counter()
                r = reconstruct_constitutive(run)
                dt = time.perf_counter() - t0
                err, worst, extra = max_error(r.law, case["truth"], case["fit"])
                iv = intervals(r.law, [component_signals(run.stage("nonlinear"))],
                               fit_rate=r.settings.fit_rate)["parameters"]
                cover = [iv[k]["low"] <= v <= iv[k]["high"] for k, v in flat(case["truth"]).items() if v and k in iv]
                rows.append((err, worst, r.validation["nrmse"], dt, yardstick(case["fit"], case["validation"]),
                             extra, cover))
            e = np.array([r[0] for r in rows]) * 100
            v = np.array([r[2] for r in rows]) * 100
            tt = np.array([r[3] for r in rows])
            y = np.array([r[4] for r in rows]) * 100
            worst = rows[int(np.argmax(e))][1]
            extra = sorted({t for r in rows for t in r[5]})
            cov = [c for r in rows for c in r[6]]
            print(f"{name:30s} {snr:4.0f} | {np.median(e):10.3f} [{e.max():9.3f}] {worst:>8s} | "
                  f"{np.median(v):7.3f} [{v.max():7.3f}] {np.median(tt):5.2f} [{tt.max():4.2f}] | "
                  f"{np.median(y):7.2f} [{y.max():7.2f}] | {sum(cov):3d}/{len(cov):3d}"
                  + (f"  extra terms: {', '.join(extra)}" if extra else ""))


if __name__ == "__main__":
    main()

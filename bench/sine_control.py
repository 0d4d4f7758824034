"""Closed-loop sine control against open loop on the simulated rig (issue 19).

    python bench/sine_control.py              # control table (about 1-2 min)
    python bench/sine_control.py --recon 0 1 2  # + reconstruction from the shipped (volts) and the
                                              #   base-target protocol on these noise seeds (~1.5 min each)

Cases (lockstep simulated rig, seed 0, the shipped rig limits: 1 Vpp/s ramps, 6 Vpp):

- steps of the base target, off resonance (8 Hz) and at the specimen's resonance (14.2 Hz);
- a stepped sweep through the resonance at a constant base target of 0.05 mm;
- the nonlinear stage's levels at 0.88 x the resonance (12.5 Hz), 0.08 mm x 1.5^k.

Open loop: the generator voltage that gives the target according to a small-amplitude
calibration at 8 Hz (what an operator who knows the shaker's sensitivity would set); its error
is the steady base amplitude over the target. Closed loop: rig.sine_control through the runner.
Settling: drive cycles from the step (or frequency change) until every later analysis window
(2 periods, at least 0.1 s) is within +-0.5 dB of the target (closed loop) or of its own final
value (open loop). Steady error: the largest |error| over the last 2 s of each hold.
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rig.messages import Acquire, BeginStage, ControlSine, EndStage, Ramp, Rest, SetFrequency  # noqa: E402
from rig.protocol import load_protocol  # noqa: E402
from rig.session import acquire, simulated_rig  # noqa: E402
from rig.sine_control import ControlSettings, SineController, fundamental  # noqa: E402

FS = 10000.0
HOLD_S = 4.0
STEADY_S = 2.0
TOL = 0.5


def windows(x, f, fs=FS):
    """Fundamental amplitude over consecutive analysis windows (the controller's window length)."""
    n = SineController(1.0, f, max_vpp=1.0, ramp_rate_vpp_per_s=1.0, settings=ControlSettings()).window_n(fs)
    ends = np.arange(n, x.size + 1, n)
    return ends, np.array([fundamental(x[e - n:e], fs, f) for e in ends])


def settle_cycles(ends, amps, ref, f):
    bad = np.flatnonzero(np.abs(20 * np.log10(amps / ref)) > TOL)
    if bad.size and bad[-1] == amps.size - 1:
        return math.inf
    k = bad[-1] + 1 if bad.size else 0
    return ends[k] / FS * f


def open_loop(f, vpp, target, seconds):
    """Plan piece: open loop at vpp from the present output; returns (settle cycles, steady error dB)."""
    yield SetFrequency(f)
    ramp_s = abs(vpp - (yield Acquire(0.0001)).amplitude_vpp) / 1.0   # shipped ramp rate 1 Vpp/s
    yield Ramp(vpp)
    w = yield Acquire(seconds)
    ends, amps = windows(w.x_base, f)
    final = amps[ends >= ends[-1] - STEADY_S * FS]
    err = 20 * np.log10(final / target)
    # the ramp's time counts in the settling, as it does for the closed loop
    return ramp_s * f + settle_cycles(ends, amps, float(np.mean(final)), f), float(err[np.argmax(np.abs(err))]), vpp


def closed_loop(f, target):
    yield SetFrequency(f)
    res = yield ControlSine(target, HOLD_S, label=f"{target * 1e3:g} mm")
    recs = res.records
    ends = np.array([r["sample_index"] for r in recs]) - res.start_index
    amps = np.array([r["achieved_m"] for r in recs])
    steady = amps[ends >= ends[-1] - STEADY_S * FS]
    err = 20 * np.log10(steady / target)
    return settle_cycles(ends, amps, target, f), float(err[np.argmax(np.abs(err))]), res.vpp


def scenario(cases, closed: bool, calib):
    """cases: list of (label, f, target, fresh) ; fresh = start from rest."""
    rows = []
    yield Rest(0.2)
    yield BeginStage("bench", {})
    for label, f, target, fresh in cases:
        if fresh:
            yield Rest(0.5)
        if closed:
            rows.append((label, f, target, *(yield from closed_loop(f, target))))
        else:
            rows.append((label, f, target, *(yield from open_loop(f, target / calib, target, HOLD_S + 1.0))))
    yield EndStage({})
    return rows


def run_plan(plan):
    with simulated_rig(speed=None, seed=0) as (_, cfg), tempfile.TemporaryDirectory() as d:
        out = acquire(cfg, load_protocol(), Path(d) / "b.h5", lockstep=True, plan=plan)
    if out.status != "complete":
        raise SystemExit(f"bench run {out.status}: {out.reason}")
    return out.plan_result


def calibrate():
    """Open-loop sensitivity at 8 Hz, small amplitude (m of base per Vpp)."""
    def plan():
        yield Rest(0.2)
        yield BeginStage("calibration", {})
        yield SetFrequency(8.0)
        yield Ramp(0.2)
        w = yield Acquire(3.0)
        yield EndStage({})
        return fundamental(w.x_base[-int(FS):], FS, 8.0) / 0.2
    return run_plan(plan())


def control_table():
    calib = calibrate()
    fr = 14.2
    groups = {
        "step": [("step 0 -> 0.1 mm", 8.0, 0.1e-3, True), ("step 0.1 -> 0.2 mm", 8.0, 0.2e-3, False),
                 ("step 0 -> 0.1 mm", fr, 0.1e-3, True), ("step 0.1 -> 0.2 mm", fr, 0.2e-3, False)],
        "sweep": [("sweep 0.05 mm", f, 0.05e-3, i == 0)
                  for i, f in enumerate((10.0, 12.0, 13.0, 13.5, 14.0, 14.2, 14.4, 15.0, 17.0, 20.0))],
        "levels": [(f"level {k + 1}", 12.5, 0.08e-3 * 1.5 ** k, k == 0) for k in range(8)],
    }
    lines = [f"sine control on the simulated rig (seed 0): open loop at the 8 Hz small-amplitude calibration "
             f"({calib * 1e3:.4f} mm/Vpp) vs closed loop (rig.sine_control, defaults)", ""]
    head = (f"{'case':<22}{'f Hz':>6}{'target mm':>11} | {'OL Vpp':>7}{'OL err dB':>10}{'OL settle cyc':>14} | "
            f"{'CL Vpp':>7}{'CL settle cyc':>14}{'CL err dB':>10}")
    lines += [head, "-" * len(head)]
    t0 = time.time()
    for name, cases in groups.items():
        ol = run_plan(scenario(cases, False, calib))
        cl = run_plan(scenario(cases, True, calib))
        for (label, f, target, o_set, o_err, o_v), (_, _, _, c_set, c_err, c_v) in zip(ol, cl):
            lines.append(f"{label:<22}{f:>6.2f}{target * 1e3:>11.4f} | {o_v:>7.3f}{o_err:>+10.2f}{o_set:>14.1f} | "
                         f"{c_v:>7.3f}{c_set:>14.1f}{c_err:>+10.2f}")
        lines.append("")
    lines.append(f"OL err: steady base amplitude over the target (largest |error| in the last {STEADY_S:g} s of the "
                 f"hold); OL settle: to within {TOL} dB of its own final value. CL settle: to within {TOL} dB of the "
                 f"target for good; CL err: largest |error| in the last {STEADY_S:g} s. Ramps at 1 Vpp/s count in "
                 f"the settling. ({time.time() - t0:.0f} s)")
    return "\n".join(lines)


def recon_table(seeds):
    from recon import ReconSettings, reconstruct
    from shakerlab.runfile.reader import load_run

    names = ("c_m", "k_m", "alpha_m", "gamma", "delta")
    protocols = {"volts (shipped)": None,
                 "base targets": Path(__file__).resolve().parents[1] / "rig" / "base_target_protocol.toml"}
    head = f"{'protocol':<18}{'seed':>5} " + "".join(f"{n:>9}" for n in names) + \
        f"{'y^2':>9}{'y^3':>9}{'y^2*dy':>9}{'NRMSE %':>9}  terms"
    lines = ["reconstruction (weak form, as shakerlab demo) from each protocol, error vs the simulator's truth [%]",
             "", head, "-" * len(head)]
    for label, path in protocols.items():
        for seed in seeds:
            with simulated_rig(speed=None, seed=seed) as (sim, cfg), tempfile.TemporaryDirectory() as d:
                out = acquire(cfg, load_protocol(path), Path(d) / "r.h5", lockstep=True)
                truth = sim.world.truth()
                if out.status != "complete":
                    lines.append(f"{label:<18}{seed:>5}  run {out.status}: {out.reason}")
                    continue
                res = reconstruct(load_run(out.path), ReconSettings(form="weak"))
            got = res.to_dict()["parameters"]
            errs = [got[n] / truth[n] - 1 for n in names]
            errs += [got["fn_m"].get(k, 0.0) / truth["fn_m"][k] - 1 for k in ("y^2", "y^3", "y^2*dy")]
            extra = sorted(set(got["fn_m"]) - set(truth["fn_m"]))
            lines.append(f"{label:<18}{seed:>5} " + "".join(f"{e * 100:>+9.2f}" for e in errs)
                         + f"{res.validation['nrmse'] * 100:>9.2f}  {'exact' if not extra else '+' + ','.join(extra)}")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recon", type=int, nargs="*", metavar="SEED", help="also compare reconstructions on these seeds")
    ap.add_argument("--no-control", action="store_true", help="skip the control table")
    a = ap.parse_args(argv)
    if not a.no_control:
        print(control_table(), flush=True)
    if a.recon:
        print()
        print(recon_table(a.recon))


if __name__ == "__main__":
    main()

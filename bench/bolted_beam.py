"""The real bolted-beam shaker test (UNESP-BERT, ../shared/data/bolted_beam): import the LMS Test.Lab
files directly, reconstruct from the chirps, and predict every other record, beside a linear model
fitted by output error on the same two chirps (the yardstick of issue 14). Prints a table.

    python bench/bolted_beam.py [--data ../shared/data/bolted_beam] [--work DIR]

Force = the shaker amplifier's voltage (the voltage-to-force gain is unknown, so 1/m absorbs it);
tip motion = the laser vibrometer's velocity (recon differentiates it once and integrates it once).
Stages: linear = 0.05 V chirp, nonlinear = 0.30 V chirp, validation = 0.15 V chirp.
The second column fits the exciter too (``reconstruct --drive``: the force is HP(u + u2 u^2)).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon import ReconSettings, reconstruct  # noqa: E402
from recon.estimator.fallback import simpler_models  # noqa: E402
from recon.model import HystereticModel  # noqa: E402
from recon.output_error.polish import polish  # noqa: E402
from recon.validation import nrmse  # noqa: E402
from shakerlab.runfile.reader import load_run  # noqa: E402

MAP = ["--map", "x=Time_Laser__X:v", "--map", "force=Time_Shaker__X"]
HELD_OUT = ("chirp_0p10", "chirp_0p15", "chirp_0p20", "chirp_0p25", "sine_09p5Hz", "sine_17Hz", "sine_20Hz")


def files(data: Path, rec: str) -> list[str]:
    return [str(data / rec / "Time.mat"), str(data / rec / "TimeShaker.mat")]


def shakerlab(*args) -> None:
    subprocess.run([sys.executable, "-m", "shakerlab.cli", *args], check=True, capture_output=True, text=True)


def exciter_evidence(data: Path) -> list[str]:
    """Model-free evidence of the exciter, from the raw MAT files: the chirp's phase lead at low
    frequency (tip displacement per volt), and the second harmonic of each sine read as a force
    distortion u2 u^2 through the 0.15 V chirp's frequency response at twice the tone."""
    from scipy.io import loadmat

    def load(rec):
        v = loadmat(data / rec / "Time.mat")["Time_Laser__X"][0, 0]["y_values"][0, 0]["values"].ravel()
        u = loadmat(data / rec / "TimeShaker.mat")["Time_Shaker__X"][0, 0]["y_values"][0, 0]["values"].ravel()
        return v, u
    fs = 1024.0
    v, u = load("chirp_0p15")
    f = np.fft.rfftfreq(v.size, 1 / fs)
    h = np.fft.rfft(v) / np.fft.rfft(u) / (2j * np.pi * np.maximum(f, 1e-9))     # displacement per volt

    def frf(f0):
        i = int(np.argmin(abs(f - f0)))
        return np.mean(h[i - 1:i + 2])
    out = ["chirp 0.15 V, phase of tip displacement per volt: "
           + ", ".join(f"{f0:g} Hz {np.degrees(np.angle(frf(f0))):+.0f} deg" for f0 in (5, 9.5, 15, 17))]
    for rec, f0 in (("sine_09p5Hz", 9.5), ("sine_17Hz", 17.0), ("sine_20Hz", 20.0)):
        v, u = load(rec)
        t = np.arange(v.size) / fs

        def c(x, fq):
            return 2.0 / x.size * np.sum(x * np.exp(-2j * np.pi * fq * t))
        u1, v2 = c(u, f0), c(v, 2 * f0)
        eps = (v2 / (2j * np.pi * 2 * f0) / frf(2 * f0)) / (u1 ** 2 / 2)
        out.append(f"{rec}: second harmonic of the velocity {abs(v2) / abs(c(v, f0)):.1%} of the first; "
                   f"read as a drive distortion u2 = {abs(eps):.3f} at {np.degrees(np.angle(eps)):+.0f} deg")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/bolted_beam")
    ap.add_argument("--work", type=Path, default=None)
    a = ap.parse_args()
    if not a.data.is_dir():
        print(f"no bolted-beam data at {a.data}", file=sys.stderr)
        return 2
    work = a.work or Path(tempfile.mkdtemp(prefix="bolted-beam-"))
    work.mkdir(parents=True, exist_ok=True)
    run_file = work / "beam.h5"
    if not run_file.exists():
        shakerlab("import", "-o", str(run_file), "--linear", *files(a.data, "chirp_0p05"),
                  "--nonlinear", *files(a.data, "chirp_0p30"), "--validation", *files(a.data, "chirp_0p15"), *MAP)
    print("\n".join(exciter_evidence(a.data)))
    run = load_run(run_file)
    res = reconstruct(run, ReconSettings())
    drv = reconstruct(run, ReconSettings(drive=True))   # the exciter fitted too (recon.exciter)
    linear = [f for f in simpler_models(run, ReconSettings(), None) if f.kind == "linear"][0].model
    # the yardstick given the exciter too: the linear SDOF and HP(u + u2 u^2), fitted the same way
    lin_drive = HystereticModel.from_dict(linear.to_dict())
    lin_drive.drive_u2, lin_drive.drive_hp = 0.0, 2 * np.pi * 0.1
    lin_drive, _ = polish(lin_drive, [lin_drive.fit_item(run.stage(n)) for n in ("linear", "nonlinear")],
                          free=["c_m", "k_m", "inv_m", "drive_u2", "drive_hp"])
    print("identified (chirps 0.05 V and 0.30 V):", res.model.equation().replace("\n", "  |  "))
    print("verdict:", res.adequacy["verdict"], "; fallback:", (res.adequacy.get("fallback") or {}).get("kind"))
    print("linear yardstick (output error, same chirps):", linear.equation().splitlines()[0])
    print("with --drive:", drv.model.equation().replace("\n", "  |  "))
    print("linear yardstick with the exciter:", lin_drive.equation().replace("\n", "  |  "))
    print("\n| record | shakerlab NRMSE | shakerlab --drive NRMSE | linear OE NRMSE | linear OE + exciter NRMSE |"
          "\n| --- | --- | --- | --- | --- |")
    for rec in HELD_OUT:
        h5 = work / f"{rec}.h5"
        if not h5.exists():
            shakerlab("import", "-o", str(h5), "--validation", *files(a.data, rec), *MAP)
        st = load_run(h5).stage("validation")
        out = []
        for m in (res.model, drv.model, linear, lin_drive):
            _, ys = m.simulate_stage(st)
            out.append(nrmse(ys, st.y) if np.all(np.isfinite(ys)) else float("inf"))
        print("| " + rec + " | " + " | ".join(f"{v:.3f}" for v in out) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

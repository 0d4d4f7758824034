"""A real MR damper under a white-noise displacement: the constitutive law beside the yardstick.

Run:  python bench/mr_damper_real.py DIR [--fit-share 0.7]

Data (not shipped): the prototype MR damper characterisation tests of S. Dyke (NEES-2012-1158,
DesignSafe-CI, DOI 10.4231/D3V11VM6X), random displacement and random coil voltage, 3 kHz,
as converted to engineering units (columns t, A, D [cm], Y [V], fs, V [cm/s], F [N]) in the
public repository Abhay3757/PSO-Optimized-Dual-Attention-LSTM-for-MR-Damper-Force-Prediction
(Dataset/ranran_50_converted.csv, 24.6 s, 0-50 Hz; Dataset/ransim_u_converted.csv, another
test of the same damper). DIR holds those two files.

The fit uses the first ``--fit-share`` of ranran_50; held out: the rest of it
(``validation``) and the whole of ransim_u (``validation_2``). Each record is converted to a
shakerlab component-test CSV (t, x [m], force [N], v [m/s], cmd [V]) and imported with
``shakerlab import --constitutive --fs 3004.8`` (the time column is printed to 0.1 ms, a third
of a step, so the import refuses it as jittered; the files' fs column gives the rate), then reconstructed with the
command-dependent law. Printed: the law, the held-out force NRMSE, the time, and the
linear-plus-Coulomb yardstick (bench/component.py) fitted on the same samples.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from component import yardstick  # noqa: E402

from recon.constitutive.estimator import ConstitutiveSettings, reconstruct_constitutive  # noqa: E402
from shakerlab.import_command import import_csv  # noqa: E402
from shakerlab.runfile.reader import load_run  # noqa: E402


FS = 3004.8      # Hz, the files' fs column


def read(path: Path) -> dict:
    d = np.genfromtxt(path, delimiter=",", skip_header=1, usecols=(0, 2, 3, 5, 6))
    t, D, Y, V, F = d.T
    return {"t": t - t[0], "x": 0.01 * D, "cmd": Y, "v": 0.01 * V, "force": F}


def part(rec: dict, sl) -> dict:
    out = {k: v[sl] for k, v in rec.items()}
    out["t"] = out["t"] - out["t"][0]
    return out


def write(rec: dict, path: Path) -> Path:
    cols = ("t", "x", "force", "v", "cmd")
    np.savetxt(path, np.column_stack([rec[c] for c in cols]), delimiter=",", header=",".join(cols), comments="",
               fmt="%.10g")
    return path


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", type=Path)
    ap.add_argument("--fit-share", type=float, default=0.7)
    ap.add_argument("--no-velocity", action="store_true", help="differentiate x instead of using the velocity")
    args = ap.parse_args()
    a = read(args.dir / "ranran_50_converted.csv")
    b = read(args.dir / "ransim_u_converted.csv")
    n = int(args.fit_share * a["t"].size)
    recs = {"nonlinear": part(a, slice(0, n)), "validation": part(a, slice(n, None)), "validation_2": b}
    with tempfile.TemporaryDirectory() as tmp:
        files = {}
        for name, rec in recs.items():
            if args.no_velocity:
                rec = {k: v for k, v in rec.items() if k != "v"}
                cols = ("t", "x", "force", "cmd")
                np.savetxt(Path(tmp) / f"{name}.csv", np.column_stack([rec[c] for c in cols]), delimiter=",",
                           header=",".join(cols), comments="", fmt="%.10g")
                files[name] = Path(tmp) / f"{name}.csv"
            else:
                files[name] = write(rec, Path(tmp) / f"{name}.csv")
        # the files print t to 0.1 ms (a third of a step) and state fs = 3004.8 Hz in their fs
        # column: the rate is declared (--fs), as a user would after the import's refusal
        run = load_run(import_csv(Path(tmp) / "mr.h5", files, constitutive=True, fs=FS))
        for name, st in run.stages.items():
            print(f"{name}: {st.t.size} samples at {st.fs:.6g} Hz ({st.settings.get('time_base', 'uniform')})")
        t0 = time.perf_counter()
        r = reconstruct_constitutive(run, ConstitutiveSettings())
        dt = time.perf_counter() - t0
    print(r.law.equation())
    print(f"fit {dt:.2f} s; polish: {r.law.provenance.get('output_error_polish', {}).get('constant_law', {}).get('start', '')}")
    for name, e in r.validation["per_stage"].items():
        y = yardstick(recs["nonlinear"], recs[name])
        print(f"held-out force NRMSE on {name:12s}: law {100 * e:6.2f} %   linear+Coulomb yardstick {100 * y:6.2f} %")
    print(f"verdict: {r.adequacy['verdict']} ({'; '.join(r.adequacy['reasons'])})")


if __name__ == "__main__":
    main()

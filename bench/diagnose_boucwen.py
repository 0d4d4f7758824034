"""The diagnosis on the Bouc-Wen benchmark (Noel & Schoukens 2016): a record made elsewhere, by
the benchmark's own integrator, whose physics is known.

Stages: the training multisine without its first period (the start-up transient) is the fitting
stage; 70 s of the test sine sweep (60-130 s: 30-42 Hz, through the resonance) is held out. The
benchmark has no small-amplitude stage, so the paper baseline (which needs one) is not run.

- ``--baseline linear``: the linear baseline lacks the hysteresis; the right answer is
  ``hysteresis`` with the benchmark's parameters (alpha/m = 25000, beta gamma = 800,
  beta delta = -1100 per m: gamma + delta < 0, a loop that hardens).
- the true law as the baseline: the right answer is nothing.

    python bench/diagnose_boucwen.py [--data DIR] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
for p in (str(HERE.parent), str(HERE)):
    if p not in sys.path:
        sys.path.insert(0, p)

import boucwen  # noqa: E402

from recon import diagnose  # noqa: E402
from recon.model import HystereticModel  # noqa: E402
from shakerlab.output_files import write_text  # noqa: E402
from shakerlab.run_data import Run, Stage  # noqa: E402

PERIOD = 8192
SWEEP_WINDOW = (60.0, 130.0)    # s of the test sweep held out
T = boucwen.TRUE
TRUE_LAW = HystereticModel("force", T["c"] / T["m"], T["k"] / T["m"], T["alpha"] / T["m"], T["gamma"], T["delta"],
                           inv_m=1.0 / T["m"])


def benchmark_run(data: str | None = None) -> Run:
    path = boucwen.data_dir(data)
    u, y = boucwen.load_training(path)
    u, y = u[PERIOD:], y[PERIOD:]
    us, ys = boucwen.load_test(path, "sinesweep")
    i0, i1 = (int(s * boucwen.FS) for s in SWEEP_WINDOW)
    dt = 1.0 / boucwen.FS
    return Run({"nonlinear": Stage("nonlinear", np.arange(u.size) * dt, {"x": y, "force": u}, excitation="force"),
                "validation": Stage("validation", np.arange(i1 - i0) * dt, {"x": ys[i0:i1], "force": us[i0:i1]},
                                    excitation="force")},
               source="Bouc-Wen benchmark (training multisine; test sweep 60-130 s held out)")


def run_all(data: str | None = None) -> list[dict]:
    run = benchmark_run(data)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        truth_path = os.path.join(tmp, "benchmark_law.json")
        TRUE_LAW.save(truth_path)
        for name, baseline, expect in (("linear", "linear", ["hysteresis"]), ("true law", truth_path, [])):
            t0 = time.perf_counter()
            d = diagnose(run, baseline=baseline).to_dict()
            named = [m["id"] for m in d["missing_physics"]]
            params = {m["id"]: {k: v["value"] for k, v in m["parameters"].items()} for m in d["missing_physics"]}
            out.append({"baseline": name, "expected": expect, "named": named, "right": named == expect,
                        "held_out_before": d["fit_before"]["held_out_nrmse_as_given"],
                        "held_out_null": d["fit_before"].get("refit_held_out_nrmse"),
                        "held_out_after": d["fit_after"]["held_out_nrmse"], "parameters": params,
                        "seconds": time.perf_counter() - t0})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", help="benchmark data directory (default ../shared/data/boucwen)")
    ap.add_argument("--json", help="write the rows to this JSON file")
    args = ap.parse_args(argv)
    if args.json and Path(args.json).exists():
        raise SystemExit(f"{args.json}: file exists; name a new file (saved results are never overwritten)")
    rows = run_all(args.data)
    print("| baseline | expected | named | held-out NRMSE as given -> null -> after | right | s |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['baseline']} | {', '.join(r['expected']) or 'nothing'} | {', '.join(r['named']) or 'nothing'} | "
              f"{r['held_out_before']:.4g} -> {r['held_out_null']:.4g} -> {r['held_out_after']:.4g} | "
              f"{'yes' if r['right'] else 'NO'} | {r['seconds']:.0f} |")
    for r in rows:
        h = r["parameters"].get("hysteresis")
        if h:
            truth = {"alpha_m": T["alpha"] / T["m"], "gamma": T["gamma"], "delta": T["delta"]}
            print("hysteresis parameters (" + r["baseline"] + " baseline): "
                  + ", ".join(f"{k} {h[k]:.5g} (true {truth[k]:.5g}, {100 * (h[k] / truth[k] - 1):+.1f} %)"
                              for k in truth if k in h))
    if args.json:
        write_text(args.json, json.dumps(rows, indent=1), overwrite=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

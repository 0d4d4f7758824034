"""Accuracy of the reconstruction against ground truth: SDOF, two-layer, five-layer and
MR-damper examples at SNR 80/60/40/30 dB, pointwise vs weak form.

    python bench/recon_accuracy.py            # full table (several minutes on 2 busy cores)
    python bench/recon_accuracy.py --quick    # 80 and 40 dB, shorter chain records

Columns: max and median relative parameter error [%] (every per-unit-mass parameter and
fn coefficient of the truth; for chains every layer, mass ratios excluded), spurious and
missed fn terms (a hysteresis reported in a layer without one counts as spurious, a
missed one as missed), validation NRMSE on the unseen stage(s) (the worst one), fit time.
The MR isolator has no true agent-model parameters (another hysteresis law): only its
validation NRMSE is scored. The weak form exists for the SDOF estimator only.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from recon.mdof import reconstruct_chain  # noqa: E402
from recon.pipeline import ReconSettings, reconstruct  # noqa: E402
from recon.truth import sdof_run  # noqa: E402
from recon.truth_mdof import chain_run, five_layer_truth, mr_run, two_layer_truth  # noqa: E402
from shakerlab.errors import UserFacingError  # noqa: E402

KEYS = ("c_m", "k_m", "alpha_m", "gamma", "delta")


def score_sdof(model, truth):
    err = [abs(getattr(model, k) / getattr(truth, k) - 1) for k in KEYS]
    err += [abs(model.fn_m.get(k, 0.0) / v - 1) for k, v in truth.fn_m.items()]
    spur = len(set(model.fn_m) - set(truth.fn_m))
    miss = len(set(truth.fn_m) - set(model.fn_m))
    return err, spur, miss


def score_chain(res, truth):
    err, spur, miss = [], 0, 0
    for i, L in enumerate(res.layers):
        tr = truth.layer(i)
        err += [abs(getattr(L, k) / tr[k] - 1) for k in KEYS + ("inv_m",) if tr[k]]
        err += [abs(L.fn_m.get(k, 0.0) / v - 1) for k, v in tr["fn_m"].items()]
        spur += len(set(L.fn_m) - set(tr["fn_m"])) + int(L.hysteresis and not tr["hysteresis"])
        miss += len(set(tr["fn_m"]) - set(L.fn_m)) + int(tr["hysteresis"] and not L.hysteresis)
    return err, spur, miss


def run_case(system, snr, form, quick, seed=0):
    t0 = time.perf_counter()
    try:
        if system == "SDOF":
            run, truth = sdof_run("base", snr_db=snr, seed=seed)
            t0 = time.perf_counter()
            res = reconstruct(run, ReconSettings(form="weak" if form == "weak" else "joint"))
            dt = time.perf_counter() - t0
            err, spur, miss = score_sdof(res.model, truth)
            val = max(res.validation["per_stage"].values())
        elif system == "MR isolator":
            run = mr_run(snr_db=snr, seed=seed)
            t0 = time.perf_counter()
            res = reconstruct(run, ReconSettings(form="weak" if form == "weak" else "joint"))
            dt = time.perf_counter() - t0
            err, spur, miss = None, None, None
            val = max(res.validation["per_stage"].values())
        else:
            if form == "weak":
                return None
            truth = two_layer_truth() if system == "two-layer" else five_layer_truth()
            run, _ = chain_run(truth, snr_db=snr, seed=seed, duration=5.0 if quick else 10.0)
            t0 = time.perf_counter()
            res = reconstruct_chain(run, polish_substeps=1 if quick else 2)
            dt = time.perf_counter() - t0
            err, spur, miss = score_chain(res, truth)
            val = res.validation["nrmse"]
    except UserFacingError as exc:
        return {"fail": str(exc)[:70], "time": time.perf_counter() - t0}
    out = {"time": dt, "nrmse": val, "spur": spur, "miss": miss}
    if err is not None:
        e = 100 * np.array(err)
        out.update(max=float(np.max(e)), median=float(np.median(e)))
    return out


def fmt(v, spec):
    return "n/a" if v is None else format(v, spec)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="80 and 40 dB only, 5 s chain records")
    ap.add_argument("--systems", default="SDOF,two-layer,five-layer,MR isolator")
    ap.add_argument("--snr", default=None, help="comma-separated SNRs in dB (default 80,60,40,30)")
    a = ap.parse_args(argv)
    snrs = [float(s) for s in a.snr.split(",")] if a.snr else ([80.0, 40.0] if a.quick else [80.0, 60.0, 40.0, 30.0])
    warnings.filterwarnings("ignore")
    print("| system | SNR dB | form | max err % | median err % | spurious | missed | validation NRMSE | fit time s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for system in a.systems.split(","):
        for snr in snrs:
            for form in ("pointwise", "weak"):
                r = run_case(system, snr, form, a.quick)
                if r is None:
                    print(f"| {system} | {snr:g} | {form} | not implemented for chains | | | | | |", flush=True)
                elif "fail" in r:
                    print(f"| {system} | {snr:g} | {form} | failed: {r['fail']} | | | | | {r['time']:.1f} |", flush=True)
                else:
                    print(f"| {system} | {snr:g} | {form} | {fmt(r.get('max'), '.3g')} | {fmt(r.get('median'), '.3g')} | "
                          f"{fmt(r['spur'], 'd')} | {fmt(r['miss'], 'd')} | {r['nrmse']:.3g} | {r['time']:.1f} |",
                          flush=True)


if __name__ == "__main__":
    main()

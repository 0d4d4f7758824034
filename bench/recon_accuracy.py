"""Accuracy of the reconstruction against ground truth: SDOF, two-layer, five-layer and
MR-damper examples at SNR 80/60/40/30 dB, pointwise vs weak form.

    python bench/recon_accuracy.py            # full table (several minutes on 2 busy cores)
    python bench/recon_accuracy.py --quick    # 80 and 40 dB, shorter chain records
    python bench/recon_accuracy.py --systems SDOF --snr 40 --seeds 8   # the 40 dB aim over 8 noise seeds
    python bench/recon_accuracy.py --stress --seeds 50 --workers 2 --jsonl stress.jsonl   # issue 18

--stress: recordings from the independent generator (recon/testing/independent.py, no code
shared with recon), random TMP-like systems (f_n 5-60 Hz, y^2/y^3 on or off, Bouc-Wen with
gamma, delta of either sign and gamma + delta > 0), the paper's protocol (even seeds) and the
rig's protocol (odd seeds), fs log-uniform 1-10 kHz; seed i = system i with noise seed i, the
same recording at every SNR. Default reconstruct (the CLI's settings). Per SNR: share with the
exact terms, median and 95th percentile of the worst parameter error, share within 2 % / 5 %
with the exact terms, share inadmissible (alpha <= 0, gamma + delta <= 0, K <= 0, non-finite,
or a validation simulation that diverges) and share failed (reconstruct raised), and how many
of the misses the record itself explains: the output-error fit of reconstruct's polish started
at the truth with the true terms misses the target too (recon_stress.record_limit).

Columns: max and median relative parameter error [%] (every per-unit-mass parameter and
fn coefficient of the truth; for chains every layer, mass ratios excluded), spurious and
missed fn terms (a hysteresis reported in a layer without one counts as spurious, a
missed one as missed), validation NRMSE on the unseen stage(s) (the worst one), fit time. For chains the
"weak" rows use the weak path form in every hysteretic layer (recon.chain.estimator, the default;
the hysteresis decision and the pattern pilot still come from the pointwise agent model).
Each form runs on its own (``fallback_form=None``): the default pipeline would switch
to the weak form where the pointwise equation-error estimate is not admissible.
The MR isolator has no true agent-model parameters (another hysteresis law): only its
validation NRMSE is scored.
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

from recon.chain.estimator import reconstruct_chain  # noqa: E402
from recon import ReconSettings, reconstruct  # noqa: E402
from recon.testing.truth import sdof_run  # noqa: E402
from recon.testing.truth_mdof import chain_run, five_layer_truth, mr_run, two_layer_truth  # noqa: E402
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
            res = reconstruct(run, ReconSettings(form="weak" if form == "weak" else "joint", fallback_form=None))
            dt = time.perf_counter() - t0
            err, spur, miss = score_sdof(res.model, truth)
            val = max(res.validation["per_stage"].values())
        elif system == "MR isolator":
            run = mr_run(snr_db=snr, seed=seed)
            t0 = time.perf_counter()
            res = reconstruct(run, ReconSettings(form="weak" if form == "weak" else "joint", fallback_form=None))
            dt = time.perf_counter() - t0
            err, spur, miss = None, None, None
            val = max(res.validation["per_stage"].values())
        else:
            truth = two_layer_truth() if system == "two-layer" else five_layer_truth()
            run, _ = chain_run(truth, snr_db=snr, seed=seed, duration=5.0 if quick else 10.0)
            t0 = time.perf_counter()
            # chains: "weak" = the path form in every hysteretic layer (the default), "pointwise" =
            # the pointwise structured refit and h = 0 delta step
            res = reconstruct_chain(run, polish_substeps=1 if quick else 2, path_form=form == "weak")
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


def aggregate(rows: list):
    """One table row from the per-seed results: worst max error, median of the per-seed
    maxima (one seed: its median error), summed spurious/missed terms, worst NRMSE, mean time."""
    fails = [r for r in rows if "fail" in r]
    if len(fails) == len(rows):
        return fails[0]
    ok = [r for r in rows if "fail" not in r]
    good = sum(1 for r in ok if r.get("max") is not None and r["max"] <= 5.0 and r["spur"] == 0 and r["miss"] == 0)
    out = {"time": float(np.mean([r["time"] for r in rows])), "nrmse": max(r["nrmse"] for r in ok),
           "spur": None if ok[0]["spur"] is None else sum(r["spur"] for r in ok),
           "miss": None if ok[0]["miss"] is None else sum(r["miss"] for r in ok),
           "good": f"{good}/{len(rows)}" if ok[0].get("max") is not None else "n/a"}
    if ok[0].get("max") is not None:
        out["max"] = max(r["max"] for r in ok)
        out["median"] = ok[0]["median"] if len(rows) == 1 else float(np.median([r["max"] for r in ok]))
    if fails:
        out["good"] += f" ({len(fails)} failed)"
    return out


def fmt(v, spec):
    return "n/a" if v is None else format(v, spec)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="80 and 40 dB only, 5 s chain records")
    ap.add_argument("--systems", default="SDOF,two-layer,five-layer,MR isolator")
    ap.add_argument("--snr", default=None, help="comma-separated SNRs in dB (default 80,60,40,30)")
    ap.add_argument("--seeds", type=int, default=None, help="noise seeds per row (0..N-1): the row reports the worst "
                                                          "seed, the median of the per-seed maxima, and how many seeds "
                                                          "are within 5 %% with the exact pattern (default 1; --stress: 50)")
    ap.add_argument("--stress", action="store_true", help="the independent generator's stress table (issue 18)")
    ap.add_argument("--workers", type=int, default=1, help="--stress: worker processes (at most 2 on a shared machine)")
    ap.add_argument("--jsonl", default=None, help="--stress: write one JSON row per run to this file")
    ap.add_argument("--first-seed", type=int, default=0, help="--stress: seeds first-seed .. first-seed+seeds-1")
    ap.add_argument("--protocols", default="paper,rig", help="--stress: protocols, alternated over the seeds")
    ap.add_argument("--noise-offset", type=int, default=0,
                    help="--stress: noise seed = system seed + this (another noise draw of the same systems)")
    ap.add_argument("--quantity", default="displacement", choices=("displacement", "velocity", "acceleration"),
                    help="--stress: the tip recorded as this quantity, at the SNR in its own rms (velocity: white "
                         "plus 1/f noise, as a vibrometer's)")
    ap.add_argument("--seed-list", default=None, help="--stress: these seeds (comma-separated) instead of a range")
    ap.add_argument("--from-jsonl", nargs="+", default=None,
                    help="--stress: print the tables from stored rows (files of --jsonl; a later file's row for "
                         "the same seed and SNR replaces an earlier one) instead of running")
    ap.add_argument("--against", nargs="+", default=None,
                    help="--stress: compare the rows (run or --from-jsonl) with these stored rows, seed and SNR "
                         "alike: how many answers are the same (every parameter within 1e-6, the same terms) and "
                         "each one that is not")
    a = ap.parse_args(argv)
    if a.stress:
        import recon_stress  # noqa: E402  (bench/recon_stress.py: the --stress table)
        return recon_stress.main(a)
    a.seeds = a.seeds or 1
    snrs = [float(s) for s in a.snr.split(",")] if a.snr else ([80.0, 40.0] if a.quick else [80.0, 60.0, 40.0, 30.0])
    warnings.filterwarnings("ignore")
    print("| system | SNR dB | form | max err % | median err % | spurious | missed | seeds exact and <= 5 % "
          "| validation NRMSE | fit time s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for system in a.systems.split(","):
        for snr in snrs:
            for form in ("pointwise", "weak"):
                r = aggregate([run_case(system, snr, form, a.quick, seed) for seed in range(a.seeds)])
                if "fail" in r:
                    print(f"| {system} | {snr:g} | {form} | failed: {r['fail']} | | | | | | {r['time']:.1f} |",
                          flush=True)
                else:
                    print(f"| {system} | {snr:g} | {form} | {fmt(r.get('max'), '.3g')} | {fmt(r.get('median'), '.3g')} | "
                          f"{fmt(r['spur'], 'd')} | {fmt(r['miss'], 'd')} | {r['good']} | {r['nrmse']:.3g} | "
                          f"{r['time']:.1f} |", flush=True)


if __name__ == "__main__":
    sys.exit(main())

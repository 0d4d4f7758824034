"""Coverage of the 95 % parameter intervals (recon.output_error.uncertainty) over simulated repetitions.

    python bench/uncertainty_coverage.py                 # 50 repetitions at 60 dB, both modes
    python bench/uncertainty_coverage.py --reps 10 --mode structure --json

Each repetition simulates the ground-truth SDOF base-excited system
(recon.testing.truth.sdof_run, new noise seed) at the given SNR and computes the
intervals; the table gives, per parameter, the fraction of repetitions whose
interval holds the true value, the median relative half-width and the mean
relative error of the estimate (the bias).

Modes:
- ``pipeline``: the whole reconstruction (term selection, equation-error
  estimate, output-error polish), then the intervals. A true term the
  selection missed counts as not covered.
- ``structure``: the library terms fixed to the true ones; the output-error
  polish started from the true values perturbed by 3 % (as the recon step
  would hand them over), then the intervals. This isolates the calibration of
  the intervals from the term selection.

Repetitions run in parallel on a local Dask cluster (``--workers``).
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1]))

from recon.model import PARAMETER_NAMES as NAMES  # noqa: E402


def one(mode: str, seed: int, snr: float, fs: float, duration: float, resamples: int) -> dict:
    from recon.model import HystereticModel
    from recon.testing.truth import sdof_run
    from recon.output_error.uncertainty import UncertaintySettings, covers, parameter_intervals

    t0 = time.perf_counter()
    run, truth = sdof_run("base", snr_db=snr, fs=fs, duration=duration, seed=1000 + seed)
    tp = truth.to_dict()["parameters"]
    try:
        if mode == "pipeline":
            from recon import reconstruct

            model = reconstruct(run).model
        else:
            from recon.output_error.polish import polish

            rng = np.random.default_rng(seed)
            jitter = {k: (v * (1 + 0.03 * rng.standard_normal()) if not isinstance(v, dict)
                          else {kk: vv * (1 + 0.03 * rng.standard_normal()) for kk, vv in v.items()})
                      for k, v in tp.items()}
            start = HystereticModel.from_dict({"excitation": "base", "parameters": jitter})
            st = run.stage("nonlinear")        # the stage the pipeline's polish fits, from its recorded start
            model, _ = polish(start, [start.fit_item(st)])
        t1 = time.perf_counter()
        unc = parameter_intervals(model, run, UncertaintySettings(n_resamples=resamples, seed=seed))
    except Exception as exc:  # noqa: BLE001 - a failed repetition counts as not covered
        return {"seed": seed, "error": f"{type(exc).__name__}: {exc}", "covered": {}, "seconds": time.perf_counter() - t0}
    est = model.to_dict()["parameters"]
    rel_err, half = {}, {}
    for k in NAMES:
        rel_err[k] = (est[k] - tp[k]) / abs(tp[k])
        lo, hi = unc["intervals"][k]
        half[k] = 0.5 * (hi - lo) / abs(tp[k])
    for term, v in tp["fn_m"].items():
        key = f"fn_m[{term}]"
        if term in est["fn_m"]:
            rel_err[key] = (est["fn_m"][term] - v) / abs(v)
            lo, hi = unc["intervals"]["fn_m"][term]
            half[key] = 0.5 * (hi - lo) / abs(v)
    return {"seed": seed, "covered": covers(unc, tp), "rel_err": rel_err, "half_width": half,
            "terms": sorted(est["fn_m"]), "seconds": time.perf_counter() - t0, "interval_seconds": time.perf_counter() - t1,
            "at_optimum": unc["at_optimum"]}


def summarise(rows: list[dict], true_keys: list[str]) -> list[dict]:
    out = []
    for k in true_keys:
        cov = [bool(r["covered"].get(k, False)) for r in rows]
        hw = [r["half_width"][k] for r in rows if k in r.get("half_width", {})]
        err = [r["rel_err"][k] for r in rows if k in r.get("rel_err", {})]
        out.append({"parameter": k, "coverage": float(np.mean(cov)), "n": len(cov),
                    "median_half_width_pct": 100 * float(np.median(hw)) if hw else float("nan"),
                    "mean_error_pct": 100 * float(np.mean(err)) if err else float("nan"),
                    "rms_error_pct": 100 * float(np.sqrt(np.mean(np.square(err)))) if err else float("nan")})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--snr", type=float, default=60.0)
    ap.add_argument("--fs", type=float, default=2000.0)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--resamples", type=int, default=200)
    ap.add_argument("--mode", choices=("pipeline", "structure", "both"), default="both")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    from dask.distributed import Client, LocalCluster, as_completed

    from recon.testing.truth import sdof_truth

    tp = sdof_truth("base").to_dict()["parameters"]
    true_keys = list(NAMES) + [f"fn_m[{t}]" for t in tp["fn_m"]]
    modes = ("pipeline", "structure") if a.mode == "both" else (a.mode,)
    report = {}
    with LocalCluster(n_workers=a.workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                      host="127.0.0.1") as cluster, Client(cluster) as client:
        for mode in modes:
            t0 = time.perf_counter()
            futs = [client.submit(one, mode, s, a.snr, a.fs, a.duration, a.resamples, pure=False) for s in range(a.reps)]
            rows = []
            for i, f in enumerate(as_completed(futs), 1):
                rows.append(f.result())
                print(f"\r{mode}: {i}/{a.reps} repetitions", end="", file=sys.stderr, flush=True)
            print(file=sys.stderr)
            rows.sort(key=lambda r: r["seed"])
            table = summarise(rows, true_keys)
            wrong_terms = sum(1 for r in rows if r.get("terms") != sorted(tp["fn_m"]))
            report[mode] = {"table": table, "wall_s": time.perf_counter() - t0, "wrong_terms": wrong_terms,
                            "errors": [r["error"] for r in rows if "error" in r],
                            "median_interval_s": float(np.nanmedian([r.get("interval_seconds", np.nan) for r in rows])),
                            "all_covered": float(np.mean([all(r["covered"].get(k, False) for k in true_keys)
                                                          for r in rows]))}
    if a.json:
        print(json.dumps({"settings": vars(a), "results": report}, indent=2))
        return 0
    print(f"95 % interval coverage, {a.reps} repetitions, SNR {a.snr:g} dB, fs {a.fs:g} Hz, "
          f"{a.duration:g} s stages, {a.resamples} ensemble members")
    for mode, r in report.items():
        print(f"\nmode {mode}: wall {r['wall_s']:.0f} s ({a.workers} workers), interval step median "
              f"{r['median_interval_s']:.1f} s, repetitions with wrong terms {r['wrong_terms']}, "
              f"all parameters covered in {100 * r['all_covered']:.0f} %"
              + (f", failed repetitions {len(r['errors'])}" if r["errors"] else ""))
        print("| parameter | coverage | median half-width % | mean error % (bias) | rms error % |")
        print("| --- | --- | --- | --- | --- |")
        for row in r["table"]:
            print(f"| {row['parameter']} | {100 * row['coverage']:.0f} % | {row['median_half_width_pct']:.3g} | "
                  f"{row['mean_error_pct']:+.3g} | {row['rms_error_pct']:.3g} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Batch reprocessing throughput: plain loop vs Dask LocalCluster with 1 and 2 workers.

    python bench/batch_throughput.py                  # 8 runs of 2 x 4 s at 1 kHz
    python bench/batch_throughput.py --runs 4 --duration 10 --fs 2000 --json

Writes ``--runs`` simulated run files (recon.testing.truth ground truth) into a
temporary directory, then reprocesses them (reconstruction + intervals, no
write-back so every pass does the full work) with:

- ``loop``: workflows.batch.run_loop in this process (no Dask);
- ``dask N``: workflows.batch.run_batch on a fresh LocalCluster of N worker
  processes (one thread each); the wall time includes starting and stopping
  the cluster, which is also timed on its own (``cluster start+stop``).

The Dask overhead is (dask-1 wall - loop wall): scheduling, pickling the rows,
the cluster start-up and a worker's cold numba/JIT caches. The first pass of
each mode runs the numba kernels from the on-disk cache.

Dask's nanny starts every worker with OMP/OPENBLAS/MKL_NUM_THREADS=1. The loop
runs with ``--blas-threads`` (default 1, the same) so that the comparison is
of the scheduling, not of the BLAS threading: with OpenBLAS's default (one
thread per CPU) the loop was 3.5 times slower on the shared 2-CPU machine
(many small matrix products fighting over the CPUs).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--fs", type=float, default=1000.0)
    ap.add_argument("--duration", type=float, default=4.0)
    ap.add_argument("--resamples", type=int, default=200)
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS/OpenMP threads in this process for the loop (default 1, as Dask's workers set)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if "numpy" in sys.modules:
        print("warning: numpy already imported, --blas-threads has no effect", file=sys.stderr)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(a.blas_threads)
    from dask.distributed import Client, LocalCluster

    from workflows.batch import BatchSettings, process_run, run_batch, run_loop, write_simulated_run

    tmp = Path(tempfile.mkdtemp(prefix="shakerlab-batch-"))
    paths = []
    for i in range(a.runs):
        p = tmp / f"run_{i:03d}.h5"
        write_simulated_run(p, fs=a.fs, duration=a.duration, seed=i)
        paths.append(str(p))
    job = dict(uncertainty_settings={"n_resamples": a.resamples}, write_back=False, force=True)
    process_run(paths[0], BatchSettings(**job).job())          # warm this process's numba caches
    rows = []
    t = time.perf_counter()
    res = run_loop(paths, BatchSettings(**job))
    rows.append({"mode": "loop", "workers": 1, "wall_s": time.perf_counter() - t,
                 "ok": sum(r["status"] == "ok" for r in res)})
    loop_rows = res
    t = time.perf_counter()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                      host="127.0.0.1") as cluster, Client(cluster):
        pass
    cluster_s = time.perf_counter() - t
    for n in (1, 2):
        t = time.perf_counter()
        res = run_batch(paths, BatchSettings(workers=n, **job))
        rows.append({"mode": f"dask {n}", "workers": n, "wall_s": time.perf_counter() - t,
                     "ok": sum(r["status"] == "ok" for r in res),
                     "identical_to_loop": all(r["parameters"] == q["parameters"] for r, q in zip(res, loop_rows))})
    loop_s = rows[0]["wall_s"]
    for r in rows:
        r["runs_per_min"] = 60.0 * a.runs / r["wall_s"]
        r["vs_loop"] = r["wall_s"] / loop_s
    out = {"runs": a.runs, "blas_threads": a.blas_threads, "fs": a.fs, "duration_s": a.duration, "resamples": a.resamples, "cpus": os.cpu_count(),
           "load_average": os.getloadavg(), "cluster_start_stop_s": cluster_s,
           "dask_overhead_s": rows[1]["wall_s"] - loop_s, "rows": rows}
    if a.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{a.runs} runs (2 stages + validation, {a.duration:g} s at {a.fs:g} Hz), reconstruction + intervals "
          f"({a.resamples} members), {os.cpu_count()} CPUs, loop with {a.blas_threads} BLAS thread(s), load average at the end "
          f"{', '.join(f'{v:.1f}' for v in os.getloadavg())}")
    print("| mode | workers | wall s | runs/min | wall / loop | runs ok | identical to loop |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['mode']} | {r['workers']} | {r['wall_s']:.1f} | {r['runs_per_min']:.1f} | {r['vs_loop']:.2f} | "
              f"{r['ok']}/{a.runs} | {r.get('identical_to_loop', '-')} |")
    print(f"LocalCluster (2 processes) start+stop alone: {cluster_s:.1f} s; Dask overhead with 1 worker "
          f"(dask 1 - loop): {out['dask_overhead_s']:+.1f} s = {out['dask_overhead_s'] / a.runs:+.2f} s per run")
    return 0


if __name__ == "__main__":
    sys.exit(main())

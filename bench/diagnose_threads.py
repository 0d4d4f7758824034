"""`python bench/diagnose_threads.py [ROWS...] [--threads N]`: the diagnosis of independent stress
recordings (recon.testing.stress) run serially (SHAKERLAB_THREADS=1) and with N threads for the
output-error fits' finite differences (recon/threads.py), each in its own process.

Prints a table: the recording, its protocol and sample count, the wall-clock seconds of each run,
the speed-up, and whether the two diagnoses are the same to the bit (the JSON report, timing fields
aside). Default rows: #433 (paper protocol), #572 (sweep), #481 (multisine), #387 (rig).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

CHILD = r"""
import json, sys, time, warnings
warnings.filterwarnings("ignore")
sys.path[:0] = [{root!r}]
from recon import diagnose
from recon.testing.runs import to_run
from recon.testing.stress import draw, recording
d = draw({row})
rec = recording(d)
run = to_run(rec)
t0 = time.perf_counter()
out = diagnose(run, baseline="paper").to_dict()
secs = time.perf_counter() - t0
def strip(o):
    if isinstance(o, dict):
        return {{k: strip(v) for k, v in o.items() if k not in ("seconds", "time_s")}}
    if isinstance(o, list):
        return [strip(v) for v in o]
    return o
json.dump({{"seconds": secs, "protocol": d["protocol"],
           "samples": sum(int(s["t"].size) for s in rec["stages"].values()),
           "report": strip(out)}}, open({path!r}, "w"), sort_keys=True, default=str)
"""


def run_row(row: int, threads: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "out.json")
        env = dict(os.environ, SHAKERLAB_THREADS=str(threads))
        subprocess.run([sys.executable, "-c", CHILD.format(root=ROOT, row=row, path=path)],
                       check=True, env=env)
        with open(path) as f:
            return json.load(f)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", nargs="*", type=int, default=[433, 572, 481, 387])
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    print(f"| row | protocol | samples | 1 thread [s] | {a.threads} threads [s] | speed-up | same report |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for row in a.rows:
        one = run_row(row, 1)
        many = run_row(row, a.threads)
        print(f"| #{row} | {one['protocol']} | {one['samples']} | {one['seconds']:.1f} | {many['seconds']:.1f} | "
              f"{one['seconds'] / many['seconds']:.2f} | {'yes' if one['report'] == many['report'] else 'NO'} |",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

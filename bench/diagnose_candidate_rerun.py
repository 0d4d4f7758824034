"""One catalog candidate diagnosed again on chosen stress rows, against the rows' stored answers.

    python bench/diagnose_candidate_rerun.py --candidate sensor_scale --rows 0 1 13 \
        --stored bench/results/diagnose_stress_*.jsonl --jsonl out.jsonl

A change that touches one candidate's fit only (where it starts, what it may drop) can change a
row's answer only through that candidate: if it turns significant on a clean row or beside
another effect, or stops being significant where it was named. This reruns the diagnosis with
that candidate alone (its fit, its null models, its score; seconds to a minute per row, not the
several minutes of the whole catalog) and prints, per row, the candidate as stored (latest stored
answer of the row: ``--stored`` files in order, later files win) and as it now comes out. With
``--only-hysteretic`` a row whose baseline has no Bouc-Wen law is skipped (reported as such):
for changes that act only through the core without the law.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from diagnose_stress import draw, recording  # noqa: E402
from independent_run import model_of, to_run  # noqa: E402

from recon.diagnosis import diagnose as D  # noqa: E402

KEYS = ("significant", "explained", "held_out_nrmse", "started_from", "failed")


def stored_answers(files) -> dict:
    latest = {}
    for f in files:
        for line in open(f):
            r = json.loads(line)
            if "right" in r:
                latest[r["index"]] = r
    return latest


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--candidate", required=True)
    ap.add_argument("--rows", type=int, nargs="+", required=True)
    ap.add_argument("--stored", nargs="*", default=[])
    ap.add_argument("--jsonl", required=True, help="appended to, one line per row")
    ap.add_argument("--only-hysteretic", action="store_true")
    a = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    latest = stored_answers(a.stored)
    print(f"{'row':>5} {'effect':20} {'protocol':9} {'alpha':>10}  {'stored sig/expl/held':28} {'now sig/expl/held':28} from")
    with open(a.jsonl, "a") as out:
        for i in a.rows:
            t0 = time.time()
            d = draw(i)
            rec = recording(d)
            baseline = model_of(rec["baseline"]) if "baseline" in rec else "paper"
            run = to_run(rec)
            base, _ = D.resolve_baseline(run, baseline)
            old = latest.get(i, {})
            oc = {c["id"]: c for c in old.get("candidates", [])}.get(a.candidate, {})
            res = {"index": i, "effect": d["effect"], "protocol": d["protocol"], "alpha": base.baseline.alpha_m,
                   "candidate": a.candidate, "stored_named": old.get("named"), "stored_right": old.get("right"),
                   "stored": {k: oc.get(k) for k in KEYS}}
            if not (a.only_hysteretic and base.baseline.alpha_m == 0.0):
                dg = D.diagnose(run, baseline=baseline, candidates=[a.candidate]).to_dict()
                c = dg["candidates_tested"][0] if dg["candidates_tested"] else {}
                res["now"] = {k: c.get(k) for k in KEYS}
            res["seconds"] = time.time() - t0
            print(json.dumps(res), file=out, flush=True)

            def fmt(c):
                if not c:
                    return "-"
                return f"{c.get('significant')!s:5} {c.get('explained') or 0:8.3f} {c.get('held_out_nrmse') or 0:.3g}"
            print(f"{i:5d} {d['effect']:20} {d['protocol']:9} {res['alpha']:10.4g}  {fmt(res['stored']):28} "
                  f"{fmt(res.get('now')):28} {(res.get('now') or {}).get('started_from', 'skipped')}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

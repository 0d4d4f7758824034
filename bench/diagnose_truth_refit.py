"""A stress row's truth fitted again from itself: does the record pin it, or do its fitting stages
prefer another model?

    python bench/diagnose_truth_refit.py --rows 111 315 641 [--burn-in 3] [--jsonl out.jsonl]

For each row of the independent generator (bench/diagnose_stress.py) the truth's own structure is
put to the diagnosis's output-error fit (recon.diagnosis.rank.fit), started at the truth with every
parameter free (the baseline's keys and the effect's). Where a candidate's fit ended away from a
truth that passes the rule, this says which of two things happened: the fit from the truth stays
there (the diagnosis did not find the start), or it moves to a lower fitting cost and a worse
held-out NRMSE (the fitting stages prefer a wrong model; no start helps). ``--burn-in D`` leaves
the first D decay times of the true mode (D / (zeta w_n)) of the rig protocol's resonance-search
stage out of the fit: the test of that stage's start transient (docs/diagnosis.md, 2026-12-01a).
Prints one line per row and the per-stage NRMSE of the truth and of its refit.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from diagnose_stress import draw, recording  # noqa: E402
from independent_run import to_run, true_model  # noqa: E402

from recon.diagnosis import diagnose as D  # noqa: E402
from recon.diagnosis import rank  # noqa: E402

SHAPE_EXTRAS = ("v0", "side", "gap")     # set by a candidate's shape, not fitted beside the rest


def truth_refit(i: int, burn_in: float | None = None) -> dict:
    d = draw(i)
    rec = recording(d)
    run = to_run(rec)
    tm = true_model(rec)
    if tm is None:
        return {"index": i, "effect": d["effect"], "skipped": "no truth to refit (a clean row or an unstated effect)"}
    truth = tm[0]
    base, _ = D.resolve_baseline(run, "paper")
    data = rank.prepare(run, base.baseline)
    cut = None
    if burn_in:
        wn = math.sqrt(truth.baseline.k_m)
        cut = burn_in / (truth.baseline.c_m / (2 * wn) * wn)
        data = [dataclasses.replace(s, fit=s.fit & (s.t >= s.t[0] + cut)) if s.name == "resonance_search" else s
                for s in data]
    keys = list(dict.fromkeys(D.every_parameter(truth)
                              + [f"x:{e}" for e in truth.extras if e not in SHAPE_EXTRAS]))
    given = rank.fit(base, [], data)
    null = rank.fit(base, D.every_parameter(base), data, max_nfev=30)
    as_is = rank.fit(truth, [], data)
    refit = rank.fit(truth, keys, data, max_nfev=30)

    def fig(f):
        return {"cost": f.cost_fit, "held_out_nrmse": f.nrmse_held,
                "stages": {k: round(v, 6) for k, v in f.nrmse.items()}}
    return {"index": i, "effect": d["effect"], "protocol": d["protocol"], "burn_in_s": cut,
            "given": fig(given), "null": fig(null), "truth": fig(as_is), "truth_refit": fig(refit),
            "truth_extras": truth.extras, "refit_extras": refit.model.extras,
            "truth_law": [truth.baseline.alpha_m, truth.baseline.gamma, truth.baseline.delta],
            "refit_law": [refit.model.baseline.alpha_m, refit.model.baseline.gamma, refit.model.baseline.delta],
            "noise_nrmse": {s.name: s.noise / s.rms for s in data}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, nargs="+", required=True)
    ap.add_argument("--burn-in", type=float, default=None, metavar="D",
                    help="leave the resonance search's first D decay times out of the fit")
    ap.add_argument("--jsonl", default=None, help="appended to, one line per row")
    a = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    print(f"{'row':>5} {'protocol':9} {'effect':20} {'truth cost':>11} {'held':>9}  {'refit cost':>11} {'held':>9}")
    for i in a.rows:
        r = truth_refit(i, a.burn_in)
        if a.jsonl:
            with open(a.jsonl, "a") as f:
                print(json.dumps(r), file=f)
        if "skipped" in r:
            print(f"{i:5d} {r['effect']}: {r['skipped']}")
            continue
        t, f = r["truth"], r["truth_refit"]
        print(f"{i:5d} {r['protocol']:9} {r['effect']:20} {t['cost']:11.4g} {t['held_out_nrmse']:9.3g}  "
              f"{f['cost']:11.4g} {f['held_out_nrmse']:9.3g}", flush=True)
        print(f"      truth per stage {t['stages']}\n      refit per stage {f['stages']}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

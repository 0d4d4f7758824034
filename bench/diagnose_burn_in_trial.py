"""A trial of the burn-in at other settings: the whole diagnosis of chosen stress rows with every
fitting stage recorded in motion leaving its first D decay times out of the fit (main: D = 3).

    python bench/diagnose_burn_in_trial.py --rows 641 315 [--decays 3] [--jsonl out.jsonl]

D decay times of the baseline's mode are D / (zeta w_n) = 2 D / c (c per unit mass); a stage keeps
its cut only if at least 30 % of its fitting samples remain (recon.diagnosis.rank.burn_in, with
BURN_IN_DECAYS set to D for the run; --every-baseline cuts baselines without hysteresis too).
Everything else is the diagnosis as it stands. Why:
docs/diagnosis.md, 2026-12-01a (the rig protocol's resonance search starts with a hysteresis state
the fits' start does not know).
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from diagnose_stress import draw, recording  # noqa: E402
from independent_run import to_run  # noqa: E402

from recon.diagnosis import diagnose as D  # noqa: E402
from recon.diagnosis import rank  # noqa: E402

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, nargs="+", required=True)
    ap.add_argument("--decays", type=float, default=3.0)
    ap.add_argument("--every-baseline", action="store_true",
                    help="cut baselines without hysteresis too (as the 2026-12-01a/b trial runs did)")
    ap.add_argument("--jsonl", default=None, help="appended to, one line per row")
    a = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    rank.BURN_IN_DECAYS = a.decays
    if a.every_baseline:
        rank.burn_in = functools.partial(rank.burn_in, hysteresis_only=False)
    for i in a.rows:
        t0 = time.time()
        d = draw(i)
        run = to_run(recording(d))
        dg = D.diagnose(run, baseline="paper").to_dict()
        named = [m["id"] for m in dg["missing_physics"]]
        row = {"index": i, "effect": d["effect"], "protocol": d["protocol"], "decays": a.decays,
               "every_baseline": a.every_baseline, "named": named,
               "right": (named[:1] == [d["effect"]]) if d["effect"] != "none" else not named,
               "held_out": {"as_given": dg["fit_before"]["held_out_nrmse"],
                            "null": dg["fit_before"]["refit_held_out_nrmse"],
                            "after": dg["fit_after"].get("held_out_nrmse")},
               "seconds": time.time() - t0}
        if a.jsonl:
            with open(a.jsonl, "a") as f:
                print(json.dumps(row), file=f)
        print(f"#{i} {d['protocol']} {d['effect']}: named {named} ({'right' if row['right'] else 'miss'}); held-out "
              f"{row['held_out']['as_given']:.3g} as given, {row['held_out']['null']:.3g} refit, "
              f"{row['held_out']['after']:.3g} after", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

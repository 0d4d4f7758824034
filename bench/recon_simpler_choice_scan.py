"""`python bench/recon_simpler_choice_scan.py OUT.jsonl I [I ...]`: where reconstruct's choice of a
simpler model over an inadequate full model (recon.estimator.pipeline._prefer_simpler) differs
between the held-out stages alone (SIMPLER_GAIN, the rule until 2026-12-04) and the rule with the
nonlinear stage's fit (SIMPLER_FIT_SLACK, 2026-12-04), on diagnosis-stress recordings I.

Each row is reconstructed as `shakerlab diagnose` builds its paper baseline: from its fitting part,
and, where that model does not simulate a stage of the whole run (diagnose then reconstructs from
the whole run), from the whole run too. Both choices are read off the figures the result keeps
(`adequacy.fallback` or `adequacy.simpler_models_compared`): the kind the held-out NRMSE alone would
take, and the kind taken. The new rule only removes kinds from the choice, so a row where the old
rule takes no simpler model is unchanged. Rows whose baseline is the truth without a term are not
reconstructed (skipped)."""
from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from row_scan import baseline_row, scan_rows  # noqa: E402

from recon.estimator.pipeline import SIMPLER_GAIN  # noqa: E402


def choices(res) -> dict:
    """The simpler kind the held-out NRMSE alone would take (``held_out_alone``) and the kind taken
    (``taken``; None: the full model) by ``_prefer_simpler``."""
    a = res.adequacy
    fb = a.get("fallback") or {}
    if fb.get("used") and fb.get("trigger") != "inadequate":
        return {"trigger": fb.get("trigger"), "taken": fb.get("kind"), "held_out_alone": fb.get("kind")}
    cmp_ = fb if fb.get("used") else a.get("simpler_models_compared")
    if not cmp_:
        return {"trigger": None, "taken": None, "held_out_alone": None}
    full = cmp_["full_model_held_out_nrmse"]
    good = [c for c in cmp_["candidates"] if "equation" in c and math.isfinite(c["held_out_nrmse"])]
    best = min(good, key=lambda c: c["held_out_nrmse"]) if good else None
    old = best["kind"] if best is not None and best["held_out_nrmse"] < SIMPLER_GAIN * full else None
    return {"trigger": "inadequate" if fb.get("used") else "compared", "taken": fb.get("kind") if fb.get("used")
            else None, "held_out_alone": old, "full_model_held_out_nrmse": full,
            "full_model_nonlinear_stage_nrmse": cmp_.get("full_model_nonlinear_stage_nrmse"),
            "candidates": {c["kind"]: [c["held_out_nrmse"], c.get("nonlinear_stage_nrmse")] for c in good}}


def row(i: int) -> dict:
    out = baseline_row(i, choices)
    if "error" not in out and "skipped" not in out:
        out["changed"] = any(out[k]["taken"] != out[k]["held_out_alone"]
                             for k in ("fitting_part", "whole_run") if k in out)
    return out


def describe(r: dict) -> str:
    fp = r.get("fitting_part") or {}
    whole = r.get("whole_run")
    return (r.get("error") or r.get("skipped")
            or f"{fp.get('trigger')}: taken {fp.get('taken')}, held-out alone {fp.get('held_out_alone')}"
            + (f" (whole run: {whole['taken']} / {whole['held_out_alone']})" if whole else ""))


def main(argv: list[str]) -> int:
    rows = scan_rows(argv, __doc__, row, describe)
    changed = [r["index"] for r in rows if r.get("changed")]
    print(f"the choice differs from the held-out rule alone on {len(changed)} of {len(rows)} rows"
          + (f" (#{', #'.join(map(str, changed))})" if changed else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

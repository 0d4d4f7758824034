"""`python bench/recon_elastic_start_scan.py OUT.jsonl I [I ...]`: the diagnosis-stress rows whose
paper baseline the elastic kind's second start can change (recon.estimator.fallback.simpler_models,
2026-12-04: from y^2 = y^3 = 0 as well as from the inadmissible estimate's values).

Each row is reconstructed as `shakerlab diagnose` builds its paper baseline: from its fitting part,
and, where that model does not simulate a stage of the whole run (diagnose then reconstructs from
the whole run), from the whole run too. The simpler kinds' fits are read off the result
(`adequacy.fallback` or `adequacy.simpler_models_compared`). Where the elastic fit came from its
estimate start, or had one start (no `start` key: the estimate gave y^2 = y^3 = 0), the second
start changed nothing (of two starts the better fit is kept, the first on a tie): the
reconstruction, and so the diagnosis, is the one the code before gave. A row is `may_change` only where the elastic kind's fit came from the new
zero start; those rows are diagnosed again. Rows whose baseline is the truth without a term are not
reconstructed (skipped)."""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from row_scan import baseline_row, scan_rows  # noqa: E402



def elastic_fit(res) -> dict:
    """How reconstruct's result ``res`` used the simpler kinds: ``trigger`` (None: the full model was
    adequate and no simpler kind was fitted), the kind ``taken`` (None: the full model), the
    elastic fit's ``start`` and figures, and the answer's ``equation``."""
    a = res.adequacy
    fb = a.get("fallback") or {}
    cmp_ = fb if fb.get("used") else a.get("simpler_models_compared")
    if not cmp_:
        return {"trigger": None, "taken": None, "elastic_start": None, "equation": res.model.equation()}
    el = next((c for c in cmp_.get("candidates", []) if c["kind"] == "elastic"), {})
    return {"trigger": fb.get("trigger") if fb.get("used") else "compared",
            "taken": fb.get("kind") if fb.get("used") else None,
            "elastic_start": el.get("start"), "elastic_fitted_nrmse": el.get("fitted_nrmse"),
            "elastic_held_out_nrmse": el.get("held_out_nrmse"), "equation": res.model.equation()}


def row(i: int) -> dict:
    out = baseline_row(i, elastic_fit)
    if "error" in out:
        out["may_change"] = True    # not known: diagnosed again
    elif "skipped" not in out:
        out["may_change"] = any(out[k]["elastic_start"] == "zero" for k in ("fitting_part", "whole_run")
                                if k in out)
    return out


def describe(r: dict) -> str:
    fp = r.get("fitting_part") or {}
    whole = r.get("whole_run")
    text = (r.get("error") or r.get("skipped")
            or f"{fp.get('trigger')}: taken {fp.get('taken')}, elastic from {fp.get('elastic_start')}"
            + (f" (whole run: {whole['taken']}, elastic from {whole.get('elastic_start')})" if whole else ""))
    return text + (" -> may change" if r.get("may_change") else "")


def main(argv: list[str]) -> int:
    rows = scan_rows(argv, __doc__, row, describe)
    changed = [r["index"] for r in rows if r.get("may_change")]
    print(f"the elastic kind's zero start won on {len(changed)} of {len(rows)} rows"
          + (f" (#{', #'.join(map(str, changed))})" if changed else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

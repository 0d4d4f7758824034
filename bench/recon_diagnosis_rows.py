"""`python bench/recon_diagnosis_rows.py OUT.jsonl I [I ...]`: reconstruct on the fitting part of
diagnosis-stress recordings I (bench/diagnose_stress.py draws them from the index alone), as
`shakerlab diagnose` reconstructs its paper baseline; one JSON row per recording (verdict, validation
NRMSE, noise floor, the fallback used, the fitted input offset and, for an offset record, the true
one, and whether the term revision dropped a vanished Bouc-Wen law), then a table. Run it on two checkouts to compare reconstruct versions on the same records
(docs/diagnosis.md, 2026-11-28c: the offset rows)."""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from diagnose_stress import draw, recording  # noqa: E402
from row_scan import scan_rows  # noqa: E402
from independent_run import to_run  # noqa: E402

from recon import reconstruct  # noqa: E402
from recon.diagnosis import rank  # noqa: E402


def row(i: int) -> dict:
    d = draw(i)
    rec = recording(d)
    out = {"index": i, "effect": d["effect"], "protocol": d["protocol"]}
    if d["effect"] == "offset":
        out["b_true"] = -rec["effect_parameters"]["F0"] / d["system"]["m"]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = reconstruct(rank.fitting_part(to_run(rec)))
    except Exception as exc:  # noqa: BLE001 - a failed reconstruct is a row
        return {**out, "error": f"{type(exc).__name__}: {exc}"[:300]}
    m = res.model
    return {**out, "verdict": res.adequacy["verdict"], "validation_nrmse": res.adequacy["validation_nrmse"],
            "noise_floor_nrmse": res.adequacy.get("noise_floor_nrmse"),
            "simpler_model": m.provenance.get("simpler_model"), "input_offset": m.input_offset,
            # reconstruct's term revision dropped a Bouc-Wen law that had vanished (2026-12-03)
            "vanished_hysteresis": (m.provenance.get("term_selection") or {}).get("vanished_hysteresis"),
            "equation": m.equation()}


def main(argv: list[str]) -> int:
    rows = scan_rows(argv, __doc__, row)
    print(f"{'#':>5} {'verdict':>11} {'val NRMSE':>10} {'floor':>8} {'fallback':>22} {'b':>9} {'b true':>9}")
    for r in rows:
        if "error" in r:
            print(f"{r['index']:>5} {'error':>11} {r['error'][:60]}")
            continue
        f = lambda v: f"{v:.4g}" if isinstance(v, float) else "-"  # noqa: E731
        print(f"{r['index']:>5} {r['verdict']:>11} {r['validation_nrmse']:>10.4f} {f(r['noise_floor_nrmse']):>8} "
              f"{str(r['simpler_model'] or '-'):>22} {f(r['input_offset']):>9} {f(r.get('b_true')):>9}")
    ok = sum(r.get("verdict") == "adequate" for r in rows)
    print(f"adequate: {ok} of {len(rows)}")
    dropped = [r["index"] for r in rows if (r.get("vanished_hysteresis") or {}).get("applied")]
    print(f"a vanished Bouc-Wen law dropped by the term revision: {len(dropped)} of {len(rows)}"
          + (f" (#{', #'.join(map(str, dropped))})" if dropped else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

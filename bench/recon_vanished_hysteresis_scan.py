"""`python bench/recon_vanished_hysteresis_scan.py OUT.jsonl I [I ...]`: where reconstruct's step for
a vanished Bouc-Wen law (recon.estimator.pipeline._without_vanished_hysteresis, 2026-12-03) is
reached and where it changes the model, on diagnosis-stress recordings I.

Each row is reconstructed from its fitting part, as `shakerlab diagnose` builds its paper
baseline, with the step wrapped so that every call is logged (the law's share of the elastic
force, whether the law was dropped). A row on which the step is never applied reconstructs, and
so diagnoses, exactly as before the step existed. The wrapper sees the step even where a later
fallback replaces the model's provenance, which bench/recon_diagnosis_rows.py reads. Rows whose
baseline is the truth without a term are not reconstructed (skipped)."""
from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import recon.estimator.pipeline as pipeline  # noqa: E402
from diagnose_stress import draw, recording  # noqa: E402
from independent_run import to_run  # noqa: E402
from row_scan import scan_rows  # noqa: E402
from recon.diagnosis import rank  # noqa: E402


def row(i: int) -> dict:
    calls = []
    step = pipeline._without_vanished_hysteresis

    def logged(model, data, info):
        out = step(model, data, info)
        calls.append(dict(info.get("vanished_hysteresis", {}), alpha=model.alpha_m, fn=dict(model.fn_m)))
        return out

    d = draw(i)
    out = {"index": i, "effect": d["effect"], "protocol": d["protocol"], "alpha_true": d["system"]["alpha"]}
    t0 = time.perf_counter()
    pipeline._without_vanished_hysteresis = logged
    try:
        rec = recording(d)
        if "baseline" in rec:
            out["skipped"] = "baseline is the truth without a term (no reconstruct)"
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = pipeline.reconstruct(rank.fitting_part(to_run(rec)))
            out.update(calls=calls, applied=any(c.get("applied") for c in calls),
                       validation=res.adequacy.get("validation_nrmse"), fn=res.model.fn_m,
                       alpha=res.model.alpha_m)
    except Exception as exc:  # noqa: BLE001 - a failed reconstruct is a row
        out["error"] = f"{type(exc).__name__}: {exc}"[:300]
    finally:
        pipeline._without_vanished_hysteresis = step
    out["seconds"] = time.perf_counter() - t0
    return out


def main(argv: list[str]) -> int:
    rows = scan_rows(argv, __doc__, row, lambda r: r.get("error") or r.get("skipped")
                     or f"step reached {len(r['calls'])}x, applied {r['applied']}")
    applied = [r["index"] for r in rows if r.get("applied")]
    reached = [r["index"] for r in rows if r.get("calls")]
    print(f"step reached on {len(reached)} of {len(rows)} rows, applied on {len(applied)}"
          + (f" (#{', #'.join(map(str, applied))})" if applied else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

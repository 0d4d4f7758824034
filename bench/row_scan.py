"""The loop the per-row stress scans share (recon_diagnosis_rows.py, recon_vanished_hysteresis_scan.py,
recon_simpler_choice_scan.py, recon_elastic_start_scan.py): `SCRIPT OUT.jsonl I [I ...]`, one JSON row
per stress recording I, written to a new file as each row is done; and the paper-baseline
reconstruct the last two scan (:func:`baseline_row`, its imports there: the other scans do not need
them)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable


def scan_rows(argv: list[str], usage: str, row: Callable[[int], dict],
              describe: Callable[[dict], str] | None = None) -> list[dict]:
    """``row(i)`` for every index in ``argv[1:]``, each written to the new file ``argv[0]`` (never
    overwritten) and flushed as it comes; ``describe(r)``, if given, is printed per row. Exits with
    ``usage`` when the arguments are missing."""
    if len(argv) < 2:
        raise SystemExit(usage)
    path = Path(argv[0])
    try:
        f = path.open("x")
    except FileExistsError:
        raise SystemExit(f"{path} exists; name a new file (saved rows are never overwritten)")
    rows = []
    with f:
        for i in (int(a) for a in argv[1:]):
            r = row(i)
            rows.append(r)
            f.write(json.dumps(r, default=float) + "\n")
            f.flush()
            if describe is not None:
                print(f"#{i}: " + describe(r), flush=True)
    return rows


def baseline_row(i: int, summarise: Callable) -> dict:
    """Stress recording ``i`` reconstructed as `shakerlab diagnose` builds its paper baseline: from its
    fitting part (``fitting_part``: ``summarise(result)``), and, where that model does not simulate a
    stage of the whole run (diagnose then reconstructs from the whole run), from the whole run too
    (``whole_run``). Rows whose baseline is the truth without a term are ``skipped``; a failure is the
    row's ``error``."""
    import time
    import warnings

    import numpy as np
    from diagnose_stress import draw, recording
    from independent_run import to_run

    from recon.diagnosis import rank
    from recon.estimator.fallback import score
    from recon.estimator.pipeline import reconstruct

    d = draw(i)
    out = {"index": i, "effect": d["effect"], "protocol": d["protocol"]}
    t0 = time.perf_counter()
    try:
        rec = recording(d)
        if "baseline" in rec:
            out["skipped"] = "baseline is the truth without a term (no reconstruct)"
        else:
            whole = to_run(rec)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = reconstruct(rank.fitting_part(whole))
                out["fitting_part"] = summarise(res)
                if rank.uncovered_stages(whole) and not all(np.isfinite(score(res.model, whole, [n]))
                                                            for n in whole.stages):
                    out["whole_run"] = summarise(reconstruct(whole))
    except Exception as exc:  # noqa: BLE001 - a failed reconstruct is a row
        out["error"] = f"{type(exc).__name__}: {exc}"[:300]
    out["seconds"] = time.perf_counter() - t0
    return out

"""The loop the per-row stress scans share (recon_diagnosis_rows.py, recon_vanished_hysteresis_scan.py,
recon_simpler_choice_scan.py): `SCRIPT OUT.jsonl I [I ...]`, one JSON row per stress recording I,
written to a new file as each row is done."""
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

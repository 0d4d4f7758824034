"""Helpers shared by the tests and a bench script that only need numpy: nothing here is part of
the application. bench/csv_import_memory.py imports :func:`write_csv` from here (one copy)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_csv(path: Path, rows: int) -> None:
    """A base-excitation CSV of ``rows`` samples at 10 kHz, written in blocks (t to 10 significant
    digits, as an exporter writes it): the large file of the import-memory check."""
    t = np.arange(rows) / 10000.0
    with open(path, "w") as fh:
        fh.write("t,x_base,x_tip\n")
        for i in range(0, rows, 100_000):
            j = min(i + 100_000, rows)
            block = np.column_stack([t[i:j], 1e-3 * np.sin(t[i:j]), 2e-3 * np.sin(t[i:j])])
            np.savetxt(fh, block, delimiter=",", fmt=["%.10g", "%.9e", "%.9e"])

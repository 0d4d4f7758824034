"""Helpers shared by the tests and a bench script that only need numpy: nothing here is part of
the application. bench/csv_import_memory.py imports :func:`write_csv` from here (one copy); the
weak-form checks at 40 dB are shared by test_recon_weak_path.py and test_recon_cli.py (one record is
fitted once, through the CLI, and checked the same way as the others)."""
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


WEAK_CORE = ("c_m", "k_m", "alpha_m", "gamma", "delta")


def check_weak_form_at_40db(params: dict, path_rows: int, truth) -> None:
    """The issue's aim: at 40 dB SNR the weak form (path rows, then output-error polish and term
    selection) gives the exact pattern, the Bouc-Wen parameters within 5 % and the fn coefficients
    within 10 % (8 seeds in bench/recon_accuracy.py: core <= 2.3 %, fn <= 7.9 %). ``params``: the
    model JSON's "parameters"."""
    assert set(params["fn_m"]) == set(truth.fn_m)
    for k in WEAK_CORE:
        assert abs(params[k] / getattr(truth, k) - 1) < 0.05, (k, params[k])
    for k, v in truth.fn_m.items():
        assert abs(params["fn_m"][k] / v - 1) < 0.10, (k, params["fn_m"][k])
    assert path_rows > 500

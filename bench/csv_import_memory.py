"""Peak memory of `shakerlab import` on a large CSV, against the size of the file.

    python bench/csv_import_memory.py [ROWS]      # default 5 000 000 rows (about 220 MB)

Writes the CSV in a temporary directory (t printed to 10 significant digits, as an exporter
does), imports it (shakerlab.import_command.import_csv) under tracemalloc and prints the
file size, the peak of Python-allocated memory (numpy arrays included) and their ratio.
"""
from __future__ import annotations

import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import write_csv  # noqa: E402  (tests/helpers.py: the same file the import-memory test reads)


def measure(rows: int) -> dict:
    from shakerlab.import_command import import_csv

    with tempfile.TemporaryDirectory() as d:
        csv = Path(d) / "big.csv"
        write_csv(csv, rows)
        size = csv.stat().st_size
        tracemalloc.start()
        t0 = time.perf_counter()
        import_csv(Path(d) / "big.h5", {"linear": csv})
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return {"rows": rows, "file_bytes": size, "peak_bytes": peak, "ratio": peak / size, "seconds": seconds}


if __name__ == "__main__":
    r = measure(int(sys.argv[1]) if len(sys.argv) > 1 else 5_000_000)
    print(f"{r['rows']} rows, file {r['file_bytes'] / 1e6:.1f} MB: peak {r['peak_bytes'] / 1e6:.1f} MB "
          f"({r['ratio']:.2f} x the file), {r['seconds']:.1f} s")

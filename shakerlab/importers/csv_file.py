"""The shakerlab CSV: one file per stage, a header line naming the channels.

Headers: ``t,x_base|v_base|a_base,x_tip|v_tip|a_tip`` (base excitation) or
``t,force,x|v|a`` (force excitation), SI units (s, m, m/s, m/s^2, N). With a channel mapping
(``--map``) any header is read and its columns are channels by name. ``#`` lines and blank
lines are skipped; every bad value is reported with its file, line and column.
"""
from __future__ import annotations

import bz2
import gzip
import lzma
from pathlib import Path

import numpy as np

from shakerlab.errors import UserFacingError
from shakerlab.importers.signal import Signal
from shakerlab.quantities import PREFIX

MOTION = tuple(PREFIX.values())
HEADERS = {("t", f"{b}_base", f"{p}_tip"): "base" for b in MOTION for p in MOTION}
HEADERS.update({("t", "force", m): "force" for m in MOTION})
EXPECTED = "'t,x_base,x_tip' (base excitation) or 't,force,x' (force excitation); v_ or a_ for velocity or acceleration"


def printed_quantum(field: str) -> float:
    """The place value of the last printed digit of a number as written ('1.2345e-3' -> 1e-7)."""
    mant, _, exp = field.lower().partition("e")
    decimals = len(mant.partition(".")[2])
    try:
        e = int(exp) if exp else 0
    except ValueError:
        e = 0
    return 10.0 ** (e - decimals)


# a CSV compressed whole (``run.csv.gz``) is read through its decompressor, streamed
COMPRESSED = {".gz": gzip.open, ".bz2": bz2.open, ".xz": lzma.open}


def data_suffix(path) -> str:
    """The suffix that names the format, past a compression suffix: ".csv" for "a.csv.gz"."""
    suffixes = [x.lower() for x in Path(path).suffixes]
    if len(suffixes) >= 2 and suffixes[-1] in COMPRESSED:
        return suffixes[-2]
    return Path(path).suffix.lower()


def _lines(path: Path):
    """(line number, stripped line) of every non-blank, non-comment line, streamed from the file."""
    opener = COMPRESSED.get(Path(path).suffix.lower(), open)
    try:
        with opener(path, "rt", encoding="utf-8-sig", newline=None) as fh:
            for lineno, line in enumerate(fh, start=1):
                stripped = line.strip()
                if stripped and not stripped.startswith("#"):
                    yield lineno, stripped
    except FileNotFoundError:
        raise UserFacingError(f"{path}: no such file") from None
    except (OSError, EOFError, lzma.LZMAError, UnicodeDecodeError) as exc:
        raise UserFacingError(f"{path}: cannot read as a text CSV file ({exc})") from None


def parse(path: str | Path, any_header: bool = False):
    """(header, data rows as an array, line numbers, time quanta) of a CSV file.

    Streamed in two passes (count the rows, then fill preallocated arrays): the memory used is the
    arrays returned (8 bytes per value, 12 per row for the line number and time quantum), never a
    copy of the text or a list per row."""
    path = Path(path)
    header = None
    n_rows = -1
    for lineno, stripped in _lines(path):
        if header is None:
            header = _header(path, lineno, stripped, any_header)
        n_rows += 1
    if header is None:
        raise UserFacingError(f"{path}: empty file (expected a header {EXPECTED})")
    if n_rows < 2:
        raise UserFacingError(f"{path}: needs at least 2 data lines, found {n_rows}")
    ncol = len(header)
    data = np.empty((n_rows, ncol), dtype=float)
    linenos = np.empty(n_rows, dtype=np.int32 if n_rows < 2**31 else np.int64)
    quanta = np.empty(n_rows, dtype=np.float32)
    timed = header[0].lower() == "t"
    k = -1
    for lineno, stripped in _lines(path):
        if k < 0:
            k = 0
            continue
        if k >= n_rows:
            raise UserFacingError(f"{path}: the file grew while it was read (line {lineno}); import a finished file")
        fields = stripped.split(",")
        if len(fields) != ncol:
            raise UserFacingError(
                f"{path}: line {lineno}: {len(fields)} column(s), the header has {ncol} ({','.join(header)})"
            )
        row = data[k]
        for col, field in enumerate(fields):
            field = field.strip()
            try:
                value = float(field)
            except ValueError:
                raise UserFacingError(
                    f"{path}: line {lineno}, column {col + 1} ({header[col]}): {field!r} is not a number"
                ) from None
            if value - value != 0.0:        # inf or nan
                raise UserFacingError(f"{path}: line {lineno}, column {col + 1} ({header[col]}): value {field!r} "
                                      f"is not finite")
            row[col] = value
        if timed and k and row[0] <= data[k - 1, 0]:
            raise UserFacingError(
                f"{path}: line {lineno}, column 1 (t): time {fields[0].strip()} does not increase "
                f"(previous {float(data[k - 1, 0])!r})"
            )
        linenos[k] = lineno
        quanta[k] = printed_quantum(fields[0].strip())
        k += 1
    if k != n_rows:
        raise UserFacingError(f"{path}: the file changed while it was read ({k} data lines, {n_rows} counted)")
    return header, data, linenos, quanta


def _header(path: Path, lineno: int, stripped: str, any_header: bool) -> tuple:
    fields = [f.strip() for f in stripped.split(",")]
    header = tuple(f.lower() for f in fields) if not any_header else tuple(fields)
    if not any_header and header not in HEADERS:
        raise UserFacingError(f"{path}: line {lineno}: header is {stripped!r}; expected {EXPECTED}")
    if any_header and len(set(header)) != len(header):
        raise UserFacingError(f"{path}: line {lineno}: the header names a column twice ({stripped!r})")
    return header


def read_signals(path: str | Path, time_column: str | None = "t") -> list[Signal]:
    """Every column of a CSV with any header as a Signal; ``time_column`` (None: no time
    column, the rate comes from --fs) gives their time base."""
    header, data, lines, quanta = parse(path, any_header=True)
    src = str(path)
    time = None
    if time_column is not None:
        if time_column not in header:
            raise UserFacingError(f"{path}: no time column {time_column!r} (columns: {', '.join(header)}); "
                                  f"map it with --map t=NAME or give --fs")
        time = data[:, header.index(time_column)]
        steps = np.diff(time)
        if np.any(steps <= 0):
            k = int(np.flatnonzero(steps <= 0)[0]) + 1
            raise UserFacingError(f"{path}: line {lines[k]}: time {time[k]!r} does not increase (previous {time[k - 1]!r})")
    return [Signal(name=h, values=data[:, i], source=src, time=time, quantum=quanta, lines=lines)
            for i, h in enumerate(header) if h != time_column]

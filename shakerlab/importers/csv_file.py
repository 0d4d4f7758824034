"""The shakerlab CSV: one file per stage, a header line naming the channels.

Headers: ``t,x_base|v_base|a_base,x_tip|v_tip|a_tip`` (base excitation) or
``t,force,x|v|a`` (force excitation), SI units (s, m, m/s, m/s^2, N). With a channel mapping
(``--map``) any header is read and its columns are channels by name. ``#`` lines and blank
lines are skipped; every bad value is reported with its file, line and column.
"""
from __future__ import annotations

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


def parse(path: str | Path, any_header: bool = False):
    """(header, data rows as an array, line numbers, time quanta) of a CSV file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise UserFacingError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserFacingError(f"{path}: cannot read as a text CSV file ({exc})") from None
    header = None
    rows: list[list[float]] = []
    linenos: list[int] = []
    quanta: list[float] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [f.strip() for f in stripped.split(",")]
        if header is None:
            header = tuple(f.lower() for f in fields) if not any_header else tuple(fields)
            if not any_header and header not in HEADERS:
                raise UserFacingError(f"{path}: line {lineno}: header is {stripped!r}; expected {EXPECTED}")
            if any_header and len(set(header)) != len(header):
                raise UserFacingError(f"{path}: line {lineno}: the header names a column twice ({stripped!r})")
            continue
        if len(fields) != len(header):
            raise UserFacingError(
                f"{path}: line {lineno}: {len(fields)} column(s), the header has {len(header)} ({','.join(header)})"
            )
        row = []
        for col, (name, field) in enumerate(zip(header, fields), start=1):
            try:
                value = float(field)
            except ValueError:
                raise UserFacingError(
                    f"{path}: line {lineno}, column {col} ({name}): {field!r} is not a number"
                ) from None
            if not np.isfinite(value):
                raise UserFacingError(f"{path}: line {lineno}, column {col} ({name}): value {field!r} is not finite")
            row.append(value)
        if header[0].lower() == "t" and rows and row[0] <= rows[-1][0]:
            raise UserFacingError(
                f"{path}: line {lineno}, column 1 (t): time {fields[0]} does not increase "
                f"(previous {rows[-1][0]!r})"
            )
        rows.append(row)
        linenos.append(lineno)
        quanta.append(printed_quantum(fields[0]))
    if header is None:
        raise UserFacingError(f"{path}: empty file (expected a header {EXPECTED})")
    if len(rows) < 2:
        raise UserFacingError(f"{path}: needs at least 2 data lines, found {len(rows)}")
    return header, np.asarray(rows, dtype=float), np.asarray(linenos), np.asarray(quanta)


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

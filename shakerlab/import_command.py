"""``shakerlab import``: turn recordings from other systems into a shakerlab run file.

One CSV file per stage with a header line, either ``t,x_base,x_tip`` (base
excitation, SI units: s, m, m) or ``t,force,x`` (force excitation: s, N, m).
Lines starting with ``#`` and blank lines are skipped. Every bad value is
reported with its file, line and column.

``shakerlab import --recover CRASHED.h5 -o COPY.h5`` copies an interrupted run
file into a new, cleanly closed one (see ``shakerlab.runfile.results.recover_copy``);
the input is never modified, and ``-o`` may not name it, even with ``--force``.
The output is written through a temporary file under the output lock
(``shakerlab.output_files``): an existing file is replaced only when the new one is
complete, and never while another shakerlab process writes it.
"""
from __future__ import annotations

from pathlib import Path

STAGE_OPTIONS = ("linear", "nonlinear", "validation")
HEADERS = {("t", "x_base", "x_tip"): "base", ("t", "force", "x"): "force"}


def register(subparsers) -> None:
    """Add ``import`` to the ``shakerlab`` parser."""
    p = subparsers.add_parser(
        "import",
        help="convert CSV recordings (one file per stage) into a shakerlab run file",
        description="Convert CSV recordings into a shakerlab HDF5 run file. Each CSV has a header "
        "'t,x_base,x_tip' (base excitation, SI units) or 't,force,x' (force excitation).",
    )
    p.add_argument("-o", "--output", required=True, type=Path, help="run file to write (.h5)")
    for stage in STAGE_OPTIONS:
        p.add_argument(f"--{stage}", type=Path, metavar="CSV", help=f"CSV file of the {stage} stage")
    p.add_argument("--recover", type=Path, metavar="RUN.h5",
                   help="instead: copy an interrupted run file into a cleanly closed one")
    p.add_argument("--force", action="store_true", help="overwrite the output file")
    p.set_defaults(handler=_handle)


def read_csv(path: str | Path):
    """Parse one stage CSV; return (excitation, {column: float array}).

    Raises UserFacingError naming the file, line and column of the first bad value.
    """
    import numpy as np  # heavy: numpy, h5py; loaded when the command runs

    from shakerlab.errors import UserFacingError  # heavy: numpy, h5py; loaded when the command runs

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise UserFacingError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserFacingError(f"{path}: cannot read as a text CSV file ({exc})") from None
    lines = text.splitlines()
    header = None
    rows: list[list[float]] = []
    for lineno, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [f.strip() for f in stripped.split(",")]
        if header is None:
            header = tuple(f.lower() for f in fields)
            if header not in HEADERS:
                raise UserFacingError(
                    f"{path}: line {lineno}: header is {stripped!r}; expected 't,x_base,x_tip' "
                    f"(base excitation) or 't,force,x' (force excitation)"
                )
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
        if rows and row[0] <= rows[-1][0]:
            raise UserFacingError(
                f"{path}: line {lineno}, column 1 (t): time {fields[0]} does not increase "
                f"(previous {rows[-1][0]!r})"
            )
        rows.append(row)
    if header is None:
        raise UserFacingError(f"{path}: empty file (expected a header 't,x_base,x_tip' or 't,force,x')")
    if len(rows) < 2:
        raise UserFacingError(f"{path}: needs at least 2 data lines, found {len(rows)}")
    data = np.asarray(rows, dtype=float)
    return HEADERS[header], {name: data[:, i] for i, name in enumerate(header)}


def import_csv(output: str | Path, stage_files: dict[str, str | Path], *, overwrite: bool = False) -> Path:
    """Write a run file from ``{stage name: CSV path}``; return the output path."""
    import numpy as np  # heavy: numpy, h5py; loaded when the command runs

    from shakerlab.errors import UserFacingError  # heavy: numpy, h5py; loaded when the command runs
    from shakerlab.runfile.writer import RunWriter  # heavy: numpy, h5py; loaded when the command runs

    if not stage_files:
        raise UserFacingError("nothing to import: give at least one of --linear, --nonlinear, --validation")
    parsed = {}
    for stage, csv_path in stage_files.items():
        parsed[stage] = (csv_path, *read_csv(csv_path))
    kinds = {kind for _, kind, _ in parsed.values()}
    if len(kinds) > 1:
        desc = ", ".join(f"{p} is {k} excitation" for p, k, _ in parsed.values())
        raise UserFacingError(f"the stage files mix excitation kinds ({desc}); one run has one kind")
    output = Path(output)
    with RunWriter(output, overwrite=overwrite, attrs={"source": "import"}) as writer:
        writer.log("info", f"imported with shakerlab import from {len(parsed)} CSV file(s)")
        for stage, (csv_path, kind, cols) in parsed.items():
            t = cols["t"]
            dt = np.diff(t)
            fs = 1.0 / float(np.median(dt))
            jitter = float(np.max(np.abs(dt - np.median(dt))) / np.median(dt))
            settings = {"source_file": str(Path(csv_path).resolve()), "source_t0": float(t[0]),
                        "sampling_jitter": jitter}
            sw = writer.begin_stage(stage, fs=fs, excitation=kind, settings=settings)
            channels = [c for c in cols if c != "t"]
            sw.append(0, {c: cols[c] for c in channels}, time_s=t - t[0])
            sw.close("complete", summary={"n_samples": int(t.size), "duration_s": float(t[-1] - t[0])})
            writer.log("info", f"stage {stage!r}: {t.size} samples from {csv_path} ({kind} excitation, "
                               f"fs {fs:.6g} Hz)")
    return output


def _handle(args) -> int:
    from shakerlab.errors import UserFacingError  # heavy: numpy, h5py; loaded when the command runs
    from shakerlab.runfile.reader import read_info  # heavy: numpy, h5py; loaded when the command runs
    from shakerlab.runfile.results import recover_copy  # heavy: numpy, h5py; loaded when the command runs

    if args.recover is not None:
        if any(getattr(args, s) for s in STAGE_OPTIONS):
            raise UserFacingError("--recover copies a run file; do not combine it with --linear/--nonlinear/--validation")
        recover_copy(args.recover, args.output, overwrite=args.force)
        print(f"wrote {args.output} (clean copy of {args.recover})")
        return 0
    files = {s: getattr(args, s) for s in STAGE_OPTIONS if getattr(args, s) is not None}
    out = import_csv(args.output, files, overwrite=args.force)
    info = read_info(out)
    for name, st in info["stages"].items():
        print(f"{name}: {st['n_samples']} samples at {st['fs']:.6g} Hz")
    print(f"wrote {out}")
    return 0

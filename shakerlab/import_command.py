"""``shakerlab import``: turn recordings from other systems into a shakerlab run file.

One CSV file per stage with a header line, either ``t,x_base,x_tip`` (base
excitation, SI units: s, m, m) or ``t,force,x`` (force excitation: s, N, m); a motion
column may be velocity or acceleration (``v_tip``, ``a_base``, ``v`` ...). Lines starting
with ``#`` and blank lines are skipped. Every bad value is reported with its file, line and
column. Lab formats (LMS Test.Lab .mat, NI .tdms, UFF .uff/.unv) and CSVs with other
headers are read through a channel map (``--map ROLE=CHANNEL[:QUANTITY]``); readers in
``shakerlab/importers/``. The time base is checked (``shakerlab.importers.timebase``):
jitter and gaps are refused unless ``--resample``; ``--fs`` declares the rate.

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
MAT_SUFFIXES = {".mat": "lms_mat", ".tdms": "tdms", ".uff": "uff58", ".unv": "uff58", ".csv": "csv_file",
                ".txt": "csv_file"}


def register(subparsers) -> None:
    """Add ``import`` to the ``shakerlab`` parser."""
    p = subparsers.add_parser(
        "import",
        help="convert recordings (CSV, LMS .mat, TDMS, UFF; one stage per option) into a shakerlab run file",
        description="Convert recordings into a shakerlab HDF5 run file. A CSV has a header "
        "'t,x_base,x_tip' (base excitation, SI units) or 't,force,x' (force excitation); a motion column may "
        "be velocity or acceleration (v_tip, a_base, v, a). Other files (.mat LMS Test.Lab, .tdms, .uff/.unv "
        "dataset 58) and other CSV headers need a channel map (--map). See docs/recording-format.md.",
    )
    p.add_argument("-o", "--output", required=True, type=Path, help="run file to write (.h5)")
    for stage in STAGE_OPTIONS:
        p.add_argument(f"--{stage}", type=Path, nargs="+", metavar="FILE",
                       help=f"file(s) of the {stage} stage (several files: their channels are pooled)")
    p.add_argument("--map", action="append", metavar="ROLE=CHANNEL[:Q]", default=None,
                   help="channel for a role: t, force, x_base, x_tip, x (and velocity, command with --constitutive); "
                        "Q = x|v|a (displacement, velocity, "
                        "acceleration), e.g. --map x=Time_Laser__X:v --map force=Time_Shaker__X")
    p.add_argument("--map-file", type=Path, metavar="TOML", help="the channel map as a [map] table")
    p.add_argument("--fs", type=float, metavar="HZ",
                   help="sampling rate: for files without a time base, or overriding the file's; with "
                        "--resample, the rate to resample to")
    p.add_argument("--resample", action="store_true",
                   help="interpolate (cubic) unevenly sampled records onto a uniform grid instead of refusing them")
    p.add_argument("--recover", type=Path, metavar="RUN.h5",
                   help="instead: copy an interrupted run file into a cleanly closed one")
    p.add_argument("--constitutive", action="store_true",
                   help="a component test (displacement imposed, force measured): CSV 't,x,force[,v][,cmd]' "
                        "(v a measured velocity, cmd an extra input such as an MR damper's command); the run file "
                        "records the mode and reconstruct identifies the force law (docs/constitutive.md)")
    p.add_argument("--force", action="store_true", help="overwrite the output file")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(handler=_handle)


def read_csv(path: str | Path):
    """Parse one stage CSV; return (excitation, {column: float array}).

    Raises UserFacingError naming the file, line and column of the first bad value.
    """
    from shakerlab.importers import csv_file  # heavy: numpy; loaded when the command runs

    header, data, _, _ = csv_file.parse(path)
    return csv_file.HEADERS[header], {name: data[:, i] for i, name in enumerate(header)}


def _signals(path: Path, time_column):
    import importlib  # lazy: the reader of one format

    from shakerlab.errors import UserFacingError  # heavy: loaded when the command runs
    from shakerlab.importers.csv_file import data_suffix  # heavy: numpy; loaded when the command runs

    module = MAT_SUFFIXES.get(data_suffix(path))

    if module is None:
        raise UserFacingError(f"{path}: unknown file type {path.suffix!r} (expected one of "
                              f"{', '.join(sorted(MAT_SUFFIXES))}; a CSV may be compressed: .csv.gz, .csv.bz2, "
                              f".csv.xz)")
    reader = importlib.import_module(f"shakerlab.importers.{module}")
    if module == "csv_file":
        return reader.read_signals(path, time_column)
    return reader.read_signals(path)


def _stage_from_map(files: list[Path], mapping: dict):
    """(excitation, {role: Signal}, {role: quantity}, time Signal or None) of one stage."""
    from shakerlab.errors import UserFacingError  # heavy: loaded when the command runs

    time_column = mapping["t"][0] if "t" in mapping else "t"
    pool: dict = {}
    for f in files:
        tc = time_column
        from shakerlab.importers.csv_file import data_suffix, parse  # heavy: numpy; loaded when the command runs

        if data_suffix(f) in (".csv", ".txt"):

            header = parse(f, any_header=True)[0]
            tc = time_column if time_column in header else None
        for sig in _signals(Path(f), tc):
            if sig.name in pool and pool[sig.name].source != sig.source:
                raise UserFacingError(f"channel {sig.name!r} is in both {pool[sig.name].source} and {sig.source}")
            pool[sig.name] = sig
    roles, quantities = {}, {}
    for role, (channel, quantity) in mapping.items():
        if role == "t":
            continue
        if channel not in pool:
            raise UserFacingError(f"--map {role}={channel}: no channel {channel!r} in {', '.join(map(str, files))} "
                                  f"(channels: {', '.join(sorted(pool))})")
        roles[role] = pool[channel]
        if role not in ("force", "velocity", "command"):
            quantities[role] = quantity or pool[channel].quantity or "displacement"
    time_sig = None
    if "t" in mapping:
        name = mapping["t"][0]
        if name in pool:
            time_sig = pool[name]
        elif not any(s.time is not None for s in roles.values()):
            raise UserFacingError(f"--map t={name}: no channel {name!r} (channels: {', '.join(sorted(pool))})")
    excitation = "force" if "force" in roles else "base"
    return excitation, roles, quantities, time_sig


def _time_base(stage: str, roles: dict, time_sig, fs, resample):
    """(t from 0, fs, info, resample_from) common to a stage's role signals."""
    import numpy as np  # heavy: numpy, h5py; loaded when the command runs

    from shakerlab.errors import UserFacingError  # heavy: loaded when the command runs
    from shakerlab.importers import timebase  # heavy: numpy; loaded when the command runs
    from shakerlab.importers.signal import Signal  # heavy: numpy; loaded when the command runs

    sigs = list(roles.values())
    n = {s.values.size for s in sigs}
    if len(n) > 1:
        desc = ", ".join(f"{s.name} ({s.source}) {s.values.size}" for s in sigs)
        raise UserFacingError(f"stage {stage!r}: the channels differ in length: {desc} samples")
    n = n.pop()
    if time_sig is not None:
        sigs = [Signal(name=time_sig.name, values=time_sig.values, source=time_sig.source,
                       time=time_sig.values, lines=time_sig.lines)]
    explicit = [s for s in sigs if s.time is not None]
    if explicit:
        ref = explicit[0]
        for s in explicit[1:]:
            if s.time is not ref.time and not np.array_equal(s.time, ref.time):
                raise UserFacingError(f"stage {stage!r}: {ref.name} and {s.name} have different time columns")
        if ref.time.size != n:
            raise UserFacingError(f"stage {stage!r}: time channel {ref.name} has {ref.time.size} samples, "
                                  f"the channels {n}")
        t, rate, info, t_from = timebase.check(ref, resample=resample, fs=fs)
        return t, rate, dict(info, source_t0=float(ref.time[0])), t_from
    rates = [s for s in sigs if s.dt is not None]
    if not rates:
        if fs is None:
            raise UserFacingError(f"stage {stage!r}: {', '.join(s.name for s in sigs)} carry no time base: "
                                  f"give the sampling rate with --fs (or map a time channel with --map t=NAME)")
        return np.arange(n) / fs, float(fs), {"time_base": f"declared --fs {fs:g} Hz"}, None
    ref = rates[0]
    for s in rates[1:]:
        if abs(s.dt - ref.dt) > 1e-9 * ref.dt or abs(s.t0 - ref.t0) > 0.5 * ref.dt:
            raise UserFacingError(f"stage {stage!r}: {ref.name} ({ref.source}: start {ref.t0:g} s, step "
                                  f"{ref.dt:.9g} s) and {s.name} ({s.source}: start {s.t0:g} s, step {s.dt:.9g} s) "
                                  f"are not on one time base")
    info = {"sampling_jitter": 0.0, "source_t0": ref.t0}
    if fs is not None and abs(fs * ref.dt - 1.0) > 1e-9:
        if resample:
            grid = np.arange(int(np.floor((n - 1) * ref.dt * fs + 1e-9)) + 1) / fs
            info["time_base"] = f"resampled (cubic) from {1 / ref.dt:.9g} Hz to {fs:g} Hz (--resample)"
            return grid, float(fs), info, np.arange(n) * ref.dt
        info["time_base"] = f"declared --fs {fs:g} Hz (the file says {1 / ref.dt:.9g} Hz)"
        return np.arange(n) / fs, float(fs), info, None
    return np.arange(n) * ref.dt, 1.0 / ref.dt, info, None


def import_csv(output: str | Path, stage_files: dict, *, overwrite: bool = False, mapping: dict | None = None,
               fs: float | None = None, resample: bool = False, constitutive: bool = False,
               progress=None) -> Path:
    """Write a run file from ``{stage name: file path or list of paths}``; return the output path.

    Without ``mapping`` every file is a shakerlab CSV (header names the roles); with it, the
    files of a stage (any supported format) are pooled and the map picks the roles.
    ``constitutive``: component-test files (``t,x,force[,v][,cmd]``, or a map with x and force);
    the run file's ``mode`` attribute says so (shakerlab.modes). ``progress(text, fraction)`` is told
    each stage as it is read and written (the command line shows it on stderr)."""
    import numpy as np  # heavy: numpy, h5py; loaded when the command runs

    from shakerlab.errors import UserFacingError  # heavy: numpy, h5py; loaded when the command runs
    from shakerlab.importers import csv_file, timebase  # heavy: numpy; loaded when the command runs
    from shakerlab.quantities import channel_name, parse_channel  # heavy: numpy; loaded when the command runs
    from shakerlab.runfile.writer import RunWriter  # heavy: numpy, h5py; loaded when the command runs

    if not stage_files:
        raise UserFacingError("nothing to import: give at least one of --linear, --nonlinear, --validation")
    if fs is not None and not (np.isfinite(fs) and fs > 0):
        raise UserFacingError(f"--fs {fs!r}: the sampling rate must be a positive number of Hz")
    parsed = {}
    say = progress or (lambda text, fraction: None)
    for i, (stage, files) in enumerate(stage_files.items()):
        files = [Path(f) for f in (files if isinstance(files, (list, tuple)) else [files])]
        say(f"reading stage {stage} from {', '.join(f.name for f in files)}", i / (2 * len(stage_files)))
        if mapping:
            kind, roles, quantities, time_sig = _stage_from_map(files, mapping)
            if constitutive:
                component_roles(stage, files, roles, quantities)
            elif {"velocity", "command"} & set(roles):
                raise UserFacingError(f"--map {'/'.join(sorted({'velocity', 'command'} & set(roles)))}: these roles "
                                      f"belong to a component test; add --constitutive")
        elif constitutive:
            kind, roles, quantities, time_sig = _component_csv(stage, files)
        else:
            if len(files) != 1 or csv_file.data_suffix(files[0]) not in (".csv", ".txt", ""):
                raise UserFacingError(f"--{stage} {' '.join(map(str, files))}: without --map, one shakerlab CSV "
                                      f"per stage; map the channels of other files with --map ROLE=CHANNEL[:Q]")
            header, data, lines, quanta = csv_file.parse(files[0])
            kind = csv_file.HEADERS[header]
            from shakerlab.importers.signal import Signal  # heavy: numpy; loaded when the command runs

            tsig = Signal(name="t", values=data[:, 0], source=str(files[0]), time=data[:, 0], quantum=quanta,
                          lines=lines)
            roles, quantities = {}, {}
            for i, name in enumerate(header[1:], start=1):
                role, q = parse_channel(name) or (name, None)
                roles[role] = Signal(name=name, values=data[:, i], source=str(files[0]), time=tsig.time,
                                     quantum=quanta, lines=lines)
                if q is not None:
                    quantities[role] = q
            time_sig = None
        t, rate, info, t_from = _time_base(stage, roles, time_sig, fs, resample)
        values = {}
        for role, sig in roles.items():
            name = channel_name(role, quantities[role]) if role in quantities else role
            values[name] = sig.values if t_from is None else timebase.interpolate(sig.values, t_from, t)
        parsed[stage] = (files, kind, t, rate, info, values, quantities)
    kinds = {p[1] for p in parsed.values()}
    if len(kinds) > 1:
        desc = ", ".join(f"{' '.join(map(str, p[0]))} is {p[1]} excitation" for p in parsed.values())
        raise UserFacingError(f"the stage files mix excitation kinds ({desc}); one run has one kind")
    from shakerlab.output_files import check_name, check_signals, disk_full, need_space, no_space  # heavy: loaded when the command runs
    from shakerlab.output_files import signals_deferred  # heavy: loaded when the command runs

    output = check_name(output)
    attrs = {"source": "import"}
    if constitutive:
        from shakerlab.modes import CONSTITUTIVE, MODE_ATTR  # heavy: loaded when the command runs

        attrs[MODE_ATTR] = CONSTITUTIVE
    # each sample: time, sample index and every channel (8 bytes each) and a flag byte per channel
    n_bytes = sum(p[2].size * (16 + 9 * len(p[5])) for p in parsed.values()) + (1 << 20)
    need_space(output.parent, n_bytes, f"{output.name} was left as it was" if output.exists() else "nothing was written")
    keep = f"{output.name} was left as it was" if output.exists() else "nothing was written"
    try:
        with signals_deferred(), RunWriter(output, overwrite=overwrite, attrs=attrs) as writer:
            if writer.removed_stale:
                print(writer.removed_stale)
            _write_stages(writer, parsed, mapping, constitutive, check_signals, say)
            check_signals()
    except (OSError, RuntimeError, ValueError) as exc:
        if disk_full(exc):
            raise no_space(output, keep) from None
        raise
    return output


# samples per append: the interrupt is looked at between them, and no copy is larger than this
APPEND_BLOCK = 1 << 20


def _write_stages(writer, parsed: dict, mapping, constitutive: bool, between, say) -> None:
    writer.log("info", f"imported with shakerlab import from {len(parsed)} stage file set(s)"
               if mapping else f"imported with shakerlab import from {len(parsed)} CSV file(s)")
    for j, (stage, (files, kind, t, rate, info, values, quantities)) in enumerate(parsed.items()):
        say(f"writing stage {stage} ({t.size} samples)", 0.5 + j / (2 * len(parsed)))
        src = [str(Path(f).resolve()) for f in files]
        settings = {"source_file": src[0] if len(src) == 1 else src, "source_t0": info.pop("source_t0", None)}
        if settings["source_t0"] is None:
            settings.pop("source_t0")
        settings.update(info)
        if mapping:
            settings["channel_map"] = {r: f"{c}:{q}" if q else c for r, (c, q) in mapping.items()}
        extra = {c: EXTRA_UNITS[c] for c in values if c in EXTRA_UNITS} if constitutive else {}
        sw = writer.begin_stage(stage, fs=rate, excitation=kind, settings=settings,
                                quantities={r: q for r, q in quantities.items() if q != "displacement"},
                                extra_channels=extra)
        for i in range(0, t.size, APPEND_BLOCK):
            j = min(i + APPEND_BLOCK, t.size)
            sw.append(i, {c: v[i:j] for c, v in values.items()}, time_s=t[i:j])
            between()
        sw.close("complete", summary={"n_samples": int(t.size), "duration_s": float(t[-1] - t[0])})
        qs = ", ".join(f"{r} {q}" for r, q in quantities.items() if q != "displacement")
        writer.log("info", f"stage {stage!r}: {t.size} samples from {', '.join(map(str, files))} ({kind} "
                           f"excitation{', ' + qs if qs else ''}, fs {rate:.6g} Hz)")


# a component test's CSV columns -> the run file's channels (shakerlab.modes), and their units
COMPONENT_COLUMNS = {"x": "x", "force": "force", "v": "velocity", "cmd": "command"}
EXTRA_UNITS = {"velocity": "m/s", "command": "command units"}


def component_roles(stage: str, files, roles: dict, quantities: dict) -> None:
    """Refuse a component test without a force or a displacement channel (names the files)."""
    from shakerlab.errors import UserFacingError  # heavy: loaded when the command runs

    where = " ".join(map(str, files))
    if "force" not in roles:
        raise UserFacingError(f"--{stage} {where}: a component test (--constitutive) needs a measured force: "
                              f"a column 'force' [N] (CSV 't,x,force[,v][,cmd]') or --map force=CHANNEL")
    if "x" not in roles or quantities.get("x", "displacement") != "displacement":
        raise UserFacingError(f"--{stage} {where}: a component test (--constitutive) needs the imposed displacement "
                              f"x [m] (CSV 't,x,force[,v][,cmd]'; a measured velocity goes in column v beside it)")


def _component_csv(stage: str, files):
    """(kind, roles, quantities, time Signal) of one component-test CSV ``t,x,force[,v][,cmd]``."""
    from shakerlab.errors import UserFacingError  # heavy: loaded when the command runs
    from shakerlab.importers import csv_file  # heavy: numpy; loaded when the command runs
    from shakerlab.importers.signal import Signal  # heavy: numpy; loaded when the command runs

    if len(files) != 1 or csv_file.data_suffix(files[0]) not in (".csv", ".txt", ""):
        raise UserFacingError(f"--{stage} {' '.join(map(str, files))}: with --constitutive and without --map, one "
                              f"CSV 't,x,force[,v][,cmd]' per stage")
    header, data, lines, quanta = csv_file.parse(files[0], any_header=True)
    names = [h.lower() for h in header]
    unknown = [h for h in names[1:] if h not in COMPONENT_COLUMNS]
    if names[0] != "t" or unknown:
        raise UserFacingError(f"{files[0]}: header {','.join(header)!r}: a component test's CSV has the columns "
                              f"t,x,force and optionally v (measured velocity) and cmd (command)"
                              + (f"; unknown column(s) {', '.join(unknown)}" if unknown else "; the first is t"))
    time_sig = Signal(name="t", values=data[:, 0], source=str(files[0]), time=data[:, 0], quantum=quanta, lines=lines)
    roles = {COMPONENT_COLUMNS[h]: Signal(name=h, values=data[:, i], source=str(files[0]), time=time_sig.time,
                                          quantum=quanta, lines=lines) for i, h in enumerate(names) if i}
    component_roles(stage, files, roles, {})
    return "force", roles, {}, time_sig


def _handle(args) -> int:
    from shakerlab.errors import UserFacingError  # heavy: numpy, h5py; loaded when the command runs
    from shakerlab.runfile.reader import read_info  # heavy: numpy, h5py; loaded when the command runs
    from shakerlab.runfile.results import recover_copy  # heavy: numpy, h5py; loaded when the command runs
    from shakerlab.output_files import check_name  # heavy: loaded when the command runs

    check_name(args.output)
    if args.recover is not None:
        if any(getattr(args, s) for s in STAGE_OPTIONS):
            raise UserFacingError("--recover copies a run file; do not combine it with --linear/--nonlinear/--validation")
        lost: list[str] = []
        recover_copy(args.recover, args.output, overwrite=args.force, losses=lost)
        for line in lost:
            print(f"recovery: {line}")
        print(f"wrote {args.output} (clean copy of {args.recover}, status recovered; "
              f"{'what was dropped or rebuilt is listed above and in its event log' if lost else 'every object copied as stored'})")
        return 0
    from shakerlab.importers import mapping  # heavy: loaded when the command runs

    files = {s: getattr(args, s) for s in STAGE_OPTIONS if getattr(args, s) is not None}
    cmap = mapping.parse(args.map, args.map_file)
    from shakerlab import progress_view  # heavy: loaded when the command runs

    live = progress_view.start("importing", quiet=args.quiet)
    ok = False
    try:
        out = import_csv(args.output, files, overwrite=args.force, mapping=cmap or None, fs=args.fs,
                         resample=args.resample, constitutive=args.constitutive,
                         progress=None if live is None else
                         lambda text, f: live.line.update(progress_view.Status(text, f, 0.0, None)))
        ok = True
    finally:
        progress_view.stop("imported in {elapsed}" if ok else None)
    info = read_info(out)
    for name, st in info["stages"].items():
        print(f"{name}: {st['n_samples']} samples at {st['fs']:.6g} Hz")
    print(f"wrote {out}")
    return 0

"""The shakerlab run file: one HDF5 file per run (writer, reader, results).

Layout (NeXus-style group classes in the ``NX_class`` attribute; the full
reference is ``docs/recording-format.md``)::

    /                               format, format_version, software_version,
                                    created, clean_close, default="entry"
    /entry            NXentry       status, start_time, end_time, excitation
      config/         NXcollection  rig_toml, protocol_toml (text datasets)
      instrument/     NXinstrument  one group per instrument: identity, address,
                                    settings_json (+ scalar settings as attrs)
      stages/         NXcollection  attr ``order`` (stage names in run order)
        <name>/       NXdata        excitation, fs, status, start_index,
                                    t0 (s since trigger), settings_json, summary_json
          sample_index  int64   sample number since the common trigger
          time          float64 seconds since the stage's first sample
          x_base, x_tip float64 metres as acquired (or force [N], x [m])
          flags_<ch>    uint8   sensor flags per sample (0 = good)
          steps         compound: sample_index, amplitude_vpp, frequency_hz, label
      events          compound: wall_time, run_time, level, message
      results/        NXcollection  one group per reprocessing (reconstruction_000, ...)

Crash safety: the file is written with the default libver (never SWMR),
datasets are chunked and resizable and the writer flushes at least every
``flush_interval`` seconds, so a SIGKILL or power loss leaves a file that
opens directly and holds everything up to the last flush. ``clean_close`` is
set only by :meth:`RunWriter.close`; :func:`open_for_results` refuses to open
a file for writing unless it is set (opening a crashed file for writing is the
one way to lose it) and :func:`recover_copy` makes a clean copy instead.
Readers always open read-only.
"""
from __future__ import annotations

import datetime as _dt
import json
import time
from pathlib import Path

import numpy as np

from shakerlab import __version__
from shakerlab.errors import UserFacingError
from shakerlab.run_data import CHANNELS, Run, Stage

FORMAT = "shakerlab-run"
FORMAT_VERSION = 1
CHUNK = 8192
LEVELS = ("debug", "info", "warning", "error", "critical")

_STR = None  # h5py string dtype, created lazily (keeps import light)


def _str_dtype():
    global _STR
    if _STR is None:
        import h5py

        _STR = h5py.string_dtype("utf-8")
    return _STR


def _now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _jsonable(value):
    """Settings -> JSON-safe values (numpy scalars and arrays, paths, tuples)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def _set_scalar_attrs(obj, settings: dict) -> None:
    """Store settings as JSON, plus each scalar as its own attribute (handy in HDFView)."""
    settings = _jsonable(settings)
    obj.attrs["settings_json"] = json.dumps(settings, sort_keys=True)
    for key, value in settings.items():
        if isinstance(value, (bool, int, float, str)) and key not in ("settings_json",):
            obj.attrs[key] = value


def _step_dtype():
    return np.dtype(
        [("sample_index", "<i8"), ("amplitude_vpp", "<f8"), ("frequency_hz", "<f8"), ("label", _str_dtype())]
    )


def _event_dtype():
    return np.dtype(
        [("wall_time", "<f8"), ("run_time", "<f8"), ("level", _str_dtype()), ("message", _str_dtype())]
    )


class StageWriter:
    """Appends one stage's samples; made by :meth:`RunWriter.begin_stage`."""

    def __init__(self, writer: "RunWriter", group, channels: tuple[str, ...], start_index: int, fs: float):
        self._writer = writer
        self.group = group
        self.name = group.name.rsplit("/", 1)[-1]
        self.channels = channels
        self.start_index = int(start_index)
        self.fs = float(fs)
        self.n_samples = 0
        self.n_flagged = 0
        self.closed = False

    def append(self, index0: int, values: dict[str, np.ndarray], flags: dict[str, np.ndarray] | None = None,
               time_s: np.ndarray | None = None) -> None:
        """Append samples ``index0 .. index0+n-1`` of every channel (same length each).

        ``time_s`` (seconds since the stage start) defaults to the sample
        index over ``fs``; importers pass the file's own time column.
        """
        if self.closed:
            raise RuntimeError(f"stage {self.name!r} is closed")
        arrays = {ch: np.asarray(values[ch], dtype=float) for ch in self.channels}
        n = arrays[self.channels[0]].size
        if any(a.shape != (n,) for a in arrays.values()):
            raise ValueError(f"stage {self.name!r}: channels differ in length")
        if n == 0:
            return
        index = np.arange(index0, index0 + n, dtype=np.int64)
        if time_s is None:
            time_s = (index - self.start_index) / self.fs
        g = self.group
        new = self.n_samples + n
        columns = {"sample_index": index, "time": np.asarray(time_s, dtype=float)}
        columns.update(arrays)
        for ch in self.channels:
            f = np.zeros(n, np.uint8) if flags is None or ch not in flags else np.asarray(flags[ch], np.uint8)
            self.n_flagged += int(np.count_nonzero(f))
            columns[f"flags_{ch}"] = f
        for key, col in columns.items():
            ds = g[key]
            ds.resize((new,))
            ds[self.n_samples:new] = col
        self.n_samples = new
        g.attrs["n_samples"] = new
        self._writer._maybe_flush()

    def add_step(self, sample_index: int, amplitude_vpp: float, frequency_hz: float, label: str = "") -> None:
        """Record a setpoint change (a row of the stage's ``steps`` table)."""
        ds = self.group["steps"]
        n = ds.shape[0]
        ds.resize((n + 1,))
        ds[n] = (int(sample_index), float(amplitude_vpp), float(frequency_hz), str(label))
        self._writer._maybe_flush()

    def close(self, status: str = "complete", summary: dict | None = None) -> None:
        if self.closed:
            return
        self.group.attrs["status"] = status
        self.group.attrs["end_index"] = self.start_index + self.n_samples
        if summary is not None:
            self.group.attrs["summary_json"] = json.dumps(_jsonable(summary), sort_keys=True)
        self.closed = True
        self._writer.flush()


class RunWriter:
    """Writes one run file. Use as a context manager or call :meth:`close`.

    ``RunWriter(path)`` refuses to overwrite an existing file unless
    ``overwrite=True``.
    """

    def __init__(self, path: str | Path, *, overwrite: bool = False, flush_interval: float = 0.5,
                 attrs: dict | None = None):
        import h5py

        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise UserFacingError(f"{self.path}: file exists (choose another -o name or delete it)")
        try:
            self.file = h5py.File(self.path, "w")  # default libver, never SWMR
        except OSError as exc:
            raise UserFacingError(f"{self.path}: cannot create the run file ({exc})") from None
        self.flush_interval = float(flush_interval)
        self._last_flush = time.monotonic()
        self._t_start = time.time()
        self.n_events = 0
        f = self.file
        f.attrs.update({
            "format": FORMAT, "format_version": FORMAT_VERSION, "software_version": __version__,
            "creator": f"shakerlab {__version__}", "created": _now_iso(), "file_name": self.path.name,
            "clean_close": False, "NX_class": "NXroot", "default": "entry",
        })
        entry = f.create_group("entry")
        entry.attrs.update({"NX_class": "NXentry", "status": "running", "start_time": _now_iso()})
        for key, value in (attrs or {}).items():
            entry.attrs[key] = _jsonable(value) if not isinstance(value, dict) else json.dumps(_jsonable(value))
        entry.create_group("config").attrs["NX_class"] = "NXcollection"
        entry.create_group("instrument").attrs["NX_class"] = "NXinstrument"
        stages = entry.create_group("stages")
        stages.attrs["NX_class"] = "NXcollection"
        stages.attrs["order"] = json.dumps([])
        entry.create_group("results").attrs["NX_class"] = "NXcollection"
        entry.create_dataset("events", shape=(0,), maxshape=(None,), dtype=_event_dtype(), chunks=(256,))
        self.stages: dict[str, StageWriter] = {}
        self.flush()

    # -- context manager ---------------------------------------------------
    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.file.id.valid:
            self.close("complete" if exc_type is None else "error")

    # -- metadata ------------------------------------------------------------
    def set_attrs(self, **attrs) -> None:
        for key, value in attrs.items():
            self.file["entry"].attrs[key] = (
                json.dumps(_jsonable(value)) if isinstance(value, (dict, list)) else _jsonable(value)
            )

    def set_text(self, name: str, text: str) -> None:
        """Store a text document (``rig_toml``, ``protocol_toml``, ...) under ``entry/config``."""
        grp = self.file["entry/config"]
        if name in grp:
            del grp[name]
        grp.create_dataset(name, data=str(text), dtype=_str_dtype())
        self.flush()

    def set_instrument(self, name: str, *, identity: str, address: str, settings: dict | None = None) -> None:
        """Record an instrument's identity (``*IDN?``-like), address and settings."""
        grp = self.file["entry/instrument"].require_group(name)
        grp.attrs["NX_class"] = "NXcollection"
        grp.attrs["identity"] = str(identity)
        grp.attrs["address"] = str(address)
        _set_scalar_attrs(grp, settings or {})
        self.flush()

    def log(self, level: str, message: str, run_time: float = float("nan"), wall_time: float | None = None) -> None:
        """Append an event (level in debug/info/warning/error/critical)."""
        if level not in LEVELS:
            raise ValueError(f"event level {level!r} is not one of {LEVELS}")
        ds = self.file["entry/events"]
        n = ds.shape[0]
        ds.resize((n + 1,))
        ds[n] = (time.time() if wall_time is None else wall_time, run_time, level, str(message))
        self.n_events = n + 1
        if level in ("warning", "error", "critical"):
            self.flush()
        else:
            self._maybe_flush()

    # -- stages ----------------------------------------------------------------
    def begin_stage(self, name: str, *, fs: float, excitation: str = "base", start_index: int = 0,
                    settings: dict | None = None) -> StageWriter:
        """Create ``entry/stages/<name>`` and return its :class:`StageWriter`."""
        if excitation not in CHANNELS:
            raise ValueError(f"excitation must be one of {sorted(CHANNELS)}")
        stages = self.file["entry/stages"]
        if name in stages:
            raise ValueError(f"stage {name!r} already recorded in {self.path}")
        channels = CHANNELS[excitation]
        g = stages.create_group(name)
        g.attrs.update({
            "NX_class": "NXdata", "signal": channels[1], "axes": "time", "excitation": excitation,
            "fs": float(fs), "start_index": int(start_index), "t0": int(start_index) / float(fs),
            "status": "recording", "n_samples": 0, "start_time": _now_iso(),
        })
        _set_scalar_attrs(g, settings or {})
        g.create_dataset("sample_index", shape=(0,), maxshape=(None,), dtype="<i8", chunks=(CHUNK,))
        t = g.create_dataset("time", shape=(0,), maxshape=(None,), dtype="<f8", chunks=(CHUNK,))
        t.attrs["units"] = "s"
        for ch in channels:
            d = g.create_dataset(ch, shape=(0,), maxshape=(None,), dtype="<f8", chunks=(CHUNK,))
            d.attrs["units"] = "N" if ch == "force" else "m"
            g.create_dataset(f"flags_{ch}", shape=(0,), maxshape=(None,), dtype="u1", chunks=(CHUNK,))
        g.create_dataset("steps", shape=(0,), maxshape=(None,), dtype=_step_dtype(), chunks=(64,))
        order = json.loads(stages.attrs["order"])
        order.append(name)
        stages.attrs["order"] = json.dumps(order)
        sw = StageWriter(self, g, channels, start_index, fs)
        self.stages[name] = sw
        self.flush()
        return sw

    # -- flushing and closing --------------------------------------------------
    def _maybe_flush(self) -> None:
        if time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()

    def flush(self) -> None:
        self.file.flush()
        self._last_flush = time.monotonic()

    def close(self, status: str = "complete") -> None:
        """Close every open stage, write the end status and mark the file cleanly closed."""
        if not self.file.id.valid:
            return
        for sw in self.stages.values():
            if not sw.closed:
                sw.close(status="interrupted" if status != "complete" else "complete")
        entry = self.file["entry"]
        entry.attrs["status"] = status
        entry.attrs["end_time"] = _now_iso()
        self.file.attrs["clean_close"] = True
        self.file.flush()
        self.file.close()


# ---------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------

def _open_read(path: str | Path):
    import h5py

    path = Path(path)
    if not path.exists():
        raise UserFacingError(f"{path}: no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise UserFacingError(f"{path}: not a readable HDF5 file ({exc})") from None
    if f.attrs.get("format") != FORMAT or "entry" not in f:
        f.close()
        raise UserFacingError(f"{path}: not a shakerlab run file (root attribute 'format' is not {FORMAT!r})")
    return f


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def stage_order(f) -> list[str]:
    stages = f["entry/stages"]
    order = json.loads(_text(stages.attrs.get("order", "[]")))
    return [n for n in order if n in stages] + [n for n in stages if n not in order]


def read_run(path: str | Path, stages: list[str] | None = None) -> Run:
    """Read a run file into a :class:`~shakerlab.run_data.Run` (read-only open).

    Every recorded stage is returned (``linear``, ``nonlinear``,
    ``validation``, ``resonance_search``, ...) unless ``stages`` names a
    subset. A stage's ``settings`` holds its recorded settings plus
    ``status``, ``summary``, ``t0`` and ``steps``. Samples flagged by a
    sensor (out of range, signal loss) cannot be used: a stage holding any is
    refused with a message naming the first one.
    """
    path = Path(path)
    with _open_read(path) as f:
        entry = f["entry"]
        out: dict[str, Stage] = {}
        names = stage_order(f)
        if stages is not None:
            missing = [s for s in stages if s not in names]
            if missing:
                raise UserFacingError(f"{path}: no stage(s) {', '.join(missing)} (stages: {', '.join(names)})")
            names = [n for n in names if n in stages]
        for name in names:
            g = entry["stages"][name]
            excitation = _text(g.attrs.get("excitation", "base"))
            n = int(g["time"].shape[0])
            if n < 2:
                continue  # a stage interrupted before its first block holds nothing to analyse
            channels = {ch: g[ch][:] for ch in CHANNELS[excitation]}
            for ch in CHANNELS[excitation]:
                flags = g[f"flags_{ch}"][:]
                if flags.any():
                    i = int(np.flatnonzero(flags)[0])
                    raise UserFacingError(
                        f"{path}: stage {name!r} channel {ch!r} has {int(np.count_nonzero(flags))} flagged "
                        f"sample(s) (sensor out of range or signal loss), first at sample {i}"
                    )
            settings = json.loads(_text(g.attrs.get("settings_json", "{}")))
            settings["status"] = _text(g.attrs.get("status", ""))
            settings["t0"] = float(g.attrs.get("t0", 0.0))
            settings["summary"] = json.loads(_text(g.attrs.get("summary_json", "{}")))
            settings["steps"] = [
                {"sample_index": int(r["sample_index"]), "amplitude_vpp": float(r["amplitude_vpp"]),
                 "frequency_hz": float(r["frequency_hz"]), "label": _text(r["label"])}
                for r in g["steps"][:]
            ]
            out[name] = Stage(name=name, t=g["time"][:], channels=channels, excitation=excitation,
                              settings=settings)
        attrs = {k: _text(v) if isinstance(v, bytes) else (v.item() if isinstance(v, np.generic) else v)
                 for k, v in entry.attrs.items()}
        attrs["clean_close"] = bool(f.attrs.get("clean_close", False))
        attrs["software_version"] = _text(f.attrs.get("software_version", ""))
    if not out:
        raise UserFacingError(f"{path}: the run file holds no recorded samples")
    return Run(stages=out, attrs=attrs, source=str(path))


def read_events(path: str | Path) -> list[dict]:
    """The event log: dicts with wall_time, run_time, level, message."""
    with _open_read(path) as f:
        return [
            {"wall_time": float(r["wall_time"]), "run_time": float(r["run_time"]),
             "level": _text(r["level"]), "message": _text(r["message"])}
            for r in f["entry/events"][:]
        ]


def read_info(path: str | Path) -> dict:
    """Run-level metadata: attributes, instruments, config texts, stage summaries, results."""
    with _open_read(path) as f:
        entry = f["entry"]
        info = {
            "clean_close": bool(f.attrs.get("clean_close", False)),
            "software_version": _text(f.attrs.get("software_version", "")),
            "status": _text(entry.attrs.get("status", "")),
            "config": {k: _text(entry["config"][k][()]) for k in entry["config"]},
            "instruments": {},
            "stages": {},
            "results": list(entry["results"]),
        }
        for name, g in entry["instrument"].items():
            info["instruments"][name] = {
                "identity": _text(g.attrs.get("identity", "")),
                "address": _text(g.attrs.get("address", "")),
                "settings": json.loads(_text(g.attrs.get("settings_json", "{}"))),
            }
        for name in stage_order(f):
            g = entry["stages"][name]
            info["stages"][name] = {
                "status": _text(g.attrs.get("status", "")),
                "n_samples": int(g["time"].shape[0]),
                "fs": float(g.attrs.get("fs", 0.0)),
                "t0": float(g.attrs.get("t0", 0.0)),
                "settings": json.loads(_text(g.attrs.get("settings_json", "{}"))),
                "summary": json.loads(_text(g.attrs.get("summary_json", "{}"))),
            }
        return info


# ---------------------------------------------------------------------------
# reprocessing: results written back into the run file
# ---------------------------------------------------------------------------

def _refuse_unclean(path: Path) -> None:
    raise UserFacingError(
        f"{path} was not closed cleanly (the recording was interrupted); it stays readable but is never "
        f"opened for writing. Make a clean copy with `shakerlab import --recover {path} -o COPY.h5` "
        f"and write into the copy."
    )


def open_for_results(path: str | Path):
    """Open a cleanly closed run file in mode 'a' (h5py.File); refuse any other file."""
    import h5py

    path = Path(path)
    with _open_read(path) as f:
        clean = bool(f.attrs.get("clean_close", False))
    if not clean:
        _refuse_unclean(path)
    return h5py.File(path, "a")


def add_result(path: str | Path, kind: str, payload: dict, text: str = "") -> str:
    """Write one reprocessing result as ``entry/results/<kind>_NNN``; return the group path.

    ``payload`` is stored as JSON (``result_json``), ``text`` (e.g. the
    printed equation) as a string dataset.
    """
    with open_for_results(path) as f:
        results = f["entry/results"]
        i = 0
        while f"{kind}_{i:03d}" in results:
            i += 1
        g = results.create_group(f"{kind}_{i:03d}")
        g.attrs.update({"NX_class": "NXcollection", "kind": kind, "created": _now_iso(),
                        "software_version": __version__})
        g.create_dataset("result_json", data=json.dumps(_jsonable(payload), sort_keys=True), dtype=_str_dtype())
        if text:
            g.create_dataset("text", data=str(text), dtype=_str_dtype())
        return g.name


def read_results(path: str | Path) -> dict[str, dict]:
    """All results written back into the file: {group name: payload dict}."""
    with _open_read(path) as f:
        return {name: json.loads(_text(g["result_json"][()])) for name, g in f["entry/results"].items()}


def recover_copy(src: str | Path, dst: str | Path) -> Path:
    """Copy an interrupted run file (read-only open) into a new, cleanly closed file.

    Everything up to the source's last flush is copied; the copy's status is
    ``recovered`` and an event records where it came from. The source is
    never opened for writing.
    """
    import h5py

    src, dst = Path(src), Path(dst)
    if dst.exists():
        raise UserFacingError(f"{dst}: file exists (choose another -o name or delete it)")
    with _open_read(src) as f, h5py.File(dst, "w") as g:
        for key, value in f.attrs.items():
            g.attrs[key] = value
        for name in f:
            f.copy(f[name], g, name=name)
        was = _text(g["entry"].attrs.get("status", ""))
        g["entry"].attrs["status"] = "recovered"
        for sname in g["entry/stages"]:
            st = g["entry/stages"][sname]
            if _text(st.attrs.get("status", "")) == "recording":
                st.attrs["status"] = "interrupted"
        ev = g["entry/events"]
        n = ev.shape[0]
        ev.resize((n + 1,))
        ev[n] = (time.time(), float("nan"), "warning",
                 f"recovered copy of {src} (status was {was!r}, file not closed cleanly)")
        g.attrs["recovered_from"] = str(src)
        g.attrs["clean_close"] = True
    return dst

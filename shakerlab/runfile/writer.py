"""Writing a run file while it is recorded (layout and crash safety: shakerlab.runfile.format)."""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import h5py
import numpy as np

from shakerlab import __version__
from shakerlab.errors import UserFacingError
from shakerlab.jsonsafe import clean
from shakerlab.output_files import (OutputLock, check_name, check_signals, free_bytes, mount_point, partial_path,
                                    refuse_partial)
from shakerlab.quantities import DISPLACEMENT, QUANTITIES, UNITS, channel_name
from shakerlab.run_data import CHANNELS, check_stage_name
from shakerlab.runfile.format import (CHUNK, FORMAT, FORMAT_VERSION, LEVELS, event_dtype, now_iso, open_read,
                                      set_scalar_attrs, step_dtype, str_dtype)


class NoSpace(UserFacingError):
    """The file system of a run file being written is (almost) full: nothing more is buffered."""

    def __init__(self, partial: Path, free: int, need: int):
        self.partial = partial
        super().__init__(f"no space left on {mount_point(partial)} (writing {partial}: {free} bytes free, "
                         f"{need} needed to go on)")


def _clean_attr(value):
    return clean(value, nan_to_none=False)


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
        self._writer.check_space(n * (17 + 9 * len(self.channels)))
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
            self.group.attrs["summary_json"] = json.dumps(_clean_attr(summary), sort_keys=True)
        self.closed = True
        self._writer.flush()


class RunWriter:
    """Writes one run file. Use as a context manager or call :meth:`close`.

    ``RunWriter(path)`` refuses to overwrite an existing file unless
    ``overwrite=True``. The file is written as ``path.partial`` (crash safe,
    flushed as it grows) under the output lock of ``path``
    (:mod:`shakerlab.output_files`) and renamed to ``path`` by :meth:`close`
    after it was reopened and its sample counts checked; an existing ``path``
    is untouched until then. Leaving the ``with`` block by an exception, or
    :meth:`discard`, deletes the partial file and keeps ``path`` as it was. A
    crash leaves ``path.partial`` (recover it with ``shakerlab import
    --recover``).

    ``append=True`` adds stages to the cleanly closed run file ``path`` the same way: a copy is
    recorded into and renamed over it (:meth:`_open_for_append`); ``overwrite`` and ``attrs`` do
    not apply.
    """

    def __init__(self, path: str | Path, *, overwrite: bool = False, flush_interval: float = 0.5,
                 attrs: dict | None = None, append: bool = False):
        if append:
            self._open_for_append(path, flush_interval)
            return
        self.path = check_name(path)
        self.partial = partial_path(self.path)
        self.problems: list[str] = []      # what the check after closing found (empty: the file is whole)
        self.renamed = False
        self.overwrite = overwrite
        if self.path.is_dir():
            raise UserFacingError(f"{self.path}: is a directory, expected a run file name")
        if self.path.exists() and not overwrite:
            raise UserFacingError(f"{self.path}: file exists (choose another -o name or delete it)")
        self._lock = OutputLock(self.path).acquire()
        self.removed_stale: str | None = None     # what a stale import's partial file was, when removed
        try:
            if overwrite:
                self.removed_stale = remove_stale_import(self.partial)
            refuse_partial(self.path)
            try:
                self.file = h5py.File(self.partial, "x")  # default libver, never SWMR
            except (OSError, ValueError) as exc:
                raise UserFacingError(f"{self.path}: cannot create the run file {self.partial} ({exc})") from None
        except BaseException:
            self._lock.release()
            raise
        self._start_clock(flush_interval)
        self.n_events = 0
        f = self.file
        f.attrs.update({
            "format": FORMAT, "format_version": FORMAT_VERSION, "software_version": __version__,
            "creator": f"shakerlab {__version__}", "created": now_iso(), "file_name": self.path.name,
            "clean_close": False, "NX_class": "NXroot", "default": "entry", "writer_pid": os.getpid(),
        })
        entry = f.create_group("entry")
        entry.attrs.update({"NX_class": "NXentry", "status": "running", "start_time": now_iso()})
        for key, value in (attrs or {}).items():
            entry.attrs[key] = _clean_attr(value) if not isinstance(value, dict) else json.dumps(_clean_attr(value))
        entry.create_group("config").attrs["NX_class"] = "NXcollection"
        entry.create_group("instrument").attrs["NX_class"] = "NXinstrument"
        stages = entry.create_group("stages")
        stages.attrs["NX_class"] = "NXcollection"
        stages.attrs["order"] = json.dumps([])
        entry.create_group("results").attrs["NX_class"] = "NXcollection"
        entry.create_dataset("events", shape=(0,), maxshape=(None,), dtype=event_dtype(), chunks=(256,))
        self.stages: dict[str, StageWriter] = {}
        self.flush()

    def _start_clock(self, flush_interval: float) -> None:
        """The flush schedule and the session clock of a file opened for writing."""
        self.flush_interval = float(flush_interval)
        self._last_flush = time.monotonic()
        self._unflushed = 0
        self._t_start = time.time()

    def _open_for_append(self, path: str | Path, flush_interval: float) -> None:
        """``append=True``: record more stages into a cleanly closed run file. The file itself is
        never written in place: under its output lock it is copied to ``path.partial``, the new
        stages go into the copy (flushed as it grows, as any recording), and :meth:`close` renames
        the checked copy over the file. A crash or a failure leaves the file as it was (and the
        copy with what was recorded, for ``shakerlab import --recover``)."""
        target = Path(path)
        if not target.is_file():
            raise UserFacingError(f"{target}: no run file to add stages to")
        target = target.resolve()    # a symbolic link is written through, the link stays
        with open_read(target) as f:
            if not bool(f.attrs.get("clean_close", False)):
                raise UserFacingError(f"{target}: was not closed cleanly; stages are added only to a whole run "
                                      f"file (make a clean copy with `shakerlab import --recover`)")
        self.path = target
        self.partial = partial_path(target)
        self.problems = []
        self.renamed = False
        self.overwrite = True        # the rename replaces the file this copy extends
        self.removed_stale = None
        self._lock = OutputLock(target).acquire()
        try:
            refuse_partial(target)
            need = target.stat().st_size + self.RESERVE_BYTES
            if free_bytes(target) < need:
                raise UserFacingError(f"{target}: no room to add stages (a copy needs {need} bytes); "
                                      f"the file was left as it was")
            shutil.copy2(target, self.partial)
            try:
                self.file = h5py.File(self.partial, "a")
            except (OSError, ValueError) as exc:
                self.partial.unlink(missing_ok=True)
                raise UserFacingError(f"{target}: cannot open the copy {self.partial} ({exc})") from None
        except BaseException:
            self._lock.release()
            raise
        self._start_clock(flush_interval)
        self.file.attrs.update({"clean_close": False, "writer_pid": os.getpid()})
        self.file["entry"].attrs["status"] = "running"
        self.n_events = int(self.file["entry/events"].shape[0])
        self.stages = {}
        self.flush()

    def end_index(self) -> int:
        """The sample index one past the last recorded sample of any stage (0 for none)."""
        stages = self.file["entry/stages"]
        return max((int(g.attrs.get("end_index", g.attrs.get("start_index", 0) + g.attrs.get("n_samples", 0)))
                    for g in stages.values()), default=0)

    # -- context manager ---------------------------------------------------
    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.discard()
        elif self.file.id.valid:
            self.close("complete")

    # -- metadata ------------------------------------------------------------
    def set_attrs(self, **attrs) -> None:
        for key, value in attrs.items():
            self.file["entry"].attrs[key] = (
                json.dumps(_clean_attr(value)) if isinstance(value, (dict, list)) else _clean_attr(value)
            )

    def set_text(self, name: str, text: str) -> None:
        """Store a text document (``rig_toml``, ``protocol_toml``, ...) under ``entry/config``."""
        grp = self.file["entry/config"]
        if name in grp:
            del grp[name]
        grp.create_dataset(name, data=str(text), dtype=str_dtype())
        self.flush()

    def set_instrument(self, name: str, *, identity: str, address: str, settings: dict | None = None) -> None:
        """Record an instrument's identity (``*IDN?``-like), address and settings."""
        grp = self.file["entry/instrument"].require_group(name)
        grp.attrs["NX_class"] = "NXcollection"
        grp.attrs["identity"] = str(identity)
        grp.attrs["address"] = str(address)
        set_scalar_attrs(grp, settings or {})
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
                    settings: dict | None = None, quantities: dict | None = None,
                    extra_channels: dict | None = None) -> StageWriter:
        """Create ``entry/stages/<name>`` and return its :class:`StageWriter`.

        ``quantities`` maps a motion role (``x_base``, ``x_tip``, ``x``) to the quantity its
        sensor reports (default displacement); the channel is then named by its quantity
        (``v_tip``) and carries ``quantity`` and ``units`` attributes. ``extra_channels``
        {name: units} adds channels beyond the roles (a component test's measured velocity or
        command, shakerlab.modes), listed in the stage attribute ``extra_channels``."""
        if excitation not in CHANNELS:
            raise ValueError(f"excitation must be one of {sorted(CHANNELS)}")
        check_stage_name(name, self.path)
        quantities = dict(quantities or {})
        bad = {r: q for r, q in quantities.items() if r not in CHANNELS[excitation] or r == "force"
               or q not in QUANTITIES}
        if bad:
            raise ValueError(f"quantities {bad}: roles are {CHANNELS[excitation]} (not force), "
                             f"quantities {QUANTITIES}")
        stages = self.file["entry/stages"]
        if name in stages:
            raise ValueError(f"stage {name!r} already recorded in {self.path}")
        channels = tuple(channel_name(r, quantities[r]) if quantities.get(r, DISPLACEMENT) != DISPLACEMENT else r
                         for r in CHANNELS[excitation])
        role_of = dict(zip(channels, CHANNELS[excitation]))
        extra_channels = dict(extra_channels or {})
        channels = channels + tuple(extra_channels)
        g = stages.create_group(name)
        g.attrs.update({
            "NX_class": "NXdata", "signal": channels[1], "axes": "time", "excitation": excitation,
            "fs": float(fs), "start_index": int(start_index), "t0": int(start_index) / float(fs),
            "status": "recording", "n_samples": 0, "start_time": now_iso(),
        })
        if extra_channels:
            g.attrs["extra_channels"] = json.dumps(list(extra_channels))
        set_scalar_attrs(g, settings or {})
        g.create_dataset("sample_index", shape=(0,), maxshape=(None,), dtype="<i8", chunks=(CHUNK,))
        t = g.create_dataset("time", shape=(0,), maxshape=(None,), dtype="<f8", chunks=(CHUNK,))
        t.attrs["units"] = "s"
        for ch in channels:
            d = g.create_dataset(ch, shape=(0,), maxshape=(None,), dtype="<f8", chunks=(CHUNK,))
            if ch in extra_channels:
                d.attrs["units"] = str(extra_channels[ch])
            elif ch == "force":
                d.attrs["units"] = "N"
            else:
                q = quantities.get(role_of[ch], DISPLACEMENT)
                d.attrs["units"] = UNITS[q]
                if q != DISPLACEMENT:     # displacement-only stages keep the version-1 attributes
                    d.attrs["quantity"] = q
            g.create_dataset(f"flags_{ch}", shape=(0,), maxshape=(None,), dtype="u1", chunks=(CHUNK,))
        g.create_dataset("steps", shape=(0,), maxshape=(None,), dtype=step_dtype(), chunks=(64,))
        order = json.loads(stages.attrs["order"])
        order.append(name)
        stages.attrs["order"] = json.dumps(order)
        sw = StageWriter(self, g, channels, start_index, fs)
        self.stages[name] = sw
        self.flush()
        return sw

    # -- flushing and closing --------------------------------------------------
    # bytes kept free on the file system: room to flush what is buffered and to close the file
    RESERVE_BYTES = 512 * 1024

    def check_space(self, n_bytes: int) -> None:
        """Refuse to buffer ``n_bytes`` more when the file system could not then take the flush and
        the close: HDF5 fails part-way on a full disk (and h5py reports it only while freeing its
        objects), so the writer stops while the file on disk is still whole to its last flush."""
        self._unflushed += n_bytes
        free = free_bytes(self.partial)
        need = self.RESERVE_BYTES + 2 * self._unflushed + CHUNK * 8 * 2 * max(len(self.stages), 1) * 8
        if free < need:
            raise NoSpace(self.partial, free, need)

    def _maybe_flush(self) -> None:
        if time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()

    def flush(self) -> None:
        self.file.flush()
        self._unflushed = 0
        self._last_flush = time.monotonic()

    def close(self, status: str = "complete") -> None:
        """Close every open stage, write the end status, mark the file cleanly closed, check it and
        rename it into place. ``problems`` lists what the check found (then the file stays at
        ``partial``)."""
        if not self.file.id.valid:
            return
        try:
            for sw in self.stages.values():
                if not sw.closed:
                    sw.close(status="interrupted" if status != "complete" else "complete")
            entry = self.file["entry"]
            entry.attrs["status"] = status
            entry.attrs["end_time"] = now_iso()
            self.file.attrs["clean_close"] = True
            self.file.flush()
            self.file.close()
            self.problems = self.verify()
            if not self.problems:
                try:
                    check_signals()     # a SIGINT/SIGTERM held while writing: the existing file stays
                except KeyboardInterrupt:
                    self.partial.unlink(missing_ok=True)
                    raise
                self._rename()
        finally:
            self._lock.release()

    def verify(self) -> list[str]:
        """Reopen the closed file read-only and compare it with what was written: every stage's
        datasets hold the samples appended, the events are all there, the file is marked clean."""
        problems = []
        try:
            with h5py.File(self.partial, "r") as f:
                if not bool(f.attrs.get("clean_close", False)):
                    problems.append("not marked as cleanly closed")
                n_ev = f["entry/events"].shape[0]
                if n_ev != self.n_events:
                    problems.append(f"{n_ev} events stored, {self.n_events} written")
                for name, sw in self.stages.items():
                    g = f[f"entry/stages/{name}"]
                    for key in ("sample_index", "time", *sw.channels, *(f"flags_{c}" for c in sw.channels)):
                        n = g[key].shape[0]
                        if n != sw.n_samples:
                            problems.append(f"stage {name!r} dataset {key!r}: {n} samples stored, "
                                            f"{sw.n_samples} written")
        except (OSError, KeyError) as exc:
            problems.append(f"cannot be read back ({exc})")
        return problems

    def _rename(self) -> None:
        try:
            if self.overwrite:
                os.replace(self.partial, self.path)
            else:  # never replace a file that appeared meanwhile: link fails if the name exists
                os.link(self.partial, self.path)
                self.partial.unlink()
        except OSError as exc:
            self.problems.append(f"cannot be renamed to {self.path} ({exc.strerror}); the run is in {self.partial}")
            return
        self.renamed = True

    def abandon(self) -> None:
        """Stop writing, keep the partial file as it is on disk (whole to its last flush, not marked
        clean) and release the lock: what a full disk leaves, for ``shakerlab import --recover``."""
        try:
            if self.file.id.valid:
                self.file.close()
        except Exception:  # noqa: BLE001 - the data on disk is what was flushed; closing may fail to add to it
            pass
        finally:
            self._lock.release()

    def discard(self) -> None:
        """Close and delete the partial file; ``path`` keeps whatever it held before."""
        try:
            if self.file.id.valid:
                self.file.close()
            self.partial.unlink(missing_ok=True)
        finally:
            self._lock.release()

    def n_recorded(self) -> int:
        """Samples appended over all stages."""
        return sum(sw.n_samples for sw in self.stages.values())


def remove_stale_import(partial: Path) -> str | None:
    """Delete ``partial`` if it is certainly the leftover of a killed ``shakerlab import`` (its writer
    process is gone; its sources can be imported again) and say so; anything else (a recording, a file
    that cannot be read) is kept. Called under the output lock, so no live shakerlab process writes it."""
    if not partial.is_file() or partial.is_symlink():
        return None
    try:
        with h5py.File(partial, "r") as f:
            source = f["entry"].attrs.get("source", "") if "entry" in f else ""
            pid = int(f.attrs.get("writer_pid", 0))
    except Exception:  # noqa: BLE001 - unreadable: not known to be an import's, kept
        return None
    if (source.decode() if isinstance(source, bytes) else str(source)) != "import":
        return None
    if pid:
        try:
            os.kill(pid, 0)
            return None         # that process still runs (under another name?): keep its file
        except ProcessLookupError:
            pass
        except PermissionError:
            return None
    partial.unlink()
    return f"removed {partial}, left by an import that was killed (pid {pid or 'unknown'}, no longer running)"

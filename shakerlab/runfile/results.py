"""Results written back into a run file (reprocessing), and clean copies of interrupted files."""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import h5py

from shakerlab import __version__
from shakerlab.errors import UserFacingError
from shakerlab.jsonsafe import clean
from shakerlab.output_files import (OutputLock, atomic_output, check_signals, disk_full, need_space, no_space,
                                    signals_deferred, temp_path)
from shakerlab.runfile.format import event_dtype, now_iso, open_read, str_dtype, text


def _refuse_unclean(path: Path) -> None:
    raise UserFacingError(
        f"{path} was not closed cleanly (the recording was interrupted); it stays readable but is never "
        f"opened for writing. Make a clean copy with `shakerlab import --recover {path} -o COPY.h5` "
        f"and write into the copy."
    )


def open_for_results(path: str | Path):
    """Open a cleanly closed run file in mode 'a' (h5py.File); refuse any other file."""
    path = Path(path)
    with open_read(path) as f:
        clean = bool(f.attrs.get("clean_close", False))
    if not clean:
        _refuse_unclean(path)
    return h5py.File(path, "a")


def add_result(path: str | Path, kind: str, payload: dict, text: str = "", attrs: dict | None = None) -> str:
    """Write one reprocessing result as ``entry/results/<kind>_NNN``; return the group path.

    ``payload`` is stored as JSON (``result_json``), ``text`` (e.g. the
    printed equation) as a string dataset, ``attrs`` as attributes of the group.
    The run file is never modified in place: under its output lock it is copied
    to a temporary file next to it, the result is written into the copy, and the
    copy is renamed over the file (a failure or a crash leaves the file as it was).
    """
    path = Path(path)
    with open_read(path) as f:
        clean_close = bool(f.attrs.get("clean_close", False))
    if not clean_close:
        _refuse_unclean(path)
    # a symbolic link is written through: the result goes into the file it points to, the link stays
    target = path.resolve()
    need_space(target, target.stat().st_size + (1 << 20), f"{target.name} was left as it was")
    with signals_deferred(), OutputLock(target):
        tmp = temp_path(target)
        try:
            shutil.copy2(target, tmp)
            check_signals()
            with h5py.File(tmp, "a") as f:
                results = f["entry/results"]
                i = 0
                while f"{kind}_{i:03d}" in results:
                    i += 1
                g = results.create_group(f"{kind}_{i:03d}")
                g.attrs.update({"NX_class": "NXcollection", "kind": kind, "created": now_iso(),
                                "software_version": __version__, **(attrs or {})})
                g.create_dataset("result_json", data=json.dumps(clean(payload, nan_to_none=False), sort_keys=True),
                                 dtype=str_dtype())
                if text:
                    g.create_dataset("text", data=str(text), dtype=str_dtype())
                name = g.name
            check_signals()
            os.replace(tmp, target)
        except (OSError, RuntimeError) as exc:
            if disk_full(exc):
                raise no_space(target, f"{target.name} was left as it was") from None
            raise UserFacingError(f"{path}: cannot write the result back ({exc}); the run file is unchanged") from None
        finally:
            tmp.unlink(missing_ok=True)
    return name


def read_results(path: str | Path) -> dict[str, dict]:
    """All results written back into the file: {group name: payload dict}."""
    with open_read(path) as f:
        return {name: json.loads(text(g["result_json"][()])) for name, g in f["entry/results"].items()}


def recover_copy(src: str | Path, dst: str | Path, overwrite: bool = False, losses: list | None = None) -> Path:
    """Copy an interrupted run file (read-only open) into a new, cleanly closed file.

    Salvaged object by object: every group, attribute and dataset that reads back is copied; a
    dataset that does not is rebuilt from the part that reads (its numeric fields, row by row where
    a variable-length string was not flushed) and an unreadable object is dropped. Each stage's
    per-sample datasets are cut to their common length (a crash can leave one dataset a block
    ahead of the others). What was lost is appended to ``losses``, recorded as an event and in the
    entry attribute ``recovery_json``; the copy's status is ``recovered``. The source is never
    opened for writing, and ``dst`` may not be the source (not even with ``overwrite``). The copy is
    made in a temporary file renamed to ``dst`` when complete (an existing ``dst`` is replaced only
    with ``overwrite``).
    """
    src, dst = Path(src), Path(dst)
    if dst.exists() and src.exists() and os.path.samefile(src, dst):
        raise UserFacingError(f"--recover {src} -o {dst}: the output is the input file; the input is never "
                              f"overwritten. Choose another -o name.")
    if dst.is_dir():
        raise UserFacingError(f"{dst}: is a directory, expected a run file name")
    if dst.exists() and not overwrite:
        raise UserFacingError(f"{dst}: file exists (choose another -o name or delete it)")
    lost: list[str] = []
    try:
        f = open_read(src)
    except (RuntimeError, ValueError, KeyError) as exc:
        raise UserFacingError(f"{src}: cannot be recovered, the file is damaged beyond its last flush "
                              f"({type(exc).__name__}: {exc}); nothing was written") from None
    with f, atomic_output(dst, overwrite=overwrite) as tmp:
        try:
            with h5py.File(tmp, "x") as g:
                _salvage_group(f, g, lost)
                if "entry" not in g or "stages" not in g["entry"]:
                    raise KeyError("no readable entry/stages group")
                entry = g["entry"]
                was = text(entry.attrs.get("status", ""))
                entry.attrs["status"] = "recovered"
                for sname in list(entry["stages"]):
                    _common_length(entry["stages"][sname], lost)
                if "events" not in entry:
                    entry.create_dataset("events", shape=(0,), maxshape=(None,), dtype=event_dtype(), chunks=(256,))
                    lost.append("/entry/events: the event log was unreadable; an empty one was made")
                ev = entry["events"]
                notes = [f"recovered copy of {src} (status was {was!r}, file not closed cleanly)"]
                notes += [f"recovery: {x}" for x in lost]
                n = ev.shape[0]
                ev.resize((n + len(notes),))
                for i, note in enumerate(notes):
                    ev[n + i] = (time.time(), float("nan"), "warning", note)
                entry.attrs["recovery_json"] = json.dumps({"source": str(src), "lost": lost})
                g.attrs["recovered_from"] = str(src)
                g.attrs["file_name"] = dst.name
                g.attrs["clean_close"] = True
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            if disk_full(exc):
                raise no_space(dst, f"{dst.name} was left as it was" if dst.exists() else "nothing was written") \
                    from None
            raise UserFacingError(f"{src}: cannot be recovered, the file is damaged beyond its last flush "
                                  f"({type(exc).__name__}: {exc}); nothing was written") from None
    if losses is not None:
        losses.extend(lost)
    return dst


SALVAGE_BLOCK = 1 << 17      # rows copied at a time when a dataset is rebuilt


def _salvage_group(src, dst, lost: list) -> None:
    """Copy ``src``'s attributes and members into ``dst``, each on its own (see recover_copy)."""
    for key in list(src.attrs):
        try:
            dst.attrs[key] = src.attrs[key]
        except (OSError, KeyError, ValueError, RuntimeError, TypeError):
            lost.append(f"attribute {key!r} of {src.name}: unreadable, dropped")
    try:
        names = list(src)
    except (OSError, KeyError, RuntimeError) as exc:
        lost.append(f"{src.name}: its members cannot be listed ({exc}); dropped")
        return
    for name in names:
        where = f"{src.name.rstrip('/')}/{name}"
        try:
            obj = src[name]
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            lost.append(f"{where}: unreadable ({exc}), dropped")
            continue
        if isinstance(obj, h5py.Group):
            _salvage_group(obj, dst.create_group(name), lost)
            continue
        try:
            src.copy(obj, dst, name=name)
            continue
        except (OSError, KeyError, ValueError, RuntimeError, TypeError) as exc:
            if name in dst:
                del dst[name]
            why = str(exc)
        _rebuild_dataset(obj, dst, name, where, lost, why)


def _rebuild_dataset(ds, dst, name: str, where: str, lost: list, why: str) -> None:
    """A dataset h5py cannot copy whole: its readable rows, a string field that does not read left empty."""
    try:
        if ds.ndim != 1:
            dst.create_dataset(name, data=ds[()], dtype=ds.dtype)
            _copy_attrs(ds, dst[name], lost)
            return
        out = dst.create_dataset(name, shape=(0,), maxshape=(None,), dtype=ds.dtype,
                                 chunks=ds.chunks or (min(max(ds.shape[0], 1), 8192),))
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as exc:
        lost.append(f"{where}: unreadable ({exc}), dropped")
        return
    _copy_attrs(ds, out, lost)
    n_total = ds.shape[0]
    fields = ds.dtype.names or ()
    numeric = [k for k in fields if ds.dtype[k].kind != "O"]
    strings = [k for k in fields if ds.dtype[k].kind == "O"]
    blanked = 0
    n = 0
    while n < n_total:
        m = min(n + SALVAGE_BLOCK, n_total)
        try:
            block = ds[n:m]
        except (OSError, ValueError, RuntimeError, TypeError):
            block = _rows_without_strings(ds, n, m, numeric, strings) if fields else None
            if block is None:
                break
            blanked += int(block[1])
            block = block[0]
        out.resize((m,))
        out[n:m] = block
        n = m
    if n < n_total:
        lost.append(f"{where}: rows {n}..{n_total - 1} of {n_total} unreadable, dropped")
    elif not blanked:
        lost.append(f"{where}: damaged as stored ({why}); rebuilt from its {n} row(s), every row kept")
    if blanked:
        lost.append(f"{where}: {blanked} row(s) kept with the field(s) {', '.join(strings)} empty (their text "
                    f"was not flushed before the crash)")


def _rows_without_strings(ds, n: int, m: int, numeric: list, strings: list):
    """(rows n..m-1 with every readable string, how many rows had a string left empty), or None when
    even the numeric fields do not read."""
    import numpy as np  # lazy: numpy only when a compound dataset is rebuilt

    try:
        nums = ds.fields(numeric)[n:m] if numeric else None
    except (OSError, ValueError, RuntimeError, TypeError):
        return None
    rows = np.zeros(m - n, dtype=ds.dtype)
    for k in numeric:
        rows[k] = nums[k] if len(numeric) > 1 else nums
    blanked = 0
    for i in range(n, m):
        for k in strings:
            try:
                rows[k][i - n] = ds.fields(k)[i]
            except (OSError, ValueError, RuntimeError, TypeError):
                rows[k][i - n] = ""
                blanked += 1
    return rows, blanked


def _copy_attrs(src, dst, lost: list) -> None:
    for key in list(src.attrs):
        try:
            dst.attrs[key] = src.attrs[key]
        except (OSError, KeyError, ValueError, RuntimeError, TypeError):
            lost.append(f"attribute {key!r} of {src.name}: unreadable, dropped")


# a stage's datasets that are not one row per sample
NOT_PER_SAMPLE = ("steps", "control")


def _common_length(stage, lost: list) -> None:
    """Cut a stage's per-sample datasets to their common length and make its attributes agree."""
    per_sample = [k for k in stage if isinstance(stage[k], h5py.Dataset) and k not in NOT_PER_SAMPLE
                  and stage[k].ndim == 1]
    if per_sample:
        n = min(stage[k].shape[0] for k in per_sample)
        for k in per_sample:
            extra = stage[k].shape[0] - n
            if extra:
                lost.append(f"{stage.name}/{k}: {extra} sample(s) beyond the stage's common length {n} dropped "
                            f"(written after the last complete block)")
                if stage[k].maxshape[0] is None:
                    stage[k].resize((n,))
                else:
                    data, attrs = stage[k][:n], dict(stage[k].attrs)
                    del stage[k]
                    stage.create_dataset(k, data=data)
                    stage[k].attrs.update(attrs)
        stage.attrs["n_samples"] = n
        stage.attrs["end_index"] = int(stage.attrs.get("start_index", 0)) + n
    if text(stage.attrs.get("status", "")) == "recording":
        stage.attrs["status"] = "interrupted"


RUN_FILE_SUFFIXES = (".h5", ".hdf5", ".nxs")


def find_result(path: str | Path, kind: str, settings_hash: str):
    """The newest stored result of ``kind`` computed with ``settings_hash``: (group name, payload) or None."""
    found = None
    for name, payload in read_results(path).items():
        if name.startswith(kind) and (payload.get("reprocess") or {}).get("settings_hash") == settings_hash:
            found = (name, payload)
    return found


def store_result(path: str | Path, kind: str, payload: dict, text: str = "",
               settings_hash: str | None = None) -> tuple[str | None, str]:
    """Store a result in a run file where that is safe: (group name or None, a note saying what happened).

    Nothing is written into a file that is not an HDF5 run file or was not closed cleanly. With
    ``settings_hash``, a result of the same kind and hash already stored is reused (its group is
    returned) and the hash is kept as the group's ``settings_hash`` attribute."""
    path = Path(path)
    if path.suffix not in RUN_FILE_SUFFIXES:
        return None, "not written back: only .h5 run files hold results"
    try:
        with open_read(path) as f:
            clean_close = bool(f.attrs.get("clean_close", False))
        hit = find_result(path, kind, settings_hash) if settings_hash is not None and clean_close else None
    except (UserFacingError, OSError, KeyError, ValueError) as exc:
        return None, f"not written back: cannot read the run file ({exc})"
    if not clean_close:
        return None, ("not written back: the run file was not closed cleanly "
                      "(make a copy with `shakerlab import --recover`)")
    if settings_hash is not None:
        if hit is not None:
            return hit[0], f"not written again: same settings as the stored result entry/results/{hit[0]}, nothing new written"
    try:
        group = add_result(path, kind, payload, text=text,
                           attrs={"settings_hash": settings_hash} if settings_hash is not None else None)
    except UserFacingError as exc:
        return None, f"not written back: {exc}"
    name = group.rsplit("/", 1)[-1]
    where = f" {path.resolve()} (the target of the link {path})" if path.is_symlink() else ""
    return name, f"written into the run file{where} as entry/results/{name}"

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
from shakerlab.output_files import OutputLock, atomic_output, temp_path
from shakerlab.runfile.format import now_iso, open_read, str_dtype, text


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
    with OutputLock(path):
        tmp = temp_path(path)
        try:
            shutil.copy2(path, tmp)
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
            os.replace(tmp, path)
        except OSError as exc:
            raise UserFacingError(f"{path}: cannot write the result back ({exc}); the run file is unchanged") from None
        finally:
            tmp.unlink(missing_ok=True)
    return name


def read_results(path: str | Path) -> dict[str, dict]:
    """All results written back into the file: {group name: payload dict}."""
    with open_read(path) as f:
        return {name: json.loads(text(g["result_json"][()])) for name, g in f["entry/results"].items()}


def recover_copy(src: str | Path, dst: str | Path, overwrite: bool = False) -> Path:
    """Copy an interrupted run file (read-only open) into a new, cleanly closed file.

    Everything up to the source's last flush is copied; the copy's status is
    ``recovered`` and an event records where it came from. The source is
    never opened for writing, and ``dst`` may not be the source (not even with
    ``overwrite``). The copy is made in a temporary file renamed to ``dst``
    when complete (an existing ``dst`` is replaced only with ``overwrite``).
    """
    src, dst = Path(src), Path(dst)
    if dst.exists() and src.exists() and os.path.samefile(src, dst):
        raise UserFacingError(f"--recover {src} -o {dst}: the output is the input file; the input is never "
                              f"overwritten. Choose another -o name.")
    if dst.is_dir():
        raise UserFacingError(f"{dst}: is a directory, expected a run file name")
    if dst.exists() and not overwrite:
        raise UserFacingError(f"{dst}: file exists (choose another -o name or delete it)")
    with open_read(src) as f, atomic_output(dst, overwrite=overwrite) as tmp:
        try:
            with h5py.File(tmp, "x") as g:
                for key, value in f.attrs.items():
                    g.attrs[key] = value
                for name in f:
                    f.copy(f[name], g, name=name)
                was = text(g["entry"].attrs.get("status", ""))
                g["entry"].attrs["status"] = "recovered"
                for sname in g["entry/stages"]:
                    st = g["entry/stages"][sname]
                    if text(st.attrs.get("status", "")) == "recording":
                        st.attrs["status"] = "interrupted"
                ev = g["entry/events"]
                n = ev.shape[0]
                ev.resize((n + 1,))
                ev[n] = (time.time(), float("nan"), "warning",
                         f"recovered copy of {src} (status was {was!r}, file not closed cleanly)")
                g.attrs["recovered_from"] = str(src)
                g.attrs["file_name"] = dst.name
                g.attrs["clean_close"] = True
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            raise UserFacingError(f"{src}: cannot be recovered, the file is damaged beyond its last flush "
                                  f"({type(exc).__name__}: {exc}); nothing was written") from None
    return dst


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
    return name, f"written into the run file as entry/results/{name}"

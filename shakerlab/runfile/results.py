"""Results written back into a run file (reprocessing), and clean copies of interrupted files."""
from __future__ import annotations

import json
import time
from pathlib import Path

import h5py

from shakerlab import __version__
from shakerlab.errors import UserFacingError
from shakerlab.jsonsafe import clean
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
        g.attrs.update({"NX_class": "NXcollection", "kind": kind, "created": now_iso(),
                        "software_version": __version__})
        g.create_dataset("result_json", data=json.dumps(clean(payload, nan_to_none=False), sort_keys=True), dtype=str_dtype())
        if text:
            g.create_dataset("text", data=str(text), dtype=str_dtype())
        return g.name


def read_results(path: str | Path) -> dict[str, dict]:
    """All results written back into the file: {group name: payload dict}."""
    with open_read(path) as f:
        return {name: json.loads(text(g["result_json"][()])) for name, g in f["entry/results"].items()}


def recover_copy(src: str | Path, dst: str | Path) -> Path:
    """Copy an interrupted run file (read-only open) into a new, cleanly closed file.

    Everything up to the source's last flush is copied; the copy's status is
    ``recovered`` and an event records where it came from. The source is
    never opened for writing.
    """
    src, dst = Path(src), Path(dst)
    if dst.exists():
        raise UserFacingError(f"{dst}: file exists (choose another -o name or delete it)")
    with open_read(src) as f, h5py.File(dst, "w") as g:
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
        g.attrs["clean_close"] = True
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
    with open_read(path) as f:
        clean_close = bool(f.attrs.get("clean_close", False))
    if not clean_close:
        return None, ("not written back: the run file was not closed cleanly "
                      "(make a copy with `shakerlab import --recover`)")
    if settings_hash is not None:
        hit = find_result(path, kind, settings_hash)
        if hit is not None:
            return hit[0], f"not written again: same settings as the stored result entry/results/{hit[0]}, nothing new written"
    group = add_result(path, kind, payload, text=text)
    if settings_hash is not None:
        with open_for_results(path) as f:
            f[group].attrs["settings_hash"] = settings_hash
    name = group.rsplit("/", 1)[-1]
    return name, f"written into the run file as entry/results/{name}"

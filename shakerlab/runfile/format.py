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

Crash safety: the file is recorded as ``RUN.h5.partial`` and renamed to ``RUN.h5`` when it is
closed (``shakerlab.output_files``); it is written with the default libver (never SWMR),
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
from pathlib import Path

import h5py
import numpy as np

from shakerlab.errors import UserFacingError
from shakerlab.jsonsafe import clean

FORMAT = "shakerlab-run"
FORMAT_VERSION = 1
CHUNK = 8192
LEVELS = ("debug", "info", "warning", "error", "critical")

STR_DTYPE = h5py.string_dtype("utf-8")


def str_dtype():
    return STR_DTYPE


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def set_scalar_attrs(obj, settings: dict) -> None:
    """Store settings as JSON, plus each scalar as its own attribute (handy in HDFView)."""
    settings = clean(settings, nan_to_none=False)
    obj.attrs["settings_json"] = json.dumps(settings, sort_keys=True)
    for key, value in settings.items():
        if isinstance(value, (bool, int, float, str)) and key not in ("settings_json",):
            obj.attrs[key] = value


def step_dtype():
    return np.dtype(
        [("sample_index", "<i8"), ("amplitude_vpp", "<f8"), ("frequency_hz", "<f8"), ("label", str_dtype())]
    )


def event_dtype():
    return np.dtype(
        [("wall_time", "<f8"), ("run_time", "<f8"), ("level", str_dtype()), ("message", str_dtype())]
    )


def open_read(path: str | Path):
    path = Path(path)
    if not path.exists():
        partial = path.with_name(path.name + ".partial")
        if partial.exists():
            raise UserFacingError(f"{path}: no such file; {partial} holds its recording, interrupted (or still "
                                  f"running): `shakerlab import --recover {partial} -o {path}` makes the run file")
        raise UserFacingError(f"{path}: no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise UserFacingError(f"{path}: not a readable HDF5 file ({exc})") from None
    if f.attrs.get("format") != FORMAT or "entry" not in f:
        f.close()
        raise UserFacingError(f"{path}: not a shakerlab run file (root attribute 'format' is not {FORMAT!r})")
    return f


def text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def stage_order(f) -> list[str]:
    stages = f["entry/stages"]
    order = json.loads(text(stages.attrs.get("order", "[]")))
    return [n for n in order if n in stages] + [n for n in stages if n not in order]



"""LMS Test.Lab MATLAB exports (MAT v5, scipy.io.loadmat).

Each top-level struct is a channel (group): ``x_values`` holds the time axis (``start_value``,
``increment``, ``number_of_values``), ``y_values.values`` the samples (N, or N x k for a
group of k channels: address column j as ``NAME[j]``, from 0).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from shakerlab.errors import UserFacingError
from shakerlab.importers.signal import Signal


def _field(struct, name: str, path, channel: str):
    try:
        return struct[name][0, 0]
    except (KeyError, ValueError, IndexError, TypeError):
        raise UserFacingError(f"{path}: channel {channel!r} is not an LMS Test.Lab export struct "
                              f"(no field {name!r})") from None


def read_signals(path: str | Path) -> list[Signal]:
    import scipy.io  # heavy: scipy.io, loaded when a MAT file is imported

    path = Path(path)
    if not path.exists():
        raise UserFacingError(f"{path}: no such file")
    try:
        mat = scipy.io.loadmat(path)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's problem
        raise UserFacingError(f"{path}: not a readable MATLAB file ({exc})") from None
    out = []
    for name, value in mat.items():
        if name.startswith("__"):
            continue
        if not (isinstance(value, np.ndarray) and value.dtype.names and "y_values" in value.dtype.names):
            continue
        s = value[0, 0]
        xv = _field(s, "x_values", path, name)
        yv = _field(s, "y_values", path, name)
        try:
            t0 = float(np.ravel(xv["start_value"][0, 0])[0])
            inc = float(np.ravel(xv["increment"][0, 0])[0])
            count = int(np.ravel(xv["number_of_values"][0, 0])[0])
            values = np.asarray(yv["values"], float)
        except (KeyError, ValueError, IndexError, TypeError) as exc:
            raise UserFacingError(f"{path}: channel {name!r}: unreadable time axis or values ({exc})") from None
        if not inc > 0:
            raise UserFacingError(f"{path}: channel {name!r}: time increment {inc!r} is not positive")
        if values.ndim != 2 and values.ndim != 1:
            raise UserFacingError(f"{path}: channel {name!r}: values of shape {values.shape}, expected N or N x k")
        if values.ndim == 2 and 1 in values.shape:
            values = values.ravel()
        columns = [(name, values)] if values.ndim == 1 else [(f"{name}[{j}]", values[:, j])
                                                             for j in range(values.shape[1])]
        for cname, v in columns:
            if v.size != count:
                raise UserFacingError(f"{path}: channel {cname!r} holds {v.size} values, its time axis "
                                      f"says {count}")
            out.append(Signal(name=cname, values=v, source=str(path), t0=t0, dt=inc))
    if not out:
        raise UserFacingError(f"{path}: no LMS Test.Lab channel struct (with x_values and y_values) in the file")
    return out

"""UFF/UNV dataset 58 (function at nodal DOF; pyuff, the ``formats`` extra).

A channel is the record's ``id1`` text, or ``#K`` for the K-th dataset 58 of the file (from 0).
The abscissa must be evenly spaced (``abscissa_spacing`` 1: ``abscissa_min`` and
``abscissa_inc``); an uneven abscissa goes through the time-base check like a CSV time column.
The ordinate's specific data type says the quantity (8 displacement, 11 velocity, 12
acceleration), used when the mapping does not give one.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from shakerlab.errors import UserFacingError
from shakerlab.importers.signal import Signal
from shakerlab.quantities import ACCELERATION, DISPLACEMENT, VELOCITY

ORDINATE = {8: DISPLACEMENT, 11: VELOCITY, 12: ACCELERATION}


def read_signals(path: str | Path) -> list[Signal]:
    try:
        import pyuff  # optional: the formats extra (pip install 'shakerlab[formats]')
    except ImportError:
        raise UserFacingError(f"{path}: reading UFF needs pyuff: pip install 'shakerlab[formats]'") from None
    path = Path(path)
    if not path.exists():
        raise UserFacingError(f"{path}: no such file")
    try:
        sets = pyuff.UFF(str(path)).read_sets()
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's problem
        raise UserFacingError(f"{path}: not a readable UFF file ({exc})") from None
    if isinstance(sets, dict):
        sets = [sets]
    out = []
    k = 0
    for ds in sets:
        if int(ds.get("type", 0)) != 58:
            continue
        values = np.asarray(ds.get("data"), float)
        if values.ndim != 1 or np.iscomplexobj(ds.get("data")):
            raise UserFacingError(f"{path}: dataset 58 #{k} is not a real time series")
        q = ORDINATE.get(int(ds.get("ordinate_spec_data_type", 0)))
        sig = dict(values=values, source=str(path), quantity=q)
        if int(ds.get("abscissa_spacing", 1)) == 1:
            sig.update(t0=float(ds.get("abscissa_min", 0.0)), dt=float(ds["abscissa_inc"]))
        else:
            sig.update(time=np.asarray(ds["x"], float))
        names = [f"#{k}"] + ([str(ds["id1"]).strip()] if str(ds.get("id1", "")).strip() else [])
        for name in names:
            out.append(Signal(name=name, **sig))
        k += 1
    if not out:
        raise UserFacingError(f"{path}: no dataset 58 (time function) in the UFF file")
    return out

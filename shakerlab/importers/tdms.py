"""NI TDMS files (npTDMS, the ``formats`` extra).

A channel is ``GROUP/CHANNEL`` (or ``CHANNEL`` when unique). Its time base is the waveform
properties ``wf_start_offset`` and ``wf_increment`` when present; otherwise map a time
channel (``--map t=GROUP/Time``) or declare the rate with ``--fs``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from shakerlab.errors import UserFacingError
from shakerlab.importers.signal import Signal


def read_signals(path: str | Path) -> list[Signal]:
    try:
        from nptdms import TdmsFile  # optional: the formats extra (pip install 'shakerlab[formats]')
    except ImportError:
        raise UserFacingError(f"{path}: reading TDMS needs npTDMS: pip install 'shakerlab[formats]'") from None
    path = Path(path)
    if not path.exists():
        raise UserFacingError(f"{path}: no such file")
    try:
        f = TdmsFile.read(path)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's problem
        raise UserFacingError(f"{path}: not a readable TDMS file ({exc})") from None
    out = []
    for group in f.groups():
        for ch in group.channels():
            data = ch[:]
            if not np.issubdtype(np.asarray(data).dtype, np.number):
                continue
            props = ch.properties
            inc = props.get("wf_increment")
            out.append(Signal(name=f"{group.name}/{ch.name}", values=np.asarray(data, float), source=str(path),
                              t0=float(props.get("wf_start_offset", 0.0)), dt=None if inc is None else float(inc)))
    if not out:
        raise UserFacingError(f"{path}: no numeric channel in the TDMS file")
    # CHANNEL alone addresses a channel whose name is unique in the file
    names = [s.name.split("/", 1)[1] for s in out]
    for s, short in zip(list(out), names):
        if names.count(short) == 1:
            out.append(Signal(name=short, values=s.values, source=s.source, t0=s.t0, dt=s.dt))
    return out

"""The exciter between a recorded drive and the force it makes.

A lab often records the amplifier's voltage, not a force: the shaker turns that drive into
force through its own electromechanics. Two departures from a constant gain are common and
cheap to model, and both show in the real bolted-beam records (docs/real-data.md):

- an even-order distortion (reluctance force, a force factor that varies along the stroke):
  the force follows u + u2 u^2, so a pure tone drives the structure at twice its frequency
  too (the 9.5 Hz sine excites the 18.6 Hz mode);
- a low-frequency roll-off: a first-order high-pass s / (s + hp), hp the corner in rad/s,
  which leads the phase at low frequency (the chirps' +18 degrees at 5 Hz).

The model is driven by g HP_hp(u + u2 u^2) (:func:`drive_force`); with u2 = hp = 0 by g u,
as before. Used only under force excitation (under base excitation u is the measured base
acceleration, not a drive).
"""
from __future__ import annotations

import numpy as np


def drive_force(u: np.ndarray, dt: float, u2: float = 0.0, hp: float = 0.0) -> np.ndarray:
    """HP_hp(u + u2 u^2): the first-order high-pass s / (s + |hp|) by the bilinear transform at
    step ``dt``, started as if the drive had held u[0] before the record (so it starts at 0, as
    a high-pass of a constant does). hp = 0: no high-pass; u2 = 0: no distortion."""
    u = np.asarray(u, float)
    f = u + u2 * u * u if u2 else u
    hp = abs(float(hp))
    if hp == 0.0:
        return f
    from scipy.signal import lfilter, lfilter_zi  # heavy: scipy.signal costs ~0.4 CPU-s to import; only this path needs it
    k = 2.0 / dt
    b = np.array([k, -k]) / (k + hp)
    a = np.array([1.0, (hp - k) / (k + hp)])
    return lfilter(b, a, f, zi=lfilter_zi(b, a) * f[0])[0]

"""The time base of an imported stage: uniform sampling is checked, never assumed.

A time column is accepted when every time lies within its printed precision (plus 1e-6 of
a step: far below what recon can see) of a uniform grid fitted by least squares. A column
uniform to floating-point precision is stored as it is; one that is uniform only within its
printed precision (10 significant digits, say) is stored as the fitted grid. Anything else is
jitter or a gap: refused with the file, the line (or sample) of the worst step and the
measured jitter, unless the user asks for ``--resample`` (cubic interpolation of every
channel onto the uniform grid at the median rate or ``--fs``; gaps are refused even then,
since interpolating across missing samples would invent motion).
"""
from __future__ import annotations

import numpy as np

from shakerlab.errors import UserFacingError

FLOAT_UNIFORM = 5e-7        # step deviation (relative) stored as is: recon accepts 1e-6
HARMLESS = 1e-6             # deviation from the grid, in steps, that is never refused
GAP = 2.5                   # a step this many median steps long is a gap


def check(sig, resample: bool = False, fs: float | None = None):
    """(time from 0, fs, info, resample_to) for a Signal with an explicit time column.

    ``resample_to`` is None, or the uniform grid (from 0) the channels must be interpolated onto."""
    t = np.asarray(sig.time, float)
    n = t.size
    steps = np.diff(t)
    med = float(np.median(steps))
    dev = np.abs(steps - med) / med
    jitter = float(dev.max())
    info = {"sampling_jitter": jitter}
    if jitter <= FLOAT_UNIFORM and fs is None:
        return t - t[0], 1.0 / med, info, None
    i = np.arange(n) - 0.5 * (n - 1)
    dt = float(i @ (t - t.mean()) / (i @ i))
    resid = t - (t.mean() + dt * i)
    quantum = np.zeros(n) if sig.quantum is None else np.asarray(sig.quantum, float)
    allowed = 0.6 * quantum + HARMLESS * dt + 64 * np.finfo(float).eps * np.abs(t).max()
    k = int(np.argmax(dev))
    gap = steps[k] > GAP * med
    if fs is not None and not resample:
        info.update(time_base=f"declared --fs {fs:g} Hz (the file's median rate {1 / med:.9g} Hz)")
        return np.arange(n) / fs, float(fs), info, None
    if np.all(np.abs(resid) <= allowed):
        info.update(time_base="uniform within the printed precision; stored as the fitted grid",
                    max_rounding_s=float(np.abs(resid).max()))
        return np.arange(n) * dt, 1.0 / dt, info, None
    what = (f"a gap of {steps[k]:.6g} s (about {steps[k] / med - 1:.0f} sample(s) missing)" if gap else
            f"a time step of {steps[k]:.6g} s")
    prec = float(np.median(quantum)) if quantum.any() else 0.0
    msg = (f"{sig.source}: {sig.where(k + 1)}: {what} where the median step is {med:.6g} s; the sampling is "
           f"not uniform (jitter {100 * jitter:.3g} % of a step, largest deviation from a uniform grid "
           f"{np.abs(resid).max():.3g} s{f', time printed to {prec:.3g} s' if prec else ''})")
    if gap:
        raise UserFacingError(msg + ": cut the record at the gap or fill it in the source; --resample "
                                    "does not interpolate across missing samples")
    if not resample:
        raise UserFacingError(msg + ": export the record on a uniform time base, or give --resample to "
                                    "interpolate it onto a uniform grid (or --fs to declare the rate)")
    rate = float(fs) if fs is not None else 1.0 / med
    grid = np.arange(int(np.floor((t[-1] - t[0]) * rate + 1e-9)) + 1) / rate
    info.update(time_base=f"resampled (cubic) onto a uniform grid at {rate:.9g} Hz (--resample)")
    return grid, rate, info, t - t[0]


def interpolate(values: np.ndarray, t_from: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Cubic-spline values of a channel at ``grid`` (both times from the first sample)."""
    from scipy.interpolate import CubicSpline  # heavy: scipy.interpolate, only with --resample

    return CubicSpline(t_from, values)(grid)

"""Measures the protocol decides on: harmonic amplitudes, distortion, gain, loop loss factor.

All work on a window of steady-state samples at a known drive frequency
(least-squares fit of a mean and the first harmonics over a whole number of
periods), so they need no filtering and no FFT leakage correction.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np


def harmonics(x: np.ndarray, fs: float, f: float, n_harmonics: int = 5) -> np.ndarray:
    """Complex amplitudes ``X_k`` (k = 1..n) with ``x ~ mean + sum Re(X_k e^{i k w t})``.

    Uses the longest whole number of periods at the end of ``x``
    (all of ``x`` when it is shorter than one period).
    """
    x = np.asarray(x, dtype=float)
    period = fs / f
    n_periods = math.floor(x.size / period)
    n = int(round(n_periods * period)) if n_periods >= 1 else x.size
    x = x[x.size - n:]
    t = np.arange(n) / fs
    w = 2 * math.pi * f
    cols = [np.ones(n)]
    for k in range(1, n_harmonics + 1):
        cols += [np.cos(k * w * t), np.sin(k * w * t)]
    a = np.column_stack(cols)
    coef, *_ = np.linalg.lstsq(a, x, rcond=None)
    c, s = coef[1::2], coef[2::2]
    return c - 1j * s  # Re((c - i s) e^{iwt}) = c cos + s sin


@dataclass
class Response:
    """Steady-state response at one drive frequency (amplitudes are fundamental peak values, m)."""

    frequency_hz: float
    base_amplitude: float
    tip_amplitude: float
    relative_amplitude: float
    transmissibility: float       # |X_tip| / |X_base| (fundamental)
    gain: float                   # |Y| / |X_base|, y = x_tip - x_base
    phase_deg: float              # phase of Y relative to X_base
    thd: float                    # sqrt(sum_{k>=2} |Y_k|^2) / |Y_1|
    loss_factor: float            # loop energy / (pi |R_1| |Y_1|), R = -x_tip'' (restoring force per mass)
    peak_base: float              # max |x_base - mean| in the window
    peak_tip: float
    peak_relative: float

    def to_dict(self) -> dict:
        return {k: float(v) for k, v in asdict(self).items()}


def loop_energy(y_h: np.ndarray, r_h: np.ndarray, n_grid: int = 720) -> float:
    """Energy per cycle of the loop r(y) from complex harmonics (area enclosed, >0 if dissipative)."""
    phi = np.linspace(0.0, 2 * math.pi, n_grid, endpoint=False)
    k = np.arange(1, len(y_h) + 1)[:, None]
    e = np.exp(1j * k * phi[None, :])
    dy = np.real(1j * k * y_h[:, None] * e).sum(axis=0)  # dy/dphi
    r = np.real(r_h[:, None] * e).sum(axis=0)
    return float(np.sum(r * dy) * (2 * math.pi / n_grid))


def response(x_base: np.ndarray, x_tip: np.ndarray, fs: float, f: float, n_harmonics: int = 5) -> Response:
    """Analyse a steady-state window of both channels at drive frequency ``f``."""
    x_base = np.asarray(x_base, dtype=float)
    x_tip = np.asarray(x_tip, dtype=float)
    y = x_tip - x_base
    hb = harmonics(x_base, fs, f, n_harmonics)
    ht = harmonics(x_tip, fs, f, n_harmonics)
    hy = ht - hb
    w = 2 * math.pi * f
    k = np.arange(1, n_harmonics + 1)
    r_h = (k * w) ** 2 * ht  # -x_tip'' per harmonic
    b1, t1, y1 = abs(hb[0]), abs(ht[0]), abs(hy[0])
    energy = loop_energy(hy, r_h)
    r1 = abs(r_h[0])
    tiny = 1e-300
    return Response(
        frequency_hz=f,
        base_amplitude=b1,
        tip_amplitude=t1,
        relative_amplitude=y1,
        transmissibility=t1 / max(b1, tiny),
        gain=y1 / max(b1, tiny),
        phase_deg=math.degrees(np.angle(hy[0] / hb[0])) if b1 > 0 else float("nan"),
        thd=float(np.sqrt(np.sum(np.abs(hy[1:]) ** 2)) / max(y1, tiny)),
        loss_factor=energy / max(math.pi * r1 * y1, tiny),
        peak_base=float(np.max(np.abs(x_base - x_base.mean()))),
        peak_tip=float(np.max(np.abs(x_tip - x_tip.mean()))),
        peak_relative=float(np.max(np.abs(y - y.mean()))),
    )


def gain_change(before: Response, after: Response) -> float:
    """|G_after - G_before| / |G_after|, G = gain e^{i phase}: how far the relative motion's
    fundamental (amplitude and phase against the base) moved between two windows at the same drive.
    A transient from the last change of level (the free response at the resonance, beating with
    the drive) moves it; a steady response leaves it where it is."""
    ga = after.gain * np.exp(1j * np.radians(after.phase_deg))
    gb = before.gain * np.exp(1j * np.radians(before.phase_deg))
    if not (np.isfinite(ga) and np.isfinite(gb)) or after.gain <= 0:
        return float("inf")
    return float(abs(ga - gb) / after.gain)


def peak_frequency(freqs, values) -> float:
    """Frequency of the maximum of ``values`` (a resonance curve), refined between grid points.

    Near a resonance 1/|H|^2 is close to a quadratic in f^2 (exactly so for
    a single-degree-of-freedom system), so a parabola through the top three
    points in those coordinates places the peak between grid points. At an end
    of the grid the end point itself is returned.
    """
    f = np.asarray(freqs, dtype=float)
    v = np.asarray(values, dtype=float)
    f, inverse = np.unique(f, return_inverse=True)     # repeated frequencies: mean value
    v = np.bincount(inverse, weights=v) / np.bincount(inverse)
    i = int(np.argmax(v))
    if i == 0 or i == f.size - 1:
        return float(f[i])
    u = (f[i - 1:i + 2] / f[i]) ** 2 - 1.0        # scaled for a well-conditioned fit
    q = (v[i] / v[i - 1:i + 2]) ** 2
    a, b, _ = np.linalg.solve(np.vander(u, 3), q)  # the parabola through the three points
    if a <= 0:
        return float(f[i])
    return float(f[i] * np.sqrt(1.0 + np.clip(-b / (2 * a), u[0], u[2])))

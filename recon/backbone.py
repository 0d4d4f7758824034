"""Backbone and damping against amplitude from a free decay (a ring-down).

A weakly nonlinear mode rings down along its backbone: as the envelope A(t) shrinks, the
instantaneous frequency and the decay rate follow the amplitude. Both are read from the analytic
signal of the mode's response (the Hilbert-transform free-vibration analysis of structural
dynamics):

- the record is band-passed around the mode (zero-phase Butterworth, ``f_mode (1 +- band)``),
  so that other modes and a drive far from the mode do not enter;
- the analytic signal gives the envelope A and the unwrapped phase phi;
- phi' and (ln A)' are Savitzky-Golay derivatives over ``smooth_s`` (ten periods by default);
- frequency = phi' / 2 pi (the damped frequency); damping ratio = s / sqrt(s^2 + phi'^2) with
  s = -(ln A)', exact for a linear mode x = A0 exp(-zeta w_n t) cos(w_d t).

Applied to the same stretch of a recording and of a model's simulation of it, it shows where a
model's amplitude dependence departs from the structure's (docs/real-data.md: the bolted beam).
Works on any record, not only a free decay, wherever the mode's own ringing dominates the band.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shakerlab.errors import UserFacingError


@dataclass
class Backbone:
    """Per sample of the analysed stretch: time [s], envelope (units of y), frequency [Hz], damping ratio."""
    t: np.ndarray
    amplitude: np.ndarray
    frequency: np.ndarray
    damping: np.ndarray

    def binned(self, edges, min_samples: int = 50) -> list[dict]:
        """Medians of frequency and damping per amplitude bin [edges[i], edges[i+1]); a bin with
        fewer than ``min_samples`` samples gets None."""
        out = []
        for lo, hi in zip(edges[:-1], edges[1:]):
            k = (self.amplitude >= lo) & (self.amplitude < hi)
            n = int(k.sum())
            ok = n >= min_samples
            out.append({"amplitude_low": float(lo), "amplitude_high": float(hi), "samples": n,
                        "frequency_hz": float(np.median(self.frequency[k])) if ok else None,
                        "damping_ratio": float(np.median(self.damping[k])) if ok else None})
        return out

    def at(self, amplitude: float, rel_width: float = 0.1, min_samples: int = 50) -> tuple:
        """(frequency, damping) medians over the samples whose envelope is within ``rel_width`` of
        ``amplitude``; (None, None) where the decay does not pass there."""
        b = self.binned([amplitude * (1 - rel_width), amplitude * (1 + rel_width)], min_samples)[0]
        return b["frequency_hz"], b["damping_ratio"]


def free_decay_backbone(t, y, f_mode: float, t_from: float | None = None, t_to: float | None = None,
                        band: float = 0.4, smooth_s: float | None = None) -> Backbone:
    """The backbone of the mode near ``f_mode`` [Hz] in the record (t, y), over t_from <= t <= t_to
    (None: the whole record, less the filter's and the smoother's edges). See the module doc."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    if t.ndim != 1 or t.shape != y.shape or t.size < 16:
        raise UserFacingError(f"backbone: t and y must be 1-D arrays of the same length (>= 16 samples), "
                              f"got {t.shape} and {y.shape}")
    if not np.all(np.isfinite(y)):
        raise UserFacingError("backbone: the record holds non-finite samples")
    dt = float(t[1] - t[0])
    fs = 1.0 / dt
    if not 0.0 < band < 1.0:
        raise UserFacingError(f"backbone: band must lie in (0, 1) (the pass band is f_mode (1 +- band)), got {band}")
    if not (np.isfinite(f_mode) and f_mode > 0.0):
        raise UserFacingError(f"backbone: the mode's frequency must be a positive number of Hz, got {f_mode}")
    if not f_mode * (1.0 + band) < 0.5 * fs:
        raise UserFacingError(f"backbone: the mode's band {f_mode * (1 - band):.4g}-{f_mode * (1 + band):.4g} Hz "
                              f"does not lie below the Nyquist frequency {0.5 * fs:.4g} Hz")
    smooth_s = 10.0 / f_mode if smooth_s is None else float(smooth_s)
    w = max(5, int(round(smooth_s * fs)) | 1)
    # the band-pass settles within a few periods of its bandwidth; the smoother needs half a window
    edge = max(3.0 / (band * f_mode), 0.5 * w * dt)
    if t.size * dt <= 2 * edge + w * dt:
        raise UserFacingError(f"backbone: the record ({t.size * dt:.3g} s) is too short for a mode at {f_mode:g} Hz "
                              f"(needs more than {2 * edge + w * dt:.3g} s)")
    from scipy import signal  # heavy: scipy.signal costs ~0.4 CPU-s to import; only this path needs it
    sos = signal.butter(4, [f_mode * (1 - band), f_mode * (1 + band)], btype="bandpass", fs=fs, output="sos")
    yb = signal.sosfiltfilt(sos, y - np.mean(y))
    a = signal.hilbert(yb)
    amp = np.abs(a)
    phase = np.unwrap(np.angle(a))
    omega = signal.savgol_filter(phase, w, 2, deriv=1, delta=dt)
    decay = -signal.savgol_filter(np.log(np.maximum(amp, np.finfo(float).tiny)), w, 2, deriv=1, delta=dt)
    lo = t[0] + edge if t_from is None else max(float(t_from), t[0] + edge)
    hi = t[-1] - edge if t_to is None else min(float(t_to), t[-1] - edge)
    k = (t >= lo) & (t <= hi) & (amp > 0) & (omega > 0)
    if not k.any():
        raise UserFacingError(f"backbone: no samples between t = {lo:.4g} s and {hi:.4g} s "
                              f"(the record's edges, {edge:.3g} s each, are left out)")
    zeta = decay / np.sqrt(decay ** 2 + omega ** 2)
    return Backbone(t[k], amp[k], omega[k] / (2 * np.pi), zeta[k])

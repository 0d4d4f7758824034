"""Welch's averaged periodogram: the one-sided power spectral density of a sampled record.

Segments of ``nperseg`` samples overlapping by half, each with its mean removed and a periodic
Hann window applied; the density is the mean of the segments' scaled squared spectra, doubled
on every bin but the zero frequency (and the Nyquist bin of an even segment). These are the
defaults of scipy.signal.welch, which gives the same numbers to rounding
(tests/test_welch.py); the library computes it itself so that a reconstruction does not import
scipy.signal, whose import alone costs about 0.4 CPU-s per process.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.fft


def welch(x: np.ndarray, fs: float = 1.0, nperseg: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """(frequencies [Hz], power spectral density [x^2 / Hz]) of the 1-D record ``x`` sampled at
    ``fs``. A record shorter than ``nperseg`` is one segment of its own length."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"welch needs a non-empty 1-D record, got shape {x.shape}")
    nperseg = min(int(nperseg), x.size)
    if nperseg < 1:
        raise ValueError(f"welch: nperseg {nperseg} must be positive")
    noverlap = nperseg // 2
    step = nperseg - noverlap
    k = np.arange(nperseg)
    window = 0.5 - 0.5 * np.cos(2.0 * math.pi * k / nperseg)        # periodic Hann
    scale = 1.0 / (fs * float(np.sum(window * window)))
    segments = np.lib.stride_tricks.sliding_window_view(x, nperseg)[::step]
    segments = segments - segments.mean(axis=-1, keepdims=True)
    spec = np.abs(scipy.fft.rfft(segments * window, axis=-1)) ** 2 * scale
    spec[:, 1:-1 if nperseg % 2 == 0 else None] *= 2.0
    return np.fft.rfftfreq(nperseg, 1.0 / fs), spec.mean(axis=0)

"""Band-limited resampling: to reproduce a data-generation chain, and to thin a fit's input.

Two operations simulate a model the way the Bouc-Wen benchmark
data were made (input given at the recording rate, integration at ``r`` times
that rate, output low-pass filtered and decimated back):

- :func:`upsample` raises the sampling rate of an input record by an integer
  factor.  A record that holds whole periods of a periodic signal is
  interpolated exactly in the frequency domain (zero padding of its DFT); any
  other record goes through a long linear-phase polyphase FIR filter
  (:func:`scipy.signal.resample_poly` with a Kaiser-window design whose pass
  band is flat to about 1e-7 up to 45 % of the input Nyquist frequency).
- :func:`decimate_fir` mirrors MATLAB's ``decimate(x, r, 'fir')``: a 30th-order
  Hamming-window low-pass FIR (MATLAB ``fir1(30, 1/r)``) applied with its group
  delay removed (so zero phase), the record extended at both ends by point
  reflection (``2*x[0] - x[k]``) to tame edge transients, then every ``r``-th
  sample kept, starting with the first.  :func:`decimate_chain` applies it once
  per prime factor of the total rate change (20 -> 2, 2, 5), as the benchmark's
  example script does.

And one for the output-error fits (reconstruct's polish, the diagnosis's fits), which simulate a
fast record at a lower rate: :func:`thinned_input` takes every q-th sample of a model input,
low-passed first so that the noise the skipped samples carry does not fold into the response band.
"""
from __future__ import annotations

import threading
import weakref

import numpy as np

from recon.signals import edge_crossfade
from shakerlab.errors import UserFacingError

__all__ = ["upsample", "upsample_periodic", "upsample_polyphase", "decimate_fir",
           "decimate_chain", "prime_factors", "fir1_lowpass", "thinned_input"]

# thinned_input's results by the input array they were made from, while it lives: id -> {q: result}
_THINNED: dict = {}
_THINNED_LOCK = threading.Lock()


def _as_record(x, what: str) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim != 1:
        raise UserFacingError(f"{what}: expected a 1-D record, got shape {x.shape}")
    if x.size < 2:
        raise UserFacingError(f"{what}: record has {x.size} sample(s), need at least 2")
    if not np.all(np.isfinite(x)):
        bad = int(np.flatnonzero(~np.isfinite(x))[0])
        raise UserFacingError(f"{what}: non-finite value at sample {bad}")
    return x


def _check_factor(r, what: str) -> int:
    if int(r) != r or r < 1:
        raise UserFacingError(f"{what}: rate factor must be a positive integer, got {r!r}")
    return int(r)


def upsample_periodic(x, r: int) -> np.ndarray:
    """Exact band-limited interpolation of whole periods of a periodic record.

    ``x`` must hold an integer number of periods (the DFT is taken over the
    whole record).  Returns ``r * len(x)`` samples with ``out[::r] == x`` (to
    rounding).  A component at the input Nyquist frequency is split evenly
    between the positive and negative frequency, the usual convention.
    """
    x = _as_record(x, "upsample_periodic")
    r = _check_factor(r, "upsample_periodic")
    if r == 1:
        return x.copy()
    n = x.size
    spec = np.fft.rfft(x)
    out = np.zeros(n * r // 2 + 1, dtype=complex)
    out[: spec.size] = spec
    if n % 2 == 0:  # the Nyquist bin of the short record becomes an ordinary bin
        out[n // 2] *= 0.5
    return np.fft.irfft(out, n=n * r) * r


def _interp_filter(r: int, half_len_in: int = 48) -> np.ndarray:
    """Kaiser-window low-pass for interpolation by ``r`` (cut-off at the input Nyquist)."""
    n_taps = 2 * half_len_in * r + 1
    # beta 10 gives ~ -100 dB stop band; the transition is ~ 2 * 6.4 / half_len_in of the
    # input Nyquist wide, so the pass band is flat well past 40 % of it.
    from scipy import signal  # heavy: scipy.signal costs ~0.4 CPU-s to import; only this path needs it
    return signal.firwin(n_taps, 1.0 / r, window=("kaiser", 10.0))


def upsample_polyphase(x, r: int) -> np.ndarray:
    """Interpolate a non-periodic record by ``r`` with a long linear-phase FIR.

    The record is taken as zero before its first and after its last sample
    (the natural assumption for an excitation that starts from rest), so
    ``out[::r]`` reproduces ``x`` away from the first and last ~48 samples to
    better than 1e-6 relative for content below 0.45 * the input Nyquist.
    """
    x = _as_record(x, "upsample_polyphase")
    r = _check_factor(r, "upsample_polyphase")
    if r == 1:
        return x.copy()
    from scipy import signal  # heavy: scipy.signal costs ~0.4 CPU-s to import; only this path needs it
    return signal.resample_poly(x, r, 1, window=_interp_filter(r), padtype="constant")


def upsample(x, r: int, periodic: bool) -> np.ndarray:
    """Upsample ``x`` by the integer ``r``: DFT interpolation if ``periodic``, else polyphase."""
    return upsample_periodic(x, r) if periodic else upsample_polyphase(x, r)


def fir1_lowpass(order: int, cutoff: float) -> np.ndarray:
    """MATLAB ``fir1(order, cutoff)``: Hamming window, unit DC gain, cutoff re Nyquist."""
    from scipy import signal  # heavy: scipy.signal costs ~0.4 CPU-s to import; only this path needs it
    return signal.firwin(order + 1, cutoff, window="hamming", scale=True)


def decimate_fir(x, r: int, order: int = 30) -> np.ndarray:
    """MATLAB-style ``decimate(x, r, 'fir')`` (zero-phase FIR, keep ``x[0::r]``).

    Output length is ``ceil(len(x) / r)``.  The ends are extended by point
    reflection over ``order`` samples before filtering, so a record that starts
    from rest (x ~ 0 with zero slope) is filtered without a start-up transient.
    """
    x = _as_record(x, "decimate_fir")
    r = _check_factor(r, "decimate_fir")
    if order % 2:
        raise UserFacingError(f"decimate_fir: filter order must be even (linear phase), got {order}")
    if r == 1:
        return x.copy()
    if x.size <= order + 1:
        raise UserFacingError(
            f"decimate_fir: record of {x.size} samples is too short for a {order}th-order filter"
        )
    b = fir1_lowpass(order, 1.0 / r)
    half = order // 2
    head = 2.0 * x[0] - x[order:0:-1]
    tail = 2.0 * x[-1] - x[-2 : -order - 2 : -1]
    ext = np.concatenate([head, x, tail])
    filt = np.convolve(ext, b, mode="valid")  # filt[i] is centred on ext[i + half]
    centred = filt[order - half : order - half + x.size]
    return centred[::r].copy()


def prime_factors(n: int) -> list[int]:
    """Prime factors of ``n`` in increasing order (MATLAB ``factor``)."""
    n = _check_factor(n, "prime_factors")
    out, p = [], 2
    while p * p <= n:
        while n % p == 0:
            out.append(p)
            n //= p
        p += 1
    if n > 1:
        out.append(n)
    return out


def decimate_chain(x, r: int, order: int = 30) -> np.ndarray:
    """Decimate by ``r`` in steps of its prime factors (20 -> 2, 2, 5)."""
    out = _as_record(x, "decimate_chain")
    for factor in prime_factors(r):
        out = decimate_fir(out, factor, order)
    return out


def thinned_input(u: np.ndarray, q: int) -> np.ndarray:
    """Every ``q``-th sample of the input ``u``, taken after a zero-phase low-pass at 0.6 of the
    thinned record's Nyquist frequency (a Kaiser-windowed sinc of 16 q + 1 taps, run forward and
    back: flat to 1e-4 in power up to 0.16 of that Nyquist frequency, 1e-8 at it).

    The same input reaches every fit of a stage, so it is
    thinned once (kept while the input array lives).

    A Savitzky-Golay derivative of a short window passes noise far above the response band, and
    the samples skipped carry it: taken as they are, the noise above the thinned Nyquist frequency
    folds into the band, where the structure amplifies it. On a 5 kHz record thinned to 2.5 kHz,
    a stage whose input was 28 % noise was then simulated by its own true model 2 noise stds
    away from its simulation at the full rate; after the low-pass, 0.01. Within one filter
    length of each end the input is taken as it is, crossfaded into the filtered one
    (recon.signals.edge_crossfade): the filter's end extension is exact only where the input's
    curvature is zero. ``q`` <= 1: ``u`` itself."""
    u = np.asarray(u, float)
    if q <= 1:
        return u
    key = id(u)
    with _THINNED_LOCK:         # the diagnosis fits stages on threads
        hit = _THINNED.get(key)
        if hit is not None and q in hit:
            return hit[q]
    out = _thinned_input(u, q)
    with _THINNED_LOCK:
        if key not in _THINNED:
            _THINNED[key] = {}
            # the entry goes with its input (before its id can be reused)
            weakref.finalize(u, _THINNED.pop, key, None)
        _THINNED[key][q] = out
    return out


def _thinned_input(u: np.ndarray, q: int) -> np.ndarray:
    taps = 16 * q + 1
    pad = 3 * taps
    if u.size <= pad:
        return u[::q]
    # the windowed-sinc low-pass (scipy.signal.firwin's design, written out: reconstruct does not
    # import scipy.signal), run forward and back: one pass of its symmetric autocorrelation
    k = np.arange(taps) - (taps - 1) / 2.0
    b = np.sinc(0.6 / q * k) * np.kaiser(taps, 8.0)
    b /= b.sum()
    # the ends extended by odd reflection (scipy.signal.filtfilt's padtype="odd")
    ext = np.concatenate([2.0 * u[0] - u[pad:0:-1], u, 2.0 * u[-1] - u[-2:-pad - 2:-1]])
    smooth = np.convolve(ext, np.convolve(b, b), mode="same")[pad:pad + u.size]
    w = edge_crossfade(u.size, taps)
    return (w * smooth + (1.0 - w) * u)[::q]

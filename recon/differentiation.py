"""Savitzky-Golay derivatives with the window and order chosen from the data.

The choice minimises the predicted mean-square error of the highest derivative
that is needed (the third one for the nonlinear step):

- noise: the white-noise floor of the channel's spectrum (median of the upper
  half of a Hann-windowed periodogram) gives the noise variance sigma^2; the
  filter passes ``sigma^2 * sum(c^2)`` of it into the derivative (``c`` are the
  Savitzky-Golay coefficients, already scaled by the sampling step);
- bias: every spectral bin that stands out of the floor (above the expected
  maximum of the noise bins, ``floor * ln(n_bins)``) is treated as signal, and
  the filter's frequency-response error ``|H(w) - (i w)^d|^2`` at that bin,
  weighted by the bin's power, gives the bias.

Both are exact for the given coefficients, so the trade-off is computed, not
tuned. The same (window, order) is then used for every derivative of every
channel of the stage, so that y, y', y'', y''' come from one local polynomial.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np
import scipy.fft
import scipy.linalg
from scipy.ndimage import convolve1d

from recon.content_cache import ContentCache, digest
from shakerlab.errors import UserFacingError

# the search space of choose_window, not tuned choices: the predicted error picks the window and order
ORDERS = (3, 5, 7)          # polynomial orders tried
N_WINDOWS = 40              # windows per order, log-spaced up to the longest one considered


@dataclass
class SpectrumEstimate:
    """What the differentiation assumed about one channel."""

    noise_std: float          # white-noise standard deviation [channel units]
    bandwidth_hz: float       # highest frequency that stands out of the noise floor
    freqs: np.ndarray         # significant bins [Hz]
    power: np.ndarray         # their mean-square contribution, floor removed


@dataclass
class DiffChoice:
    window: int
    order: int
    deriv: int
    noise_level: dict          # channel -> noise std
    bandwidth_hz: float
    predicted_rmse: float      # predicted rms error of the chosen derivative

    def to_dict(self) -> dict:
        return asdict(self)


_SPECTRA = ContentCache()        # estimate_spectrum's results by the channel's content
_WINDOWS = ContentCache()        # choose_window's results by the channels' content and arguments


def estimate_spectrum(x: np.ndarray, dt: float) -> SpectrumEstimate:
    """Noise floor and significant signal bins of a sampled channel (computed once per content:
    the result is shared, its arrays read-only)."""
    x = np.asarray(x, float)
    key = (digest(x), float(dt))
    hit = _SPECTRA.get(key)
    if hit is not None:
        return hit
    est = _estimate_spectrum(x, dt)
    est.freqs.setflags(write=False)
    est.power.setflags(write=False)
    _SPECTRA.put(key, est)
    return est


def _estimate_spectrum(x: np.ndarray, dt: float) -> SpectrumEstimate:
    n = x.size
    if n < 64:
        raise UserFacingError(f"differentiation needs at least 64 samples, got {n}")
    # remove a linear trend so that the end mismatch does not leak
    tt = np.arange(n)
    x = x - np.polyval(np.polyfit(tt, x, 1), tt)
    w = np.hanning(n)
    sw2 = float(np.sum(w * w))
    spec = np.abs(np.fft.rfft(w * x)) ** 2
    f = np.fft.rfftfreq(n, dt)
    upper = spec[spec.size // 2:]
    # median of exponential(chi2_2) bins = ln2 * mean
    floor = float(np.median(upper) / np.log(2.0))
    noise_var = floor / sw2
    # a noise bin exceeds floor*ln(n/p) with probability p/n: p = 1 % false-alarm for the whole spectrum
    thresh = floor * np.log(100.0 * spec.size)
    sig = spec > thresh
    sig[0] = False
    power = np.where(sig, 2.0 * (spec - floor) / (n * sw2), 0.0)
    idx = np.flatnonzero(sig)
    bw = float(f[idx[-1]]) if idx.size else 0.0
    return SpectrumEstimate(float(np.sqrt(max(noise_var, 0.0))), bw, f[idx], power[idx])


# ---------------------------------------------------------------- Savitzky-Golay coefficients and filter
# The two functions below compute what scipy.signal.savgol_coeffs (use 'conv' / 'dot', pos at the
# window's centre) and savgol_filter (mode 'interp') compute, by the same least squares, so that
# reconstruct does not import scipy.signal, whose import alone costs about 0.4 CPU-s per process
# (tests/test_differentiation_savgol.py compares the two on many windows).

def savgol_coeffs(window: int, order: int, deriv: int = 0, delta: float = 1.0, use: str = "conv") -> np.ndarray:
    """The Savitzky-Golay filter of odd or even length ``window``, polynomial ``order``, for the
    ``deriv``-th derivative at sampling step ``delta``: the least-squares polynomial of the window's
    samples, evaluated at its centre. ``use='conv'`` for a convolution, ``'dot'`` for a dot product
    with the samples in order."""
    if order >= window:
        raise ValueError(f"Savitzky-Golay order {order} must be less than the window {window}")
    if use not in ("conv", "dot"):
        raise ValueError(f"use must be 'conv' or 'dot', not {use!r}")
    halflen, rem = divmod(window, 2)
    pos = halflen if rem else halflen - 0.5
    if deriv > order:
        return np.zeros(window)
    x = np.arange(-pos, window - pos, dtype=np.float64)
    if use == "conv":
        x = x[::-1]
    A = x ** np.arange(order + 1).reshape(-1, 1)
    y = np.zeros(order + 1)
    y[deriv] = math.factorial(deriv) / (delta ** deriv)
    rcond = np.finfo(np.float64).eps * max(A.shape[-1], A.shape[-2])
    return scipy.linalg.lstsq(A, y, cond=rcond)[0]


def _edge_values(x: np.ndarray, start: int, stop: int, interp_start: int, interp_stop: int, order: int,
                 deriv: int, delta: float) -> np.ndarray:
    """The ``deriv``-th derivative of the least-squares polynomial through x[start:stop], at the
    samples interp_start..interp_stop (as savgol_filter's 'interp' mode fills a record's ends)."""
    edge = x[start:stop]
    t = np.arange(0, stop - start, dtype=x.dtype)
    powers = np.flip(np.arange(order + 1, dtype=t.dtype))
    lhs = t[:, None] ** powers[None, :]
    scale = np.sqrt(np.sum(lhs * lhs, axis=0))
    lhs /= scale
    c = scipy.linalg.lstsq(lhs, edge, cond=t.shape[0] * np.finfo(t.dtype).eps)[0]
    c = (c.T / scale).T
    if deriv > 0:               # the polynomial's derivative, highest power first
        n = c.shape[0]
        if n <= deriv:
            c = np.zeros_like(c[:1])
        else:
            c = c[:-deriv].copy()
            for k in range(deriv):
                c *= np.arange(n - k - 1, deriv - k - 1, -1, dtype=c.dtype)
    i = np.arange(interp_start - start, interp_stop - start, dtype=c.dtype)
    values = np.zeros_like(i)
    for cj in c:
        values = values * i + cj
    return values / (delta ** deriv)


def savgol_filter(x: np.ndarray, window: int, order: int, deriv: int = 0, delta: float = 1.0) -> np.ndarray:
    """The Savitzky-Golay smoothed ``deriv``-th derivative of ``x`` (1-D), the ends filled from the
    polynomial fitted to the first and the last ``window`` samples (savgol_filter's mode 'interp')."""
    x = np.asarray(x)
    if x.dtype != np.float64 and x.dtype != np.float32:
        x = x.astype(np.float64)
    if window > x.shape[0]:
        raise ValueError(f"Savitzky-Golay window {window} is longer than the record ({x.shape[0]} samples)")
    y = convolve1d(x, savgol_coeffs(window, order, deriv=deriv, delta=delta), mode="constant")
    half = window // 2
    n = x.shape[0]
    y[0:half] = _edge_values(x, 0, window, 0, half, order, deriv, delta)
    y[n - half:n] = _edge_values(x, n - window, n, n - half, n, order, deriv, delta)
    return y


@lru_cache(maxsize=4096)
def filter_coefficients(window: int, order: int, deriv: int, dt: float) -> np.ndarray:
    return savgol_coeffs(window, order, deriv=deriv, delta=dt, use="dot")


def _response_error(coeffs: np.ndarray, dt: float, deriv: int, omega: np.ndarray) -> np.ndarray:
    half = (coeffs.size - 1) // 2
    k = np.arange(coeffs.size) - half
    # savgol_coeffs(use='dot'): estimate_i = sum_j c_j x_{i+j-half}
    h = np.exp(1j * np.outer(omega, k * dt)) @ coeffs
    return np.abs(h - (1j * omega) ** deriv) ** 2


def predicted_errors(window: int, order: int, deriv: int, dt: float, spectra: list[SpectrumEstimate]):
    """(noise variance, squared bias) of the derivative estimate."""
    c = filter_coefficients(window, order, deriv, float(dt))
    noise = bias = 0.0
    g = float(np.sum(c * c))
    for s in spectra:
        noise += s.noise_std ** 2 * g
        if s.freqs.size:
            bias += float(np.sum(s.power * _response_error(c, dt, deriv, 2 * np.pi * s.freqs)))
    return noise, bias


def predicted_mse(window: int, order: int, deriv: int, dt: float, spectra: list[SpectrumEstimate]) -> float:
    noise, bias = predicted_errors(window, order, deriv, dt, spectra)
    return noise + bias


BIAS_BLOCK = 256     # spectral lines per block of choose_window's tables (memory: 2 x 256 x 1000 floats)


def choose_window(channels: dict[str, np.ndarray], dt: float, deriv: int = 3, window: int | None = None,
                  order: int | None = None, for_regression: bool = True,
                  coefficients=filter_coefficients) -> DiffChoice:
    """Pick the Savitzky-Golay (window, order) minimising the predicted error of ``deriv``.

    ``for_regression``: the derivatives feed a least-squares regression over all N
    samples, which averages the (zero-mean) noise down by ~1/N but passes the filter's
    bias through in full, and amplifies it along the nearly collinear library directions.
    The criterion is then bias^2 + noise^2/N instead of the pointwise bias^2 + noise^2.
    ``coefficients(window, order, deriv, dt)``: the filter judged (:func:`stable_coefficients`
    for :func:`stable_derivatives`).

    Computed once per content of the channels and arguments; each call returns its own copy.
    """
    key = (tuple((name, digest(np.asarray(x, float))) for name, x in channels.items()), float(dt), deriv,
           window, order, for_regression, coefficients)
    hit = _WINDOWS.get(key)
    if hit is None:
        hit = _choose_window(channels, dt, deriv, window, order, for_regression, coefficients)
        _WINDOWS.put(key, hit)
    return DiffChoice(window=hit.window, order=hit.order, deriv=hit.deriv, noise_level=dict(hit.noise_level),
                      bandwidth_hz=hit.bandwidth_hz, predicted_rmse=hit.predicted_rmse)


def _choose_window(channels: dict[str, np.ndarray], dt: float, deriv: int, window: int | None,
                   order: int | None, for_regression: bool, coefficients) -> DiffChoice:
    spectra = {name: estimate_spectrum(x, dt) for name, x in channels.items()}
    if window is not None:
        order = order or 5
        if window % 2 == 0 or window <= order:
            raise UserFacingError(f"Savitzky-Golay window must be odd and larger than the order {order}, got {window}")
        mse = predicted_mse(window, order, deriv, dt, list(spectra.values()))
        return DiffChoice(window=window, order=order, deriv=deriv,
                          noise_level={k: s.noise_std for k, s in spectra.items()},
                          bandwidth_hz=max(s.bandwidth_hz for s in spectra.values()),
                          predicted_rmse=float(np.sqrt(mse)))
    n = min(x.size for x in channels.values())
    bw = max(s.bandwidth_hz for s in spectra.values())
    # longest window considered: one period of the lowest significant line, capped
    max_win = min(n // 4, 2001)
    lows = [s.freqs[0] for s in spectra.values() if s.freqs.size]
    if lows and min(lows) > 0:
        max_win = min(max_win, int(1.5 / (min(lows) * dt)))
    noise_var = sum(sp.noise_std ** 2 for sp in spectra.values())
    trials = []                       # (order, window, coefficients) in the order they are judged
    for order in ORDERS:
        if order < deriv:
            continue
        w0 = order + 2 + (order % 2 == 0)
        if w0 > max_win:
            continue
        wins = np.unique(np.round(np.geomspace(w0, max(w0, max_win), N_WINDOWS)).astype(int) | 1)
        for win in wins:
            win = int(win)
            if win <= order or win > max_win:
                continue
            trials.append((order, win, coefficients(win, order, deriv, float(dt))))
    # each trial's bias: sum over a channel's significant lines of power |H(w) - (i w)^deriv|^2,
    # H(w) = sum_k c_k exp(i w k dt) = c_0 + sum_{k>0} (c_k + c_-k) cos(w k dt) + i (c_k - c_-k) sin(w k dt):
    # the same sum regrouped, so the tables are real and half as long (4x less work than the complex
    # exponential). They are made for the longest window (shorter ones use their first columns) a
    # block of lines at a time, so their memory stays bounded however many lines a long fast record
    # has (300,000 samples at 10 kHz: thousands of lines)
    kmax = max_win // 2
    kk = np.arange(1, kmax + 1) * dt
    parts = []
    for _, win, c in trials:
        half = win // 2
        parts.append((half, c[half], c[half + 1:] + c[half - 1::-1], c[half + 1:] - c[half - 1::-1]))
    bias = np.zeros(len(trials))
    for sp in spectra.values():
        for lo in range(0, sp.freqs.size, BIAS_BLOCK):
            w = 2 * np.pi * sp.freqs[lo:lo + BIAS_BLOCK]
            arg = np.outer(w, kk)
            cos, sin = np.cos(arg), np.sin(arg)
            target = (1j * w) ** deriv
            power = sp.power[lo:lo + BIAS_BLOCK]
            for j, (half, c0, even, odd) in enumerate(parts):
                re = c0 + cos[:, :half] @ even - target.real
                im = sin[:, :half] @ odd - target.imag
                bias[j] += float(np.sum(power * (re * re + im * im)))
    best = None
    for (order, win, c), b in zip(trials, bias):
        noise = noise_var * float(c @ c)
        crit = b + (noise / n if for_regression else noise)
        if best is None or crit < best[0]:
            best = (crit, win, order, noise + b)
    if best is None:
        raise UserFacingError(f"too few samples ({n}) to differentiate {deriv} times")
    return DiffChoice(
        window=best[1], order=best[2], deriv=deriv,
        noise_level={k: s.noise_std for k, s in spectra.items()},
        bandwidth_hz=bw, predicted_rmse=float(np.sqrt(best[3])),
    )


def derivatives(x: np.ndarray, dt: float, window: int, order: int, max_deriv: int = 3) -> list[np.ndarray]:
    """[x_smooth, x', ..., x^(max_deriv)] with one Savitzky-Golay filter."""
    return [savgol_filter(x, window, order, deriv=d, delta=dt) for d in range(max_deriv + 1)]


@lru_cache(maxsize=4096)
def stable_coefficients(window: int, order: int, deriv: int, dt: float) -> np.ndarray:
    """Savitzky-Golay coefficients (``use='dot'``, centre point) from the least-squares fit on the
    abscissa scaled to [-1, 1]. scipy's ``savgol_coeffs`` fits on the raw sample offsets and
    loses its accuracy for long windows (order 7: the smoothing coefficients of a 189-sample
    window sum to 1e-6 instead of 1 with scipy 1.17), which the window choice of a velocity or
    acceleration channel (fewer derivatives, longer windows) reaches."""
    half = window // 2
    x = np.arange(-half, half + 1) / half
    pinv = np.linalg.pinv(np.vander(x, order + 1, increasing=True))
    return pinv[deriv] * math.factorial(deriv) / (half * dt) ** deriv


def stable_derivatives(x: np.ndarray, dt: float, window: int, order: int, max_deriv: int) -> list[np.ndarray]:
    """[x_smooth, x', ..., x^(max_deriv)] with :func:`stable_coefficients`; the first and last
    ``window // 2`` samples from the polynomial fitted to the first and last window (as
    ``savgol_filter(mode='interp')``)."""
    x = np.asarray(x, float)
    half = window // 2
    n = x.size
    if n < window:
        raise UserFacingError(f"Savitzky-Golay window {window} is longer than the record ({n} samples)")
    xs = np.arange(-half, half + 1) / half
    pinv = np.linalg.pinv(np.vander(xs, order + 1, increasing=True))
    out = []
    for d in range(max_deriv + 1):
        c = stable_coefficients(window, order, d, float(dt))
        y = np.empty(n)
        y[half:n - half] = np.correlate(x, c, mode="valid")
        # edges: derivative d of the polynomial fitted to the end window, at the edge points
        dpoly = np.zeros((window, order + 1))
        for p in range(d, order + 1):
            dpoly[:, p] = math.perm(p, d) * xs ** (p - d)
        scale = 1.0 / (half * dt) ** d
        y[:half] = (dpoly[:half] @ (pinv @ x[:window])) * scale
        y[n - half:] = (dpoly[half + 1:] @ (pinv @ x[n - window:])) * scale
        out.append(y)
    return out


def derivative_gain(window: int, order: int, deriv: int, dt: float, f) -> np.ndarray:
    """Gain of the Savitzky-Golay ``deriv``-th derivative filter relative to the exact
    derivative at the frequencies ``f`` [Hz] (even ``deriv``: the filter is symmetric and its
    response real). 1 - gain is the passband loss; 0 Hz reports 1."""
    if deriv % 2:
        raise ValueError("derivative_gain: even derivatives only (real response)")
    h = savgol_coeffs(window, order, deriv=deriv)       # per sample^deriv
    h = h - h.mean()              # the exact coefficients sum to 0; rounding would leak into 1/w^d
    k = np.arange(window) - window // 2
    w = 2 * np.pi * np.asarray(f, float) * dt           # rad per sample
    g = np.cos(np.outer(w, k)) @ h
    out = np.ones_like(w)
    nz = w > 0
    out[nz] = g[nz] / ((-1) ** (deriv // 2) * w[nz] ** deriv)
    return out


def _gain_on_fft_grid(window: int, order: int, deriv: int, dt: float, n: int) -> np.ndarray:
    """:func:`derivative_gain` at the ``np.fft.rfftfreq(n, dt)`` frequencies, from the FFT of the
    kernel placed circularly about sample 0 (O(n log n); the cosine sum over every bin would
    take n/2 x window memory: 1.5 GB for a 25 s stage at 10 kHz)."""
    h = savgol_coeffs(window, order, deriv=deriv)
    h = h - h.mean()
    hp = np.zeros(n)
    hp[:window] = h
    resp = scipy.fft.rfft(np.roll(hp, -(window // 2))).real    # symmetric kernel: real response
    w = 2 * np.pi * np.fft.rfftfreq(n, dt) * dt
    out = np.ones_like(w)
    nz = w > 0
    out[nz] = resp[nz] / ((-1) ** (deriv // 2) * w[nz] ** deriv)
    return out


def undo_passband_loss(u: np.ndarray, dt: float, window: int, order: int, deriv: int = 2) -> np.ndarray:
    """``u`` (a Savitzky-Golay ``deriv``-th derivative) with the filter's attenuation g undone
    to first order in its passband: u + (1 - g) u, whose error relative to u / g is (1 - g)^2
    (< 1e-6 where g > 0.999).

    Only the passband is corrected: where the loss is <= 1 % (the factor there amplifies the
    noise by <= 1 %), rolled off smoothly to no correction at a 10 % loss (the transition
    band, where u is mostly noise). The record is extended by point reflection at both
    ends and the straight line through the ends removed before the FFT, so that the ends do
    not wrap onto each other. Why: at a 12.5 Hz resonance a 109-sample second-derivative
    window at 2 kHz loses 0.08 % of the base acceleration, which the output-error fit
    turned into a -0.1 % bias of the cubic stiffness (docs/reprocessing.md)."""
    n = u.size
    if n < 3:
        return u
    ext = np.concatenate([2 * u[0] - u[:0:-1], u, 2 * u[-1] - u[-2::-1]])
    ext -= ext[0] + (ext[-1] - ext[0]) * np.arange(ext.size) / (ext.size - 1)
    # both ends are 0 now: zero-padding to a fast FFT length keeps the record continuous
    # (3n - 2 is often 2 x a large prime: 20 times slower)
    m = scipy.fft.next_fast_len(ext.size, real=True)
    spectrum = scipy.fft.rfft(ext, m)
    del ext             # a long stage's arrays here are tens of MiB: each is freed once used
    f = np.fft.rfftfreq(m, dt)
    loss = 1.0 - _gain_on_fft_grid(window, order, deriv, dt, m)
    edge = np.flatnonzero(loss > 0.1)
    cut = f[edge[0]] if edge.size else np.inf
    taper = np.clip((loss - 0.01) / 0.09, 0.0, 1.0)
    taper *= np.pi
    np.cos(taper, out=taper)
    taper += 1
    taper *= 0.5
    taper[f >= cut] = 0.0
    del f
    spectrum *= loss        # the same products in the same order as (spectrum * loss) * taper
    del loss
    spectrum *= taper
    del taper
    return u + scipy.fft.irfft(spectrum, m)[n - 1:2 * n - 1]

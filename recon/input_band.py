"""The measured input's own band: the model input cleared of the noise outside it.

Output error simulates the model driven by the *measured* input. Under base excitation that is
the base sensor's reading differentiated twice, so the sensor's white noise enters the
simulation as a broadband force. Near resonance the structure picks out the part of it at its
own frequency and answers with a narrow-band random motion that no parameter set can follow: the
fit then trades damping and the Bouc-Wen shape against it. On one tone per stage this input
noise, not the output noise, can set the error of the parameters (several per cent on the loop's
shape with the input as measured, under 1 % with a noise-free base channel, the fit started at
the truth in both cases; docs/method.md).

An excitation occupies a band: one tone and its ramps a few hundred coefficients, a sweep or a
multisine its range, the exciter's harmonics where they rise above the floor. Outside that band
the input channel holds only noise. :class:`BandLimit` finds the band from the recording itself
and keeps only it:

- **Level ends.** The first and third derivatives at each end (a polynomial fit over the
  differentiation window; each within ``band_slope_sigmas`` (4) times its own noise counts as
  zero, so a stage that starts or ends at rest keeps its end as recorded) are removed by a local
  correction: a cubic times a Gaussian of about one window's reach, added back exactly afterwards.
- **Cosine series.** The orthonormal DCT-II of what is left is the Fourier series of its mirror
  image, which is then smooth at both joins (value, slope, curvature and third derivative
  continue), so a mismatch of the ends leaks little into the noise region. Under white noise of
  std sigma the coefficients are independent N(0, sigma^2).
- **The top of the band.** The floor is the median of the upper half's squared coefficients; a
  coefficient seeds the band when the mean of its ``band_smooth`` (5) neighbours' squares exceeds
  the chi-square(5) level of a ``band_false_alarm`` (1 %) false alarm over the whole series, and
  the band grows into neighbours above ``band_grow`` (3) times the floor (hysteresis
  thresholding: a tone keeps its skirts and ramps). Every coefficient up to the last one so
  reached is kept, every one above dropped.
- **Derivatives in the band.** y'' of the base from displacement (y' from velocity) is taken on
  the kept cosine series: exact there, and no noise above the band to amplify.

It is a linear filter once the band is fixed, so the same filter passed over white noise gives
the noise the cleared input still carries (the uncertainty ensemble's draws). A channel whose
band cannot be told from its noise (too short, a floor of zero, nothing above the floor, or a
band reaching half the Nyquist frequency) is left to the caller's Savitzky-Golay filter, which
also takes over at an end in motion (recon.signals.InputFilter).

The numbers the band is decided with are EstimatorTuning fields (``band_*``, recon.estimator.tuning).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.special import chdtri, gammaincinv
from scipy.fft import dct

from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning

# the fewest samples whose upper half (128 cosine coefficients) gives the noise floor as a median
MIN_SAMPLES = 256
MEDIAN_CHI2_1 = float(2.0 * gammaincinv(0.5, 0.5))     # the chi-square's (one degree) median


def _edge_derivatives(x: np.ndarray, window: int, order: int, noise_std: float,
                      slope_sigmas: float) -> tuple[float, ...]:
    """The first and third derivatives (per sample) at the first sample and at the last one:
    a polynomial of ``order`` fitted by least squares to the ``window`` samples at each end. Each
    is zero where it is within ``slope_sigmas`` times its own noise (a stage that starts or ends
    at rest keeps its ends as recorded)."""
    w = int(max(min(window, x.size // 4), 5))
    order = int(max(min(order, w - 2), 1))
    P = np.linalg.pinv(np.vander(np.arange(w) / (w - 1), order + 1, increasing=True))
    out = []
    for seg, sign in ((x[:w], 1.0), (x[::-1][:w], -1.0)):
        for k, fact in ((1, 1.0), (3, 6.0)):
            if k > order:
                out.append(0.0)
                continue
            row = P[k] * fact / (w - 1) ** k
            v = sign ** k * float(row @ seg)
            out.append(v if abs(v) > slope_sigmas * noise_std * float(np.linalg.norm(row)) else 0.0)
    return tuple(out)


def _tau(n: int, window: int) -> float:
    """The reach of the end corrections (samples)."""
    return float(min(max(window, 8), n / 8))


def _edge_function(n: int, d: tuple[float, ...], tau: float, deriv: int = 0) -> np.ndarray:
    """h, or its ``deriv``-th derivative per sample, whose first and third derivatives are ``d``
    at both ends and whose value and second derivative are zero there: at each end a cubic in the
    distance s from that end times exp(-(s/tau)^2), so it vanishes away from the ends."""
    out = np.zeros(n)
    s = np.arange(n, dtype=float)
    for (v1, v3), dist, sign in (((d[0], d[1]), s, 1.0), ((d[2], d[3]), s[::-1], -1.0)):
        if v1 == 0.0 and v3 == 0.0:
            continue
        # in the distance s (= -t at the far end) odd derivatives change sign; p = a s + b s^3,
        # with the Gaussian's curvature -2/tau^2 at s = 0 compensated in b
        a = sign * v1
        b = (sign * v3 + 6.0 * a / tau ** 2) / 6.0
        w = np.exp(-(dist / tau) ** 2)
        p0, p1, p2 = a * dist + b * dist ** 3, a + 3 * b * dist ** 2, 6 * b * dist
        w1, w2 = -2 * dist / tau ** 2 * w, (4 * dist ** 2 / tau ** 4 - 2 / tau ** 2) * w
        if deriv == 0:
            h = p0 * w
        elif deriv == 1:
            h = p1 * w + p0 * w1
        elif deriv == 2:
            h = p2 * w + 2 * p1 * w1 + p0 * w2
        else:
            raise ValueError("the end corrections have derivatives up to the second")
        out += h * sign ** deriv
    return out


def band_top(x: np.ndarray, window: int, order: int, noise_std: float,
             tuning: EstimatorTuning = DEFAULT_TUNING) -> tuple[int | None, str]:
    """The number of cosine-series coefficients that hold the excitation (the band is 0 .. top-1),
    or None and the reason when it cannot be told from the noise (``tuning``'s band_* fields)."""
    x = np.asarray(x, float)
    n = x.size
    if n < MIN_SAMPLES or not np.all(np.isfinite(x)):
        return None, "too short or not finite"
    c = dct(x - _edge_function(n, _edge_derivatives(x, window, order, noise_std, tuning.band_slope_sigmas),
                               _tau(n, window)), type=2, norm="ortho")
    c2 = c * c
    floor = float(np.median(c2[n // 2:]) / MEDIAN_CHI2_1)
    if not floor > 0.0:
        return None, "no noise floor"
    smooth = tuning.band_smooth
    p = ndimage.uniform_filter1d(c2, smooth, mode="nearest")
    seeds = p > floor * chdtri(smooth, tuning.band_false_alarm / n) / smooth
    grown = (p > tuning.band_grow * floor) | seeds
    labels, _ = ndimage.label(grown)
    keep = np.unique(labels[seeds])
    if not keep.size:
        return None, "nothing above the noise floor"
    top = int(np.flatnonzero(np.isin(labels, keep))[-1]) + 1
    if top > n // 2:
        return None, "broadband: the excitation reaches half the Nyquist frequency"
    return top, f"{top} of {n} coefficients"


@dataclass
class BandLimit:
    """A fixed band (from :func:`band_top` on the recording) applied to any series of the same
    length: the recording itself, or noise drawn for the uncertainty ensemble."""

    top: int             # coefficients 0 .. top-1 are kept
    size: int            # the series' length
    window: int          # the end-derivative fit (recon.signals: the channel's own filter)
    order: int
    noise_std: float     # the channel's white-noise level
    level_ends: tuple    # (start, end): the recording at rest there, its slope and third derivative
                         # within their noise, so the cosine series continues it smoothly
    slope_sigmas: float  # an end's derivative within this many of its noise std is zero (tuning)

    @classmethod
    def of(cls, x: np.ndarray, noise_std: float, window: int | None = None,
           order: int | None = None, tuning: EstimatorTuning = DEFAULT_TUNING) -> "BandLimit | None":
        """The band of ``x``, or None where it cannot be told from the noise (``tuning``'s band_*
        fields)."""
        x = np.asarray(x, float)
        window, order = window or min(64, x.size // 4), order or 3
        top, _ = band_top(x, window, order, noise_std, tuning)
        if top is None:
            return None
        d = _edge_derivatives(x, window, order, noise_std, tuning.band_slope_sigmas)
        return cls(top, x.size, int(window), int(order), float(noise_std),
                   (d[0] == 0.0 and d[1] == 0.0, d[2] == 0.0 and d[3] == 0.0), float(tuning.band_slope_sigmas))

    def __call__(self, x: np.ndarray, deriv: int = 0, dt: float = 1.0) -> np.ndarray:
        """``x`` cleared of what lies above the band, or its ``deriv``-th derivative (sample
        spacing ``dt``) taken in the band."""
        x = np.asarray(x, float)
        n = x.size
        if n != self.size:
            raise ValueError(f"a band of a {self.size}-sample series does not fit one of {n}")
        d = _edge_derivatives(x, self.window, self.order, self.noise_std, self.slope_sigmas)
        tau = _tau(n, self.window)
        r = x - _edge_function(n, d, tau)
        # the cosine series of r is the Fourier series of its mirror image [r, r reversed]
        spec = np.fft.rfft(np.concatenate([r, r[::-1]]))
        spec[self.top:] = 0.0
        if deriv:
            spec = spec * (2j * np.pi * np.fft.rfftfreq(2 * n, dt)) ** deriv
        out = np.fft.irfft(spec, 2 * n)[:n]
        return out + _edge_function(n, d, tau, deriv) / dt ** deriv

    @property
    def kept_share(self) -> float:
        """The share of the cosine series kept (its band relative to the Nyquist frequency)."""
        return float(self.top / self.size)

"""Model-selection criteria shared by the estimators: correlation lengths, effective sample counts, BIC."""
from __future__ import annotations

import numpy as np

from recon.content_cache import ContentCache, digest
from recon.differentiation import filter_coefficients

_EFFECTIVE = ContentCache()      # effective_samples by the residual's content (the diagnosis scores every
                                 # candidate against the same reference residual)


def filter_correlation_length(choice: dict) -> float:
    """Correlation length (in samples) of white noise after the stage's highest-derivative
    filter: sum of the squared normalised autocorrelation (Bartlett), which sets the
    effective number of independent residuals N/corr_len."""
    c = filter_coefficients(choice["window"], choice["order"], choice["deriv"], 1.0)
    r = np.correlate(c, c, "full")
    return float(np.sum((r / r.max()) ** 2))


def _autocovariance(e: np.ndarray, lags: int) -> np.ndarray:
    """Autocovariance sums of ``e`` (mean removed) at lags 0..lags-1, by FFT."""
    e = np.asarray(e, float) - np.mean(e)
    n = e.size
    f = np.fft.rfft(e, 2 * n)
    return np.fft.irfft(f * np.conj(f))[: min(n, lags)]


def bartlett_correlation_length(e: np.ndarray, lags: int) -> float:
    """1 + 2 sum_{k=1..lags} rho_k^2 of a residual (Bartlett): the factor by which correlated
    residuals reduce the number of independent samples in a variance or BIC comparison."""
    ac = _autocovariance(e, lags + 1)
    if ac[0] <= 0:
        return 1.0
    rho = ac[1:] / ac[0]
    return float(1.0 + 2.0 * np.sum(rho ** 2))


def effective_samples(r: np.ndarray, max_lag: int = 2000) -> float:
    """N / (1 + 2 sum rho_k), the sum truncated at the first non-positive autocorrelation: the
    number of independent samples a mean-square of ``r`` is worth."""
    r = np.asarray(r, float)
    key = (digest(r), max_lag)
    hit = _EFFECTIVE.get(key)
    if hit is None:
        hit = _effective_samples(r, max_lag)
        _EFFECTIVE.put(key, hit)
    return hit


def _effective_samples(r: np.ndarray, max_lag: int) -> float:
    n = r.size
    if n < 8 or not np.any(r - np.mean(r)):
        return float(max(n, 1))
    ac = _autocovariance(r, max_lag)
    ac = ac / ac[0]
    s = 0.0
    for k in range(1, ac.size):
        if ac[k] <= 0:
            break
        s += ac[k]
    return float(max(n / (1.0 + 2.0 * s), 1.0))


def decorrelation_lag(r: np.ndarray, threshold: float = 0.1) -> int:
    """First lag at which the autocorrelation of ``r`` falls below ``threshold`` (>= 1)."""
    r = np.asarray(r, float)
    n = r.size
    if n < 8 or not np.any(r - np.mean(r)):
        return 1
    acf = _autocovariance(r, n)
    acf = acf / acf[0]
    below = np.flatnonzero(acf < threshold)
    return int(below[0]) if below.size else n


def bic(rss: float, k: int, n_eff: float) -> float:
    """Bayesian information criterion of a mean-square residual ``rss`` with ``k`` parameters
    over ``n_eff`` independent samples."""
    return float(n_eff * np.log(rss) + k * np.log(n_eff))

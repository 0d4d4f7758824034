"""recon.welch gives scipy.signal.welch's default estimate (to rounding)."""
import numpy as np
import pytest
from scipy.signal import welch as scipy_welch

from recon.welch import welch


@pytest.mark.parametrize("n, nperseg, fs", [(10000, 1024, 1000.0), (3001, 256, 2500.0), (500, 1024, 1.0),
                                            (4097, 1023, 5000.0), (64, 16, 10.0)])
def test_the_density_is_scipys(n, nperseg, fs):
    rng = np.random.default_rng(n)
    x = rng.normal(0, 1e-6, n) + 1e-4 * np.sin(2 * np.pi * 0.05 * fs * np.arange(n) / fs) + 3e-5
    f, p = welch(x, fs=fs, nperseg=nperseg)
    with pytest.warns(UserWarning) if nperseg > n else _nothing():
        fs_, ps = scipy_welch(x, fs=fs, nperseg=nperseg)
    assert np.array_equal(f, fs_)
    np.testing.assert_allclose(p, ps, rtol=1e-12, atol=0)


def test_white_noise_has_its_variance_spread_over_the_band():
    rng = np.random.default_rng(0)
    x = rng.normal(0, 2.0, 200_000)
    f, p = welch(x, fs=100.0, nperseg=512)
    # one-sided density of white noise of variance 4 at fs 100: 4 / 50 per Hz
    assert abs(np.mean(p[1:-1]) / 0.08 - 1) < 0.02


def test_a_bad_record_is_refused():
    with pytest.raises(ValueError, match="non-empty 1-D"):
        welch(np.zeros((3, 3)))


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False

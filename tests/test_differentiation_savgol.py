"""recon.differentiation's Savitzky-Golay coefficients and filter give what scipy.signal's give (the
library computes them itself so that a reconstruction does not import scipy.signal)."""
import numpy as np
import pytest
from scipy.signal import savgol_coeffs as scipy_coeffs, savgol_filter as scipy_filter

from recon.differentiation import savgol_coeffs, savgol_filter


@pytest.mark.parametrize("use", ["conv", "dot"])
def test_the_coefficients_are_scipys(use):
    for window in (5, 7, 11, 21, 31, 51, 101, 8, 12):
        for order in (2, 3, 5, 7):
            if order >= window:
                continue
            for deriv in range(0, 4):
                for delta in (1.0, 1e-3, 1 / 2500.0):
                    a = savgol_coeffs(window, order, deriv=deriv, delta=delta, use=use)
                    b = scipy_coeffs(window, order, deriv=deriv, delta=delta, use=use)
                    assert np.array_equal(a, b), (window, order, deriv, delta, use)


def test_the_filter_is_scipys_interp_mode():
    rng = np.random.default_rng(3)
    t = np.arange(3000) * 1e-3
    x = np.sin(2 * np.pi * 7 * t) * 1e-3 + rng.normal(0, 1e-6, t.size)
    for window, order in ((11, 3), (21, 7), (41, 5), (8, 3)):
        for deriv in range(0, 4):
            a = savgol_filter(x, window, order, deriv=deriv, delta=1e-3)
            b = scipy_filter(x, window, order, deriv=deriv, delta=1e-3, mode="interp")
            assert np.array_equal(a, b), (window, order, deriv)


def test_a_bad_window_is_refused_with_its_reason():
    with pytest.raises(ValueError, match="order 5 must be less than the window 5"):
        savgol_coeffs(5, 5)
    with pytest.raises(ValueError, match="longer than the record"):
        savgol_filter(np.zeros(10), 21, 3)

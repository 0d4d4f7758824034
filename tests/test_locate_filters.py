"""The mismatch location's mode filters (recon.diagnosis.locate) equal scipy.signal's bilinear
discretisation and lfilter to rounding, without importing scipy.signal."""
import numpy as np
import pytest
from scipy.signal import cont2discrete, lfilter

from recon.diagnosis.locate import bilinear_biquad, mode_response, mode_response_to_motion

CASES = [(1e-3, 20.0, 0.02, 1.0), (2e-4, 300.0, 0.05, 3.0), (1e-3, 400.0, 0.01, 1e3), (4e-4, 3.0, 0.3, -2.0)]


@pytest.mark.parametrize("dt,f,zeta,g", CASES)
def test_mode_filters_equal_scipys(dt, f, zeta, g):
    w = 2 * np.pi * f
    rng = np.random.default_rng(3)
    u = rng.normal(size=8000)
    y = np.cumsum(rng.normal(size=8000)) * 1e-3
    for b, ours, x in (([g], mode_response(u, dt, w, zeta, g), u),
                       ([-1.0, 0.0, 0.0], mode_response_to_motion(y, dt, w, zeta), y)):
        num, den, _ = cont2discrete((b, [1.0, 2 * zeta * w, w * w]), dt, method="bilinear")
        ref = lfilter(np.ravel(num), den, x)
        assert np.max(np.abs(ours - ref)) <= 1e-8 * np.max(np.abs(ref))


def test_bilinear_biquad_coefficients():
    num, den, _ = cont2discrete(([0.5, 2.0, 7.0], [1.0, 3.0, 40.0]), 0.01, method="bilinear")
    n2, d2 = bilinear_biquad((0.5, 2.0, 7.0), (3.0, 40.0), 0.01)
    np.testing.assert_allclose(n2, np.ravel(num), rtol=1e-12)
    np.testing.assert_allclose(d2, den, rtol=1e-12)
    assert d2[0] == 1.0

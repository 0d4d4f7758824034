"""Counting the input's spectral lines (recon.steps.linear.count_lines), issue 14: a leaky multisine
was counted as 1-3 lines (its lines' leakage skirts touched and chained), and the linear step's
refusal under force excitation then blamed "a single tone" instead of the real cause."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lsim

from recon.differentiation import estimate_spectrum
from recon.steps.linear import count_lines, fit_linear
from shakerlab.errors import UserFacingError

FS, T = 1000.0, 10.0


def _leaky_multisine(snr_db: float, spacing_hz: float = 1.0, seed: int = 0):
    """9 lines at frequencies that are not whole cycles of the record (leakage), random phases."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(T * FS)) / FS
    freqs = 5.167 + spacing_hz * np.arange(9)
    x = sum(np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)) for f in freqs)
    return t, x + rng.normal(0.0, np.std(x) / 10 ** (snr_db / 20), t.size)


def _count(x, **kw):
    spec = estimate_spectrum(x, 1.0 / FS)
    return count_lines(spec.freqs, 1.0 / (x.size / FS), spec.power, **kw), spec


@pytest.mark.parametrize("snr_db", [40.0, 60.0, 80.0, 120.0])
@pytest.mark.parametrize("spacing_hz", [0.5, 1.0, 2.0])
def test_a_leaky_nine_line_multisine_is_nine_lines(snr_db, spacing_hz):
    _, x = _leaky_multisine(snr_db, spacing_hz)
    n, spec = _count(x)
    assert n == 9
    if snr_db >= 60:
        # the first rule (bins closer than 4 df merge) chained the skirts: the bug this fixes
        assert count_lines(spec.freqs, 1.0 / T) < 9


@pytest.mark.parametrize("snr_db", [40.0, 80.0, 120.0])
def test_a_leaky_tone_is_one_line_and_its_harmonic_a_second(snr_db):
    rng = np.random.default_rng(3)
    t = np.arange(int(T * FS)) / FS
    tone = np.sin(2 * np.pi * 7.33 * t)
    noise = rng.normal(0.0, 1.0, t.size) * np.std(tone) / 10 ** (snr_db / 20)
    assert _count(tone + noise)[0] == 1
    assert _count(tone + 0.05 * np.sin(2 * np.pi * 14.66 * t) + noise)[0] == 2


def test_the_refusal_under_a_multisine_names_the_noise_not_a_tone():
    """A force-excitation linear stage driven by a leaky 9-line multisine whose columns carry too much
    noise: the refusal must name the noise and the 9 lines, not a single tone."""
    t, force = _leaky_multisine(80.0)
    c, k = 2.0, (2 * np.pi * 8.0) ** 2
    _, y, state = lsim(([1.0], [1.0, c, k]), force, t)
    dy = np.gradient(y, t)
    ddy = force - c * dy - k * y
    lines = _count(force)[0]
    assert lines == 9
    rms = {nm: float(np.sqrt(np.mean(v ** 2))) for nm, v in (("y", y), ("dy", dy), ("u", force))}
    noisy = {nm: 0.5 * r for nm, r in rms.items()}       # columns buried in their noise
    with pytest.raises(UserFacingError) as err:
        fit_linear(y, dy, ddy, force, "force", noisy, "linear", lines)
    msg = str(err.value)
    assert "input lines 9" in msg and "single tone" not in msg and "sensor noise" in msg
    # the same stage with the first rule's count gave the wrong cause
    with pytest.raises(UserFacingError, match="single tone"):
        fit_linear(y, dy, ddy, force, "force", noisy, "linear", 2)


@pytest.mark.parametrize("snr_db", [40.0, 80.0])
def test_a_chirp_is_many_lines_not_a_single_tone(snr_db):
    from scipy.signal import chirp

    t = np.arange(int(T * FS)) / FS
    x = chirp(t, 5.0, T, 30.0) + np.random.default_rng(4).normal(0.0, 10 ** (-snr_db / 20), t.size)
    n, spec = _count(x)
    assert n >= 20                      # measured 38: 25 Hz of band, one line per Hann main lobe
    assert count_lines(spec.freqs, 1.0 / T) <= 2      # the first rule: "a single tone"

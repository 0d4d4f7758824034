"""The Savitzky-Golay window choice and the spectral noise estimate are computed once per content
of their channels (recon.content_cache): the same answer as computed afresh, a fresh answer for
changed data, and callers cannot change what later callers get. The window choice's bias, summed
with real cosine and sine tables, is the bias of the complex frequency response
(recon.differentiation.predicted_mse)."""
import numpy as np
import pytest

import recon.differentiation as D
from recon.content_cache import ContentCache, digest

DT = 1.0 / 1000.0


def _record(seed=0, n=20000, noise=1e-3):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    x = np.sin(2 * np.pi * 9.0 * t) + 0.2 * np.sin(2 * np.pi * 27.0 * t + 0.3) + 0.05 * np.sin(2 * np.pi * 45 * t)
    return x + noise * rng.normal(size=n)


@pytest.mark.parametrize("deriv,for_regression", [(3, True), (2, False), (1, False)])
def test_chosen_window_predicted_error_is_the_complex_response_error(deriv, for_regression):
    D._WINDOWS.clear()
    x = _record()
    ch = D.choose_window({"x": x}, DT, deriv=deriv, for_regression=for_regression)
    spectrum = D.estimate_spectrum(x, DT)
    noise, bias = D.predicted_errors(ch.window, ch.order, deriv, DT, [spectrum])
    assert ch.predicted_rmse == pytest.approx(np.sqrt(noise + bias), rel=1e-9)
    # and it is the minimum of the criterion over the windows tried of its order
    n = x.size

    def crit(w):
        nz, b = D.predicted_errors(w, ch.order, deriv, DT, [spectrum])
        return b + (nz / n if for_regression else nz)
    best = crit(ch.window)
    others = [w for w in _trial_windows(x, deriv, ch.order) if w > ch.order and w != ch.window]
    assert len(others) > 10 and all(best <= crit(w) * (1 + 1e-9) for w in others)


def _trial_windows(x, deriv, order):
    spectrum = D.estimate_spectrum(x, DT)
    max_win = min(x.size // 4, 2001, int(1.5 / (spectrum.freqs[0] * DT)))
    w0 = order + 2 + (order % 2 == 0)
    wins = np.unique(np.round(np.geomspace(w0, max(w0, max_win), D.N_WINDOWS)).astype(int) | 1)
    return {int(w) for w in wins if w <= max_win}


def test_cached_choice_equals_a_fresh_one_and_is_a_copy():
    x = _record(1)
    D._WINDOWS.clear()
    first = D.choose_window({"x": x}, DT, deriv=3)
    first.noise_level["force"] = 123.0                      # a caller adding a channel, as signals.py does
    hits = D._WINDOWS.hits
    again = D.choose_window({"x": x.copy()}, DT, deriv=3)   # another array, the same content
    assert D._WINDOWS.hits == hits + 1
    assert "force" not in again.noise_level
    fresh = D._choose_window({"x": x}, DT, 3, None, None, True, D.filter_coefficients)
    assert (again.window, again.order, again.predicted_rmse) == (fresh.window, fresh.order, fresh.predicted_rmse)


def test_changed_data_is_computed_afresh():
    x = _record(2)
    a = D.estimate_spectrum(x, DT)
    x[:] = _record(3, noise=1e-1)            # the same array object, changed in place
    b = D.estimate_spectrum(x, DT)
    assert b.noise_std > 10 * a.noise_std
    assert D.estimate_spectrum(x, 2 * DT).bandwidth_hz == pytest.approx(b.bandwidth_hz / 2)
    with pytest.raises(ValueError):
        b.freqs[0] = 0.0                     # shared results are read-only


def test_cache_is_bounded_and_keys_by_content():
    c = ContentCache(capacity=2)
    for i in range(3):
        c.put(digest(np.full(4, float(i))), i)
    assert c.get(digest(np.full(4, 0.0))) is None and c.get(digest(np.full(4, 2.0))) == 2
    assert digest(np.zeros(4)) != digest(np.zeros(5)) and digest(np.zeros(4)) != digest(np.zeros(4, np.float32))
    with pytest.raises(ValueError, match="capacity"):
        ContentCache(capacity=0)

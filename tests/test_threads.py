"""The finite differences of the output-error fits on threads (recon/threads.py): the same fit to
the bit as serial, the caller's floating-point error handling kept, bad settings refused."""
from __future__ import annotations

import numpy as np
import pytest

from recon import threads
from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.testing.concealed import concealed_run


def test_thread_count_comes_from_the_environment(monkeypatch):
    monkeypatch.setenv("SHAKERLAB_THREADS", "3")
    assert threads.thread_count() == 3
    monkeypatch.setenv("SHAKERLAB_THREADS", "1")
    assert threads.fd_map() is map
    monkeypatch.delenv("SHAKERLAB_THREADS")
    assert 1 <= threads.thread_count() <= threads.MAX_THREADS


@pytest.mark.parametrize("bad", ["two", "0", "-1", "1.5"])
def test_a_bad_thread_count_is_refused_by_name(monkeypatch, bad):
    monkeypatch.setenv("SHAKERLAB_THREADS", bad)
    with pytest.raises(ValueError, match="SHAKERLAB_THREADS"):
        threads.thread_count()


def test_the_threads_keep_the_callers_error_handling(monkeypatch):
    monkeypatch.setenv("SHAKERLAB_THREADS", "2")
    fmap = threads.fd_map()
    assert fmap is not map
    big = np.array([1e308])
    with np.errstate(over="raise"):
        with pytest.raises(FloatingPointError):
            list(fmap(lambda x: big * x, [10.0, 1.0]))
    with np.errstate(over="ignore"):
        out = list(fmap(lambda x: big * x, [10.0, 1.0]))
    assert np.isinf(out[0][0]) and out[1][0] == 1e308


def test_a_fit_on_threads_is_the_serial_fit_to_the_bit(monkeypatch):
    run, _, extras, baseline = concealed_run("coulomb_friction", duration=1.0, seed=0)
    data = rank.prepare(run, baseline)
    am = AugmentedModel(baseline, {"mu": 0.0, "v0": 1e-3}, ["coulomb_friction"])
    keys = ["c_m", "k_m", "x:mu"]
    scales = {"x:mu": 0.01 * max(float(np.std(d.u)) for d in data)}
    fits = {}
    for n in ("1", "2"):
        monkeypatch.setenv("SHAKERLAB_THREADS", n)
        fits[n] = rank.fit(am, keys, data, scales, max_nfev=8, bounds={"x:mu": (0.0, np.inf)})
    a, b = fits["1"], fits["2"]
    assert a.cost_fit == b.cost_fit and a.mse_held == b.mse_held
    assert a.model.extras == b.model.extras and a.model.baseline.c_m == b.model.baseline.c_m
    assert a.model.baseline.k_m == b.model.baseline.k_m and a.stderr == b.stderr
    # and the fit did move: a test of two fits that stayed at the start would prove nothing
    assert a.model.extras["mu"] > 0.0

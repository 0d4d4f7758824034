"""Single-level identification on ground truth with known parameters (not the benchmark's system).

A force-excited Bouc-Wen oscillator with a cubic stiffness term (which the
benchmark lacks), simulated through the same chain at 40 dB SNR, one
multisine level: the pipeline must find the cubic term on its own (the model
without it leaves more than noise in the residual), drop the spurious
candidates, and recover every parameter.
"""
from __future__ import annotations

import numpy as np
import pytest

from recon.simulation.newmark import NewmarkParameters, simulate_chain
from recon.benchmark.single_level import agent_model_step, identify, linear_step, periodic_record

FS = 750.0
TRUE = NewmarkParameters(c=8 / 1.5, k=3e4 / 1.5, alpha=4e4 / 1.5, gamma=600.0, delta=-300.0, b=1 / 1.5,
                         fn=(("y^3", 2e9),))


def multisine(n, periods, rms, rng):
    f = np.fft.rfftfreq(n, 1 / FS)
    spec = np.zeros(f.size, complex)
    band = (f >= 5) & (f <= 150)
    spec[band] = np.exp(2j * np.pi * rng.random(band.sum()))
    u = np.fft.irfft(spec, n=n)
    return np.tile(u * rms / u.std(), periods)


@pytest.fixture(scope="module")
def record():
    rng = np.random.default_rng(7)
    u = multisine(1024, 4, 50.0, rng)
    y = simulate_chain(TRUE, u, FS, periodic=True)  # from zero state, like the benchmark's training data
    noise = 0.01 * y.std()                          # 40 dB
    return u, y + noise * rng.standard_normal(y.size), noise


def test_preprocessing_estimates_the_noise(record):
    u, y, noise = record
    rec = periodic_record(u, y, FS)
    assert rec.period == 1024 and rec.n_periods_used == 3
    assert rec.noise_rms == pytest.approx(noise, rel=0.1)


def test_agent_model_step_runs_on_one_level(record):
    u, y, _ = record
    rec = periodic_record(u, y, FS)
    ag = agent_model_step(rec, linear_step(rec))
    assert ag.error is None, ag.error
    # the input gain is well determined even where the hysteresis split is not
    assert ag.params.b == pytest.approx(TRUE.b, rel=0.05)
    assert np.isfinite(ag.lam)


@pytest.mark.slow
def test_identify_finds_the_cubic_term_and_the_parameters(record):
    u, y, _ = record
    res = identify(u, y, FS)
    assert res.adequacy["adequate"]
    assert "y^3" in res.adequacy["fn_candidates"]
    p = res.params
    assert [n for n, _ in p.fn] == ["y^3"]
    fit, truth = p.to_benchmark(), TRUE.to_benchmark()
    for name in ("m", "k", "alpha", "gamma"):
        assert fit[name] == pytest.approx(truth[name], rel=0.01), name
    assert fit["delta"] == pytest.approx(truth["delta"], rel=0.03)
    assert fit["c"] == pytest.approx(truth["c"], rel=0.05)
    assert dict(p.fn)["y^3"] == pytest.approx(2e9, rel=0.03)
    model = res.to_model()
    assert model.excitation == "force" and model.inv_m == pytest.approx(p.b)
    assert "y^3" in model.fn_m


@pytest.mark.slow
def test_identify_on_a_sweep_from_rest_uses_the_time_domain_path():
    """A non-periodic single level (a force sweep through the resonance, from rest)."""
    t = np.arange(int(20 * FS)) / FS
    u = 40.0 * np.sin(2 * np.pi * (10.0 * t + 60.0 * t ** 2 / 40.0))  # 10 -> 70 Hz in 20 s
    true = NewmarkParameters(c=TRUE.c, k=TRUE.k, alpha=TRUE.alpha, gamma=TRUE.gamma, delta=TRUE.delta, b=TRUE.b)
    y = simulate_chain(true, u, FS, periodic=False)
    rng = np.random.default_rng(3)
    res = identify(u, y + 0.01 * y.std() * rng.standard_normal(y.size), FS, agent=False)
    assert res.record.kind == "transient"
    assert res.adequacy["adequate"]
    fit, truth = res.params.to_benchmark(), true.to_benchmark()
    for name in ("m", "k", "alpha", "gamma"):
        assert fit[name] == pytest.approx(truth[name], rel=0.01), name
    for name in ("c", "delta"):
        assert fit[name] == pytest.approx(truth[name], rel=0.03), name

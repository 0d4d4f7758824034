"""Bouc-Wen benchmark pipeline (issue 8) on the real training record, kept fast (a few seconds).

The full benchmark (all 5 periods, output-error on the whole record, test-set
e_RMS) is bench/boucwen.py; here: the generation chain with the true
parameters, each identification step on the training record or a slice of it,
and the resampling pieces the chain is built from.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from shakerlab.errors import UserFacingError
from recon.simulation import resampling
from recon.simulation.newmark import NewmarkParameters, newmark_integrate, simulate_chain
from recon.output_error.newmark_refine import refine
from recon.benchmark.single_level import detect_period, hysteresis_step, linear_step, periodic_record

FS = 750.0
TRUE = NewmarkParameters.from_benchmark(m=2.0, c=10.0, k=5e4, alpha=5e4, beta_gamma=800.0, beta_delta=-1100.0)
DATA = Path(os.environ.get("SHAKERLAB_BOUCWEN_DATA")
            or Path(__file__).resolve().parents[2] / "shared" / "data" / "boucwen")


@pytest.fixture(scope="module")
def training():
    h5py = pytest.importorskip("h5py")
    path = DATA / "train_forgione_generated.h5"
    if not path.exists():
        pytest.skip(f"Bouc-Wen benchmark data not found at {DATA}")
    with h5py.File(path, "r") as f:
        return f["multisine/u"][()].ravel().astype(float), f["multisine/y"][()].ravel().astype(float)


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


# ---- the generation chain ---------------------------------------------------------------------------------

def test_chain_with_true_parameters_reproduces_training_slice_at_noise_level(training):
    u, y = training
    n = 3000  # 4 s from zero state
    resid = simulate_chain(TRUE, u[:n], FS, periodic=False) - y[:n]
    assert 5e-6 < rms(resid) < 9e-6  # the benchmark's output noise is ~7.4e-6 m rms (8e-6 nominal)
    # the check can fail: 1 % on k alone nearly doubles the residual
    off = NewmarkParameters.from_benchmark(2.0, 10.0, 5.05e4, 5e4, 800.0, -1100.0)
    assert rms(simulate_chain(off, u[:n], FS, periodic=False) - y[:n]) > 1.2e-5


def test_chain_on_whole_periods_reproduces_the_training_record(training):
    u, y = training
    resid = simulate_chain(TRUE, u, FS, periodic=True, n_warmup_periods=0) - y
    per_period = [rms(r) for r in resid.reshape(5, -1)]
    assert max(per_period) < 8e-6  # the first period (start-up transient) included


def test_newmark_is_second_order_and_converges_to_the_fine_solution():
    rng = np.random.default_rng(3)
    t_end, fs_in = 0.4, 750.0
    u = resampling.upsample_polyphase(40 * rng.standard_normal(int(t_end * fs_in)), 1)
    ref = newmark_integrate(TRUE, resampling.upsample_polyphase(u, 160), 1 / (fs_in * 160))[0][::160]
    errs = []
    for r in (10, 20):
        y = newmark_integrate(TRUE, resampling.upsample_polyphase(u, r), 1 / (fs_in * r))[0][::r]
        errs.append(rms(y - ref))
    assert errs[1] < errs[0] / 3.0  # trapezoidal rule: error / 4 per halving of h
    assert errs[1] < 1e-3 * rms(ref)


# ---- identification steps -----------------------------------------------------------------------------------

def test_single_level_steps_on_the_training_record(training):
    u, y = training
    rec = periodic_record(u, y, FS)
    assert rec.period == 8192 and rec.n_periods_used == 4
    assert 6e-6 < rec.noise_rms < 9e-6  # the noise is estimated from the period-to-period scatter
    lin = linear_step(rec)
    # one level, hysteresis fully active: the equivalent-linear damping is far too high (true c/m = 5)
    assert lin.c > 20.0
    hyst = hysteresis_step(rec, lin).params.to_benchmark()
    truth = TRUE.to_benchmark()
    for name in ("m", "k", "alpha", "gamma", "delta"):
        assert hyst[name] == pytest.approx(truth[name], rel=0.03), name
    assert hyst["c"] == pytest.approx(truth["c"], rel=0.3)


def test_output_error_refines_a_slice_from_a_rough_start(training):
    u, y = training
    n = 1500  # 2 s from zero state keeps this test fast
    truth = TRUE.to_benchmark()
    rough = NewmarkParameters.from_benchmark(m=2.1, c=8.0, k=4.7e4, alpha=5.3e4, beta_gamma=850.0,
                                             beta_delta=-1000.0)
    res = refine(rough, u[:n], y[:n], FS, periodic=False)
    assert res.rms_initial > 5 * res.rms_final
    assert res.rms_final < 9e-6
    fit = res.params.to_benchmark()
    for name in ("m", "k", "alpha", "gamma", "delta"):
        assert fit[name] == pytest.approx(truth[name], rel=0.02), name
    assert fit["c"] == pytest.approx(truth["c"], rel=0.15)


def test_single_level_refuses_a_non_periodic_record():
    rng = np.random.default_rng(0)
    u = rng.standard_normal(4000)
    with pytest.raises(UserFacingError, match="identical periods"):
        detect_period(u)
    with pytest.raises(UserFacingError, match="equal length"):
        periodic_record(u, u[:-1], FS)


# ---- resampling -------------------------------------------------------------------------------------------------

def test_periodic_upsampling_is_exact_for_band_limited_periods():
    n, r = 512, 20
    t_fine = np.arange(n * r) / (n * r)
    fine = sum(np.cos(2 * np.pi * k * t_fine + k) for k in range(1, 60))
    up = resampling.upsample_periodic(fine[::r], r)
    assert np.max(np.abs(up - fine)) < 1e-10 * np.max(np.abs(fine))


def test_polyphase_upsampling_is_accurate_inside_the_band():
    fs, r = 750.0, 20
    t = np.arange(3000) / fs
    t_fine = np.arange(3000 * r) / (fs * r)
    x = np.sin(2 * np.pi * 40 * t) * t  # starts from zero, 40 Hz
    up = resampling.upsample_polyphase(x, r)
    ref = np.sin(2 * np.pi * 40 * t_fine) * t_fine
    core = slice(100 * r, -100 * r)
    assert np.max(np.abs(up[core] - ref[core])) < 1e-5 * np.max(np.abs(ref))


def test_fir_decimation_matches_matlab_fir1_and_is_zero_phase():
    b = resampling.fir1_lowpass(30, 0.5)
    assert b.size == 31 and np.allclose(b, b[::-1]) and b.sum() == pytest.approx(1.0)
    fs, r = 15000.0, 20
    t = np.arange(int(fs)) / fs
    x = np.sin(2 * np.pi * 30 * t + 0.3)
    y = resampling.decimate_chain(x, r)
    assert resampling.prime_factors(r) == [2, 2, 5]
    assert y.size == x.size // r
    inner = slice(10, -10)
    assert np.max(np.abs(y[inner] - x[::r][inner])) < 1e-3  # no delay, pass band gain ~1 at 30 Hz
    # a tone above the final Nyquist frequency is removed
    hi = resampling.decimate_chain(np.sin(2 * np.pi * 600 * t), r)
    assert rms(hi[inner]) < 0.05


def test_resampling_rejects_bad_input():
    with pytest.raises(UserFacingError, match="positive integer"):
        resampling.upsample_periodic(np.ones(8), 2.5)
    with pytest.raises(UserFacingError, match="non-finite"):
        resampling.decimate_fir(np.array([0.0, np.nan] * 40), 2)
    with pytest.raises(UserFacingError, match="too short"):
        resampling.decimate_fir(np.ones(20), 2)


def test_refine_model_accepts_a_hysteretic_model(training):
    from recon.model import HystereticModel
    from recon.output_error.newmark_refine import refine_model

    u, y = training
    n = 1500
    truth = TRUE.to_benchmark()
    rough = HystereticModel(excitation="force", c_m=4.0, k_m=2.4e4, alpha_m=2.6e4, gamma=850.0, delta=-1050.0,
                            inv_m=0.52, provenance={"method": "test"})
    model, res = refine_model(rough, u[:n], y[:n], FS, periodic=False)
    assert isinstance(model, HystereticModel) and model.excitation == "force"
    assert 1.0 / model.inv_m == pytest.approx(truth["m"], rel=0.01)
    assert model.alpha_m / model.inv_m == pytest.approx(truth["alpha"], rel=0.02)
    assert model.provenance["method"] == "test" and model.provenance["output_error"]["rms_final"] < 9e-6


def test_refine_keeps_the_base_excitation_input_coefficient_at_one():
    from recon.model import HystereticModel

    t = np.arange(1500) / FS
    u = 5.0 * np.sin(2 * np.pi * 12 * t) * np.minimum(t, 1.0)  # a ramped tone, like a shaker stage
    true = NewmarkParameters(c=3.0, k=2.0e4, alpha=1.5e4, gamma=500.0, delta=-200.0)
    y = simulate_chain(true, u, FS, periodic=False)
    start = HystereticModel(excitation="base", c_m=3.3, k_m=1.9e4, alpha_m=1.6e4, gamma=450.0, delta=-220.0)
    res = refine(start, u, y, FS, periodic=False)
    assert res.params.b == 1.0
    assert "b" not in res.relative_std
    assert res.params.k + res.params.alpha == pytest.approx(3.5e4, rel=1e-3)

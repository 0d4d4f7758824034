"""The diagnosis's fits iterate on a fast record's thinned samples (DiagnosisSettings.fit_rate) and
judge on every sample: the same parameters within 0.1 % (and of the truth), the held-out figures
over the whole record; the thinned input is low-passed first (recon.simulation.resampling.thinned_input)."""
import dataclasses

import numpy as np
import pytest

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.settings import DEFAULTS
from recon.differentiation import derivatives
from recon.model import HystereticModel
from recon.output_error.polish import decimate
from recon.output_error.problem import get_parameter
from recon.simulation.resampling import thinned_input
from recon.testing.concealed import concealed_run


@pytest.fixture(scope="module")
def fast_record():
    # 8 kHz, a friction concealed: the candidate's fit has a nonlinear parameter to find
    run, truth, extras, baseline = concealed_run("coulomb_friction", strength=2.0, fs=8000.0, duration=2.0, seed=3)
    return run, truth, extras


def test_a_stage_faster_than_twice_the_fit_rate_is_thinned_to_no_less_than_it(fast_record):
    run, truth, _ = fast_record
    data = rank.prepare(run, truth)
    assert [d.fit_step for d in data] == [4, 4, 4]             # 8 kHz / 2 kHz
    th = data[0].thinned()
    assert 1.0 / th.dt >= DEFAULTS.fit_rate and th.y.size == (data[0].y.size + 3) // 4
    assert th.t[0] == data[0].t[0] and th.fit_step == 1
    never = rank.prepare(run, truth, dataclasses.replace(DEFAULTS, fit_rate=0.0))
    assert [d.fit_step for d in never] == [1, 1, 1]
    slow = rank.prepare(run, truth, dataclasses.replace(DEFAULTS, fit_rate=5000.0))
    assert [d.fit_step for d in slow] == [1, 1, 1]              # 8 kHz is not twice 5 kHz


def test_a_thinned_fit_finds_the_full_fit_within_its_standard_error_and_scores_every_sample(fast_record):
    run, truth, extras = fast_record
    start = AugmentedModel(truth, {**extras, "mu": 0.7 * extras["mu"]})
    keys = ["x:mu", "c_m", "k_m"]
    fits = {}
    for rate in (2000.0, 0.0):
        data = rank.prepare(run, truth, dataclasses.replace(DEFAULTS, fit_rate=rate))
        fits[rate] = rank.fit(start, keys, data)
    thin, full = fits[2000.0], fits[0.0]
    n_held = sum(int(d.held.sum()) for d in rank.prepare(run, truth))
    assert thin.n_held == full.n_held == n_held                 # held-out figures over every sample
    for k in keys:
        a, b = get_parameter(thin.model, k), get_parameter(full.model, k)
        # measured: mu 0.040012 thinned, 0.040028 full, truth 0.04; their standard errors (3e-6)
        # take the residual as white noise and are smaller than the two simulations' own difference
        assert a == pytest.approx(b, rel=1e-3), (k, a, b)
        assert a == pytest.approx(get_parameter(AugmentedModel(truth, extras), k), rel=1e-3), (k, a)
    assert thin.nrmse_held == pytest.approx(full.nrmse_held, rel=0.05)


def test_a_thinned_input_is_low_passed_so_a_model_simulates_its_record_as_at_the_full_rate():
    # a small tone on a 5 kHz base record with sub-micron noise, differentiated by a short
    # Savitzky-Golay window (a linear stage's input: a quarter of it noise). Every other sample of
    # that input folds the noise above 1.25 kHz into the 25 Hz mode: the simulation at 2.5 kHz
    # was 2.3 noise stds from the full-rate one (measured); low-passed first, 0.05 (0.01 past
    # the first second, whose first samples are taken as they are)
    fs, q, noise = 5000.0, 2, 4e-7
    t = np.arange(int(4.0 * fs)) / fs
    xb = 7e-5 * np.clip(t / 0.4, 0, 1) ** 3 * np.sin(2 * np.pi * 13.0 * t) + np.random.default_rng(7).normal(0, noise, t.size)
    u = -derivatives(xb, 1 / fs, 25, 3, 2)[2]
    w = 2 * np.pi * 25.0
    m = HystereticModel("base", c_m=2 * 0.013 * w, k_m=w * w, alpha_m=0.0, gamma=0.0, delta=0.0)
    full = m.simulate(t, u)[0][::q]

    def error(thin_u):
        return float(np.sqrt(np.mean((m.simulate(t[::q], thin_u)[0] - full) ** 2))) / noise

    assert error(u[::q]) > 1.0
    assert error(thinned_input(u, q)) < 0.15
    # what lies in the band passes unchanged, at the kept samples
    tones = np.sin(2 * np.pi * 40 * t) + 0.5 * np.cos(2 * np.pi * 150 * t + 0.3)
    assert np.max(np.abs(thinned_input(tones, q) - tones[::q])) < 1e-3
    assert thinned_input(u, q) is thinned_input(u, q)            # made once per input
    assert thinned_input(u, 1) is u


def test_the_diagnosis_and_reconstructs_polish_thin_the_input_the_same_way(fast_record):
    run, truth, _ = fast_record
    d = rank.prepare(run, truth)[0]
    th = d.thinned()
    np.testing.assert_array_equal(th.u, thinned_input(d.u, d.fit_step))
    item, q = decimate((d.t, d.u, d.y), DEFAULTS.fit_rate)
    assert q == d.fit_step
    np.testing.assert_array_equal(item[1], th.u)

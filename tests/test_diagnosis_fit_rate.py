"""The diagnosis's fits iterate on a fast record's thinned samples (DiagnosisSettings.fit_rate) and
judge on every sample: the same parameters within 0.1 % (and of the truth), the held-out figures
over the whole record."""
import dataclasses

import pytest

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.settings import DEFAULTS
from recon.output_error.problem import get_parameter
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

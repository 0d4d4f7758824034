"""The baseline's fn terms chosen again under a candidate (recon.diagnosis.term_revision): a fit
whose structure lacks a true term and holds a wrong one gets the true structure back, and a fit of
the true structure is left as it is."""
import math

import pytest

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.term_revision import revise_terms
from recon.model import HystereticModel
from recon.testing.concealed import concealed_run


@pytest.fixture(scope="module")
def record():
    run, truth, _, _ = concealed_run(None, duration=2.0, seed=3)
    return run, truth


def fitted(run, model):
    data = rank.prepare(run, model)
    am = AugmentedModel(model, {})
    return rank.fit(am, rank.baseline_keys(model), data), data


def test_a_missing_term_is_added_and_a_standing_in_one_dropped(record):
    run, truth = record
    assert "y^2*dy" in truth.fn_m
    wrong = HystereticModel.from_dict(truth.to_dict())
    del wrong.fn_m["y^2*dy"]                 # the true dissipative term missing ...
    wrong.fn_m["dy^3"] = 0.0                 # ... and a wrong one fitted in its place
    fr, data = fitted(run, wrong)
    free = [k for k in rank.baseline_keys(wrong) if not k.startswith("fn:")]
    rev, log = revise_terms(fr, free, [], {}, {}, data, max_nfev=30)
    assert "y^2*dy" in log["terms_after"] and "dy^3" not in log["terms_after"], log
    assert set(log["terms_after"]) == set(truth.fn_m), log
    assert rev.mse_held < 0.5 * fr.mse_held
    b = rev.model.baseline
    assert math.isclose(b.fn_m["y^2*dy"], truth.fn_m["y^2*dy"], rel_tol=0.1)


def test_the_true_structure_is_left_as_it_is(record):
    run, truth = record
    fr, data = fitted(run, truth)
    free = [k for k in rank.baseline_keys(truth) if not k.startswith("fn:")]
    rev, log = revise_terms(fr, free, [], {}, {}, data, max_nfev=30)
    assert log["moves"] == [] and rev is fr

"""The polish's floor test (recon.estimator.finish.settled_cost): the generic restarts run when the
polished fit errs above the noise floor past the transient of its stage's start, not because of it.

The record is the simulated rig's own physics (sim_backend.physics, in process; test_diagnosis_rig's
rig_run): three stages from rest, the true specimen known. A stage switched on from rest starts with
an input the model takes in its own band (a filtered edge), so even the true model errs at the
start; past the first decay times of its mode it is at the noise floor.
"""
from __future__ import annotations


from recon.estimator.adequacy import noise_floor
from recon.estimator.finish import polish_and_validate, settled_cost
from recon.estimator.result import ReconSettings
from recon.estimator.tuning import DEFAULT_TUNING
from recon.model import HystereticModel
from recon.output_error.polish import item_cost
from test_diagnosis_rig import rig_run


def test_the_true_model_is_at_the_floor_past_its_start_and_a_wrong_basin_is_not():
    run, truth = rig_run(duration=6.0)
    stage = run.stage("nonlinear")
    floor = noise_floor(run, "nonlinear")
    limit = DEFAULT_TUNING.floor_factor * floor
    item = truth.fit_item(stage)
    # over the whole stage the start holds even the truth far above the limit (measured 12 x the floor) ...
    assert item_cost(truth, item)[0] > 3 * limit
    # ... past its first decay times the truth is at the floor (measured 0.99 x)
    assert settled_cost(truth, item) < 1.1 * floor
    # a stiffness split the wrong way round (k and alpha swapped, K the same) errs past the start too
    wrong = HystereticModel("base", truth.c_m, truth.alpha_m, truth.k_m, truth.gamma, truth.delta, dict(truth.fn_m))
    assert settled_cost(wrong, wrong.fit_item(stage)) > 2 * limit


def test_a_polish_that_ends_at_the_floor_past_its_start_is_not_restarted_and_says_so():
    run, truth = rig_run(duration=20.0)
    model, _ = polish_and_validate(HystereticModel.from_dict(truth.to_dict()), run, ReconSettings(), {}, {}, False)
    pol = model.provenance["output_error_polish"]
    test = pol["floor_test"]
    assert test["limit"] == DEFAULT_TUNING.floor_factor * test["noise_floor"]
    # measured: 3.9 x the floor over the whole stage (the old test restarted), 1.39 x past the start
    assert test["cost"] > test["limit"] > test["settled_cost"], test
    assert test["restart"] is False and "generic_restart" not in pol


def test_a_polish_in_a_wrong_basin_is_restarted_and_the_restart_reaches_the_floor():
    run, truth = rig_run(duration=6.0)
    wrong = HystereticModel("base", truth.c_m, truth.alpha_m, truth.k_m, truth.gamma, truth.delta, dict(truth.fn_m))
    model, _ = polish_and_validate(wrong, run, ReconSettings(), {}, {}, False)
    pol = model.provenance["output_error_polish"]
    assert pol["floor_test"]["restart"] is True and "generic_restart" in pol, pol["floor_test"]

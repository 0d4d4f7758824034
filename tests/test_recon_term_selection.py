"""Term selection by output error (recon/term_selection.py) against ground truth.

Start from a model with the wrong structure (the true y^2*dy term missing, a spurious y*dy^2
present, parameters a few percent off), polish it, and let the selection repair the structure."""
import numpy as np
import pytest

from recon.output_error.polish import polish
from recon.output_error.problem import OutputError
from recon.output_error.term_selection import select_terms, stage_data
from recon.testing.truth import sdof_run

PARAMS = ("c_m", "k_m", "alpha_m", "gamma", "delta")


@pytest.fixture(scope="module")
def truth_run():
    run, truth = sdof_run("base", snr_db=70.0, seed=1)
    return run, truth


def _wrong_structure(truth, spurious=-5.0e3):
    from dataclasses import replace

    fn = {k: v for k, v in truth.fn_m.items() if k != "y^2*dy"}
    fn["y*dy^2"] = spurious
    return replace(truth, c_m=truth.c_m * 1.05, alpha_m=truth.alpha_m * 0.97, gamma=truth.gamma * 1.04, fn_m=fn)


def test_missing_term_found_and_spurious_term_dropped(truth_run):
    run, truth = truth_run
    stage = run.stage("nonlinear")
    data, q, _ = stage_data(truth, stage)
    start, _ = polish(_wrong_structure(truth), [data], max_nfev=20)
    model, info = select_terms(start, stage, data=(data, q))
    assert info["applied"]
    assert sorted(model.fn_m) == sorted(truth.fn_m), info["steps"]
    model, _ = polish(model, [data], max_nfev=30)
    for k in PARAMS:
        assert getattr(model, k) == pytest.approx(getattr(truth, k), rel=0.01), k
    for k, v in truth.fn_m.items():
        assert model.fn_m[k] == pytest.approx(v, rel=0.02), k
    # the held-out error fell by the accepted steps, and every accepted step lowered the criterion
    accepted = [s for s in info["steps"][1:] if s.get("accepted")]
    assert accepted and all(s["ic"] < s["ic_before"] for s in accepted)


def test_true_structure_is_kept(truth_run):
    run, truth = truth_run
    stage = run.stage("nonlinear")
    data, q, _ = stage_data(truth, stage)
    model, info = select_terms(truth, stage, data=(data, q))
    assert not info["applied"], info["steps"]
    assert sorted(model.fn_m) == sorted(truth.fn_m)


def test_masked_residual_uses_only_the_fit_samples(truth_run):
    run, truth = truth_run
    data, _, _ = stage_data(truth, run.stage("nonlinear"))
    n = data[0].size
    mask = np.zeros(n, bool)
    mask[: n // 3] = True
    prob = OutputError(truth, [data], masks=[mask])
    r = prob.residual(np.zeros(len(prob.keys)))
    assert r.size == n // 3
    full = OutputError(truth, [data]).residual(np.zeros(len(prob.keys)))
    assert full.size == n
    # same simulation, the masked residual is the head of the full one, renormalised
    np.testing.assert_allclose(r * np.sqrt(n // 3), full[: n // 3] * np.sqrt(n), rtol=1e-12, atol=1e-15)

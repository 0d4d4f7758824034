"""Ground truth: simulate the SDOF hysteretic system with known parameters, reconstruct, compare."""
import numpy as np
import pytest

from recon import ReconSettings, reconstruct
from recon.testing.truth import Multisine, make_stage, sdof_run, sdof_truth
from shakerlab.errors import UserFacingError
from shakerlab.run_data import Stage

PARAMS = ("c_m", "k_m", "alpha_m", "gamma", "delta")


def rel_errors(model, truth):
    err = {k: abs(getattr(model, k) / getattr(truth, k) - 1) for k in PARAMS}
    if truth.inv_m is not None:
        err["inv_m"] = abs(model.inv_m / truth.inv_m - 1)
    for k, v in truth.fn_m.items():
        err[k] = abs(model.fn_m.get(k, 0.0) / v - 1)
    return err


@pytest.fixture(scope="module", params=["base", "force"])
def result_80db(request):
    run, truth = sdof_run(request.param, snr_db=80.0, seed=3)
    return reconstruct(run), truth


def test_80db_every_parameter_within_one_percent(result_80db):
    result, truth = result_80db
    err = rel_errors(result.model, truth)
    assert max(err.values()) < 0.01, err


def test_80db_exact_sparsity_pattern(result_80db):
    result, truth = result_80db
    assert set(result.model.fn_m) == set(truth.fn_m)


def test_80db_validation_on_unseen_stage(result_80db):
    result, _ = result_80db
    assert result.validation["stage"] == "validation"
    assert result.validation["nrmse"] < 0.01


def test_equation_error_estimate_is_close_before_polish(result_80db):
    # the equation-error (agent-model) estimate alone is already within a few percent
    result, truth = result_80db
    ee = result.model.provenance["equation_error_estimate"]
    for k in ("k_m", "alpha_m", "gamma"):
        assert abs(ee[k] / getattr(truth, k) - 1) < 0.05, (k, ee[k])
    assert set(ee["fn_m"]) == set(truth.fn_m)


def test_settings_report_choices(result_80db):
    d = result_80db[0].to_dict()
    diff = d["settings"]["differentiation"]
    assert diff["window"] % 2 == 1 and diff["order"] >= 3
    assert all(v > 0 for v in diff["noise_level"].values())
    assert 0 < d["settings"]["threshold"] < 1
    assert d["settings"]["library_order"] == 5


def test_window_adapts_to_noise():
    clean, _ = sdof_run("base", snr_db=100.0, seed=1)
    noisy, _ = sdof_run("base", snr_db=60.0, seed=1)
    from recon.signals import stage_signals

    w_clean = stage_signals(clean.stage("nonlinear"), 3).choice
    w_noisy = stage_signals(noisy.stage("nonlinear"), 3).choice
    # more noise -> longer window relative to the polynomial order
    assert w_noisy["window"] / (w_noisy["order"] + 1) > w_clean["window"] / (w_clean["order"] + 1)
    assert w_noisy["noise_level"]["x_tip"] > 10 * w_clean["noise_level"]["x_tip"]


def _steady_single_tone_force_run():
    truth = sdof_truth("force")
    rng = np.random.default_rng(5)
    st = make_stage("linear", truth, Multisine([8.0], [0.01]), 2000.0, 20.0, 80.0, rng)
    keep = st.t >= 12.0          # start-up transient decayed: a pure steady tone
    lin = Stage("linear", st.t[keep] - st.t[keep][0], {c: v[keep] for c, v in st.channels.items()}, "force")
    run, _ = sdof_run("force", snr_db=80.0, seed=5)
    run.stages["linear"] = lin
    return run


def test_single_tone_force_excitation_is_refused():
    run = _steady_single_tone_force_run()
    with pytest.raises(UserFacingError, match="cannot determine c and K.*rank-deficient.*sweep, a multisine"):
        reconstruct(run)


def test_single_tone_base_excitation_is_fine():
    # base excitation fixes the input coefficient to 1: one tone is enough
    run, truth = sdof_run("base", snr_db=80.0, seed=2)
    from recon.signals import stage_signals
    from recon.steps.linear import fit_linear

    sig = stage_signals(run.stage("linear"), 2, for_regression=False)
    lf = fit_linear(sig.y[0], sig.y[1], sig.y[2], sig.u[0], "base", sig.column_noise)
    assert lf.condition_number < 10
    assert abs(lf.K_m / truth.K_m - 1) < 0.01


def test_missing_stage_named():
    run, _ = sdof_run("base", snr_db=80.0, duration=2.0)
    del run.stages["nonlinear"]
    with pytest.raises(UserFacingError, match="no stage 'nonlinear'"):
        reconstruct(run)


def test_negligible_terms_are_pruned_after_the_output_error_fit():
    # 60 dB, noise seed 1004: the term selection keeps a spurious y^4*dy worth 0.04 % of the
    # elastic force; the pipeline drops it (< 0.2 %) and polishes again
    run, truth = sdof_run("base", snr_db=60.0, seed=1004)
    m = reconstruct(run).model
    assert set(m.fn_m) == set(truth.fn_m)
    pruned = m.provenance.get("pruned")
    assert pruned and pruned["terms"] == ["y^4*dy"] and pruned["share_of_elastic_force"]["y^4*dy"] < 2e-3
    for k in ("c_m", "k_m", "alpha_m", "gamma", "delta"):
        assert abs(getattr(m, k) / getattr(truth, k) - 1) < 0.01, k


def test_unknown_form_is_named():
    with pytest.raises(UserFacingError, match="ReconSettings.form"):
        ReconSettings(form="nonsense")
    with pytest.raises(UserFacingError, match="ReconSettings.fallback_form"):
        ReconSettings(fallback_form="pointwise")      # would otherwise be skipped silently on a bad pass

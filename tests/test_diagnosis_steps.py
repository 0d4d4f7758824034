"""The diagnosis's steps, each on a small synthetic record (recon.testing.concealed): the reference
step, locating, the origins of candidate fits, one candidate's fit (a CandidateFit near the truth),
its scoring (a concealed effect significant, a candidate the record lacks not), the rescoring
against the best null, the stage check, and the settings that hold the steps' tuned numbers."""
import dataclasses
import importlib

import pytest

from recon.diagnosis import rank
from recon.diagnosis.candidate_fit import CandidateFit, fit_candidate
from recon.diagnosis.catalog import CATALOG
from recon.diagnosis.context import DiagnosisContext
from recon.diagnosis.diagnose import (Scores, hold_to_every_stage, locate_step, reference_step,
                                      rescore_against_best_null, score_candidate)
from recon.diagnosis.references import Origin, Origins, candidate_origins
from recon.diagnosis.refits import drop_sets
from recon.diagnosis.settings import DEFAULTS, DiagnosisSettings
from recon.testing.concealed import concealed_run

FRICTION = "coulomb_friction"


@pytest.fixture(scope="module")
def record():
    """A friction concealed in a 1 kHz, 2 s record; the baseline is the truth without it."""
    run, truth, extras, baseline = concealed_run(FRICTION, strength=2.0, fs=1000.0, duration=2.0, seed=3)
    refs = reference_step(run, baseline, 30, DEFAULTS)
    findings, dctx = locate_step(run, refs, 30, DEFAULTS)
    return run, truth, extras, baseline, refs, findings, dctx


def as_given_origins(refs) -> Origins:
    """One origin: the baseline as given with c and k free (a short, deterministic start)."""
    return Origins(common=[Origin(refs.given, ["c_m", "k_m"], ["c_m", "k_m"], "given_c_k")])


def test_the_reference_is_the_better_of_the_null_model_and_the_baseline_as_given(record):
    _, _, _, baseline, refs, _, _ = record
    assert refs.kind == "model"
    assert refs.given.model.baseline.to_dict() == baseline.to_dict()     # scored, nothing moved
    assert refs.ref.mse_held == min(refs.null.mse_held, refs.given.mse_held)
    assert refs.ref_name == ("refit" if refs.ref is refs.null else "as_given")
    assert set(refs.bkeys) <= set(refs.full_free)


def test_the_locate_step_makes_the_context_every_later_step_reads(record):
    run, _, _, _, refs, findings, dctx = record
    assert isinstance(dctx, DiagnosisContext) and dctx.run is run and dctx.data is refs.data
    assert dctx.noise_mse == rank.held_noise_mse(refs.data) and dctx.noise_mse > 0
    assert dctx.rule is DEFAULTS.rule and dctx.max_nfev == 30
    assert isinstance(findings, list) and isinstance(dctx.located, dict)
    with pytest.raises(dataclasses.FrozenInstanceError):
        dctx.max_nfev = 5


def test_origins_start_at_the_reference_and_a_linear_core_follows_its_setting(record):
    _, _, _, _, refs, _, _ = record
    plain = candidate_origins(refs, ["offset"], 30, DEFAULTS)
    names = [o.name for o in plain.common]
    assert names[0] == refs.ref_name and plain.common[0].fit is refs.ref
    assert "linear_core" not in names and plain.core is None    # the reference explains most of the response
    assert plain.without_hysteresis == [] and plain.for_candidate(CATALOG["offset"]) == plain.common
    always = candidate_origins(refs, ["offset"], 30, dataclasses.replace(DEFAULTS, linear_core_nrmse=0.0))
    assert always.core is not None and always.core in always.nulls
    assert [o.name for o in always.common][-1] == "linear_core"
    # the core keeps the baseline's fn terms at 0 (free to a candidate's fit beside it)
    core_fn = always.core.model.baseline.fn_m
    assert set(core_fn) == set(refs.base.baseline.fn_m) and all(v == 0.0 for v in core_fn.values())


def test_one_candidate_is_fitted_into_a_candidate_fit_near_the_truth(record):
    _, _, extras, _, refs, _, dctx = record
    cf = fit_candidate(FRICTION, CATALOG[FRICTION], refs.given, ["c_m", "k_m"], ["c_m", "k_m"], dctx, "given_c_k")
    assert isinstance(cf, CandidateFit)
    assert cf.keys[0] == "x:mu" and cf.free == ["c_m", "k_m"] and cf.started_from == "given_c_k"
    assert cf.fitted_keys()[:2] == ["c_m", "k_m"] and "x:mu" in cf.fitted_keys()
    assert cf.fit.model.get("mu") == pytest.approx(extras["mu"], rel=0.1)
    assert cf.fit.nrmse_held < 0.5 * refs.given.nrmse_held
    assert FRICTION in cf.fit.model.added
    with pytest.raises(dataclasses.FrozenInstanceError):
        cf.keys = []


def test_scoring_names_the_concealed_effect_and_not_a_candidate_the_record_lacks(record):
    _, _, extras, _, refs, _, dctx = record
    origins = as_given_origins(refs)
    entry, cf, against = score_candidate(FRICTION, CATALOG[FRICTION], refs, origins, dctx, {})
    assert entry["significant"] and entry["explained"] > 0.5, entry
    assert entry["started_from"] == "given_c_k" and entry["held_out_nrmse"] == cf.fit.nrmse_held
    assert entry["compared_with_held_out_nrmse"] == against.nrmse_held
    assert cf.fit.model.get("mu") == pytest.approx(extras["mu"], rel=0.1)
    assert origins.nulls                       # the nested null of a significant candidate is kept
    none, cf0, _ = score_candidate("channel_delay", CATALOG["channel_delay"], refs, as_given_origins(refs), dctx, {})
    assert cf0 is not None and not none["significant"], none


def test_a_candidate_no_better_than_the_best_null_loses_its_significance(record):
    _, _, _, _, refs, _, dctx = record
    entry, cf, against = score_candidate(FRICTION, CATALOG[FRICTION], refs, as_given_origins(refs), dctx, {})
    assert entry["significant"]
    scores = Scores(tested=[entry], fits={FRICTION: cf}, references={FRICTION: (against, len(cf.keys))})
    rescore_against_best_null(scores, [refs.given], dctx)            # no better null: unchanged
    assert entry["significant"] and "compared_with_nested_null" not in entry
    rescore_against_best_null(scores, [cf.fit], dctx)                # a null as good as the candidate
    assert not entry["significant"] and entry["compared_with_nested_null"]
    assert entry["compared_with_held_out_nrmse"] == cf.fit.nrmse_held


def test_a_candidate_worse_on_a_held_out_stage_is_held_back_as_partly_explained(record):
    _, _, _, _, refs, _, dctx = record
    entry, cf, _ = score_candidate(FRICTION, CATALOG[FRICTION], refs, as_given_origins(refs), dctx, {})
    scores = Scores(tested=[entry], fits={FRICTION: cf})
    assert hold_to_every_stage(scores, refs.given, dctx) == [] and entry["significant"]
    # a "fit" whose stiffness is 20 % off, marked significant: worse than the baseline on a stage
    off = refs.given.model.copy()
    off.baseline.k_m *= 1.2
    bad = dataclasses.replace(cf, fit=rank.fit(off, [], dctx.data))
    scores = Scores(tested=[{"id": "bad", "significant": True, "explained": 0.5}], fits={"bad": bad})
    partly = hold_to_every_stage(scores, refs.given, dctx)
    assert not scores.tested[0]["significant"] and scores.tested[0]["worse_on_stages"]
    assert partly and partly[0]["ids"] == ["bad"] and partly[0]["explained"] == 0.5


def test_the_steps_tuned_numbers_are_validated_settings_with_the_calibrated_defaults():
    d = DEFAULTS
    assert (d.prune_fit_share, d.shape_screen_nfev, d.prune_pairs_up_to, d.follow_on_share, d.linear_core_nrmse,
            d.start_screen_nfev, d.output_screen_nfev) == (0.9, 6, 5, 0.5, 0.7, 5, 8)
    with pytest.raises(ValueError, match=r"prune_fit_share = 1.5 is outside \[0, 1\]"):
        DiagnosisSettings(prune_fit_share=1.5)
    with pytest.raises(ValueError, match="follow_on_share"):
        DiagnosisSettings(follow_on_share=-0.1)
    with pytest.raises(ValueError, match="shape_screen_nfev must be a whole number"):
        DiagnosisSettings(shape_screen_nfev=2.5)
    with pytest.raises(ValueError, match="start_screen_nfev"):
        DiagnosisSettings(start_screen_nfev=0)
    with pytest.raises(ValueError, match="linear_core_nrmse"):
        DiagnosisSettings(linear_core_nrmse=float("nan"))


def test_drop_sets_follow_the_pairs_setting():
    terms = ["y^2", "y^3", "y^5", "dy^3"]
    assert ("y^2", "dy^3") in drop_sets(terms)                      # 4 terms: pairs up to 5
    fewer = drop_sets(terms, dataclasses.replace(DEFAULTS, prune_pairs_up_to=3))
    assert not any(len(s) == 2 for s in fewer)
    assert tuple(terms) in fewer and ("y^2", "y^3", "y^5") in fewer   # all, and the elastic class


def test_the_operator_windows_progress_names_functions_the_steps_have():
    from rig.gui.diagnosis import STEPS  # lazy: the operator window's module, only for its step names

    for file, name, _, _ in STEPS:
        module = importlib.import_module("recon.diagnosis." + file.removesuffix(".py"))
        assert callable(getattr(module, name, None)), (file, name)

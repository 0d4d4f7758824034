"""reconstruct never ends in a traceback and never answers with an inadmissible model (issues 14, 18).

Adversarial stages either give an admissible model with an adequacy verdict or a
UserFacingError; the simpler-model fallback returns admissible models chosen by held-out
error; a model without hysteresis starts with z0 = 0.
"""
from __future__ import annotations

import numpy as np
import pytest

from recon import ReconSettings, reconstruct
from recon.estimator.adequacy import assess, one_line
from recon.estimator.fallback import admissible, simpler_models
from recon.model import HystereticModel
from recon.testing.truth import sdof_run
from shakerlab.errors import UserFacingError
from shakerlab.run_data import Run, Stage


def _replace_stage(run: Run, name: str, **channels) -> Run:
    st = run.stage(name)
    ch = dict(st.channels, **channels)
    stages = dict(run.stages)
    stages[name] = Stage(name=name, t=st.t, channels=ch, excitation=st.excitation)
    return Run(stages=stages, source=f"{run.source}+{name}-modified")


def _check_answer(run: Run):
    """The contract: an admissible model with a verdict, or a clear refusal."""
    try:
        r = reconstruct(run, ReconSettings())
    except UserFacingError as e:
        assert str(e)        # a message the CLI prints with exit 2
        return None
    assert admissible(r.model), r.model.equation()
    assert r.adequacy["verdict"] in ("adequate", "inadequate")
    assert "adequacy" in r.to_dict()
    return r


@pytest.fixture(scope="module")
def short_run():
    run, truth = sdof_run(snr_db=60.0, duration=4.0, seed=5)
    return run, truth


def test_pure_noise_nonlinear_stage(short_run):
    run, _ = short_run
    rng = np.random.default_rng(1)
    st = run.stage("nonlinear")
    scale = float(np.std(st.channels["x_tip"]))
    noisy = _replace_stage(run, "nonlinear", x_base=rng.normal(0, scale, st.t.size),
                           x_tip=rng.normal(0, scale, st.t.size))
    r = _check_answer(noisy)
    if r is not None:
        assert r.adequacy["verdict"] == "inadequate"


def test_record_with_offset(short_run):
    run, _ = short_run
    st = run.stage("nonlinear")
    off = float(np.std(st.channels["x_tip"])) * 3
    r = _check_answer(_replace_stage(run, "nonlinear", x_tip=st.channels["x_tip"] + off,
                                     x_base=st.channels["x_base"] + off))
    if r is not None:    # a constant offset of both sensors leaves y = x_tip - x_base unchanged
        assert r.adequacy["admissible"]


@pytest.mark.slow
def test_stage_dominated_by_a_second_mode(short_run):
    run, _ = short_run
    st = run.stage("nonlinear")
    amp = 3.0 * float(np.std(st.channels["x_tip"] - st.channels["x_base"]))
    mode = amp * np.sin(2 * np.pi * 61.0 * st.t)
    _check_answer(_replace_stage(run, "nonlinear", x_tip=st.channels["x_tip"] + mode))


@pytest.mark.slow
def test_simpler_models_are_admissible_and_ranked_by_held_out_error(short_run):
    run, truth = short_run
    bad = HystereticModel.from_dict(truth.to_dict())
    bad.alpha_m = -abs(bad.alpha_m)          # an inadmissible estimate, as the issue saw (alpha < 0)
    bad.gamma, bad.delta = -bad.gamma, -bad.delta
    assert not admissible(bad)
    fits = simpler_models(run, ReconSettings(), bad)
    kinds = {f.kind: f for f in fits}
    assert {"linear", "equivalent_linear", "bouc_wen"} <= set(kinds)
    for f in fits:
        if f.failed is None:
            assert admissible(f.model) and np.isfinite(f.held_out_nrmse)
    # the truth has hysteresis: the Bouc-Wen fit from the folded start predicts the held-out
    # stage better than the linear model
    assert kinds["bouc_wen"].held_out_nrmse < kinds["linear"].held_out_nrmse


def test_adequacy_line_states_both_and_points_to_diagnose(short_run):
    run, truth = short_run
    lin = HystereticModel(excitation=truth.excitation, c_m=truth.c_m, k_m=truth.K_m, alpha_m=0.0, gamma=0.0,
                          delta=0.0)
    _, ys = lin.simulate_stage(run.stage("validation"))
    from recon.validation import nrmse
    v = {"nrmse": nrmse(ys, run.stage("validation").y), "stage": "validation"}
    a = assess(lin, v, run)
    assert a["admissible"] and a["verdict"] == "inadequate"
    line = one_line(a)
    assert line.startswith("admissible: yes; adequacy: inadequate") and "shakerlab diagnose" in line


def test_model_without_hysteresis_starts_with_zero_z(short_run):
    run, truth = short_run
    lin = HystereticModel(excitation=truth.excitation, c_m=truth.c_m, k_m=truth.K_m, alpha_m=0.0, gamma=0.0,
                          delta=0.0)
    full = run.stage("validation")
    cut = slice(1001, None)           # starts mid-motion, as a steady-state record does
    st = Stage(name="validation", t=full.t[cut], channels={k: v[cut] for k, v in full.channels.items()},
               excitation=full.excitation)
    y0, v0, z0 = lin.stage_start(st)
    assert abs(y0) > 0 and z0 == 0.0
    hyst = HystereticModel.from_dict(truth.to_dict())
    assert hyst.stage_start(st)[2] != 0.0     # with hysteresis, z0 follows from the equation of motion


def _as_run(rec: dict, source: str) -> Run:
    """An independent-generator recording (base excitation) as a run, as `shakerlab import` builds it."""
    stages = {}
    for name, st in rec["stages"].items():
        t = np.asarray(st["t"], float)
        stages[name] = Stage(name, t - t[0], {c: np.asarray(st[c], float) for c in ("x_base", "x_tip")}, "base",
                             settings={"source_t0": float(t[0])})
    return Run(stages, source=source)


def independent_stress_draw(seed: int, fs: float, snr: float) -> tuple[Run, dict]:
    """Stress seed ``seed`` of the independent generator (paper protocol) as a run, and its truth
    (recon/testing/independent.py shares no code with the estimator)."""
    from recon.testing import independent as ind

    system = ind.random_system(np.random.default_rng([seed, 18]), hysteresis=True)
    rec = ind.add_noise(ind.simulate(system, "paper", fs, seed=seed), snr, seed)
    return _as_run(rec, f"independent:seed={seed}"), rec["truth"]


@pytest.fixture(scope="module")
def independent_seed0():
    """Stress seed 0: paper protocol, 5177 Hz, 50 dB; TMP-like truth with y^2 and y^3."""
    return independent_stress_draw(0, 5177.0, 50.0)


def _worst_error(model, truth):
    keys = {"c_m": model.c_m, "k_m": model.k_m, "alpha_m": model.alpha_m, "gamma": model.gamma,
            "delta": model.delta, **{f"fn:{k}": v for k, v in model.fn_m.items()}}
    return {k: abs(v / truth[k] - 1) for k, v in keys.items() if k in truth}


@pytest.mark.slow
def test_independent_draw_that_hung_the_polish_gets_the_right_answer(independent_seed0):
    """Issue 18: on this draw the equation-error estimate split k and alpha into +-9.7e10 (lambda 9
    against 1197) and polishing it ran for minutes. The polish is skipped from an inadmissible
    start; the fallback of the law's own form (Bouc-Wen + y^2 + y^3, fitted by output error from a
    generic start) is the answer, adequate, with the exact terms."""
    run, truth = independent_seed0
    r = reconstruct(run, ReconSettings())
    assert admissible(r.model), r.model.equation()
    assert r.adequacy["fallback"]["kind"] == "bouc_wen_fewer_terms"
    assert r.adequacy["verdict"] == "adequate", r.adequacy
    assert set(r.model.fn_m) == {"y^2", "y^3"}
    truth = {k: v for k, v in truth.items()} | {f"fn:{k}": v for k, v in truth.get("fn_m", {}).items()}
    err = _worst_error(r.model, truth)
    # measured: every parameter within 2.8 % (c_m), k_m 0.2 %
    assert max(err.values()) < 0.06, err


def test_estimate_that_does_not_simulate_is_restarted_without_its_fn_terms(independent_seed0):
    """An admissible estimate whose simulation diverges on the nonlinear stage is polished again from
    restarted fn terms (none; y^2 and y^3), and the better admissible restart is kept. The estimate
    is the one the pointwise pass made of this draw at 60 dB: y y'^2 for the true y^3, a y'^3, the
    stiffness split wrong (k 392 against 1516); its simulation of the 50 dB stage diverges."""
    from recon.estimator.finish import polish_and_validate
    from recon.estimator.result import ReconSettings as Settings

    run, truth = independent_seed0
    bad = HystereticModel(excitation="base", c_m=1.9891, k_m=391.952, alpha_m=2309.81, gamma=315.882,
                          delta=-185.955, fn_m={"y^2": 171098.0, "y*dy^2": -289737.0, "dy^3": 64.1776})
    assert admissible(bad)
    info, timings = {}, {}
    model, val = polish_and_validate(bad, run, Settings(), info, timings, True)
    pol = model.provenance["output_error_polish"]
    assert pol["restart"]["start_nrmse"] > 1.0          # the estimate itself does not simulate the stage
    assert pol["restart"]["kept"] == "stiffness_terms"
    assert set(model.fn_m) == {"y^2", "y^3"}
    assert val["nrmse"] < 0.02, val
    truth_all = dict(truth) | {f"fn:{k}": v for k, v in truth["fn_m"].items()}
    err = _worst_error(model, truth_all)
    # measured after this one polish (the pipeline polishes again after the term selection):
    # delta 12 % off, every other parameter within 3.3 %
    assert err.pop("delta") < 0.25 and max(err.values()) < 0.06, err


@pytest.fixture(scope="module")
def independent_seed12():
    """Stress seed 12 of the independent generator: paper protocol, 2559 Hz, 60 dB; truth with
    y^2, y^3 and a Bouc-Wen law with delta < 0 (gamma 3927, delta -1454)."""
    return independent_stress_draw(12, 2559.0, 60.0)


@pytest.mark.slow      # a whole reconstruction of a hard record (~5-11 s): the acceptance tier
def test_polish_stuck_above_the_noise_floor_restarts_from_generic_starts(independent_seed12):
    """Issue 18: on this draw the pointwise estimate had lambda = 20 against the truth's 2473 and a
    k/alpha split of -5069/16140. Restarted with y^2 and y^3 its polish stopped at NRMSE 0.0147, 13
    times the stage's noise floor, with k < 0; the term selection then added y y'^2 and y^2 y', and
    the answer was 350 % off, inadequate. The generic restarts (finish.generic_restarts) reach the
    floor: exact terms, every parameter as close as an output-error fit started at the truth (delta
    2.5 %, the rest within 0.7 %)."""
    from recon.estimator.adequacy import noise_floor
    from recon.estimator.finish import polish_and_validate
    from recon.estimator.result import ReconSettings as Settings

    run, truth = independent_seed12
    estimate = HystereticModel(excitation="base", c_m=6.61493, k_m=-5069.16, alpha_m=16139.7, gamma=126.203,
                               delta=-106.638, fn_m={"y^2": 490202.0, "y*dy^2": -144202.0})
    assert admissible(estimate)
    model, val = polish_and_validate(estimate, run, Settings(), {}, {}, True)
    pol = model.provenance["output_error_polish"]
    restart = pol["generic_restart"]
    assert restart["applied"] and restart["cost_before"] > 5 * restart["noise_floor"], restart
    assert pol["nrmse_after"] < 1.5 * noise_floor(run, "nonlinear"), pol["nrmse_after"]
    assert set(model.fn_m) == {"y^2", "y^3"}
    err = _worst_error(model, dict(truth) | {f"fn:{k}": v for k, v in truth["fn_m"].items()})
    assert max(err.values()) < 0.05, err
    assert val["nrmse"] < 0.005, val


# acceptance tier: finish.refine_start runs after every polish (the fast tier's polished reconstructions,
# e.g. test_recon_core.py's result_80db, pass through it); this is the stress-seed-24 regression
@pytest.mark.slow
def test_start_of_a_stage_in_motion_is_refitted_with_the_polished_model():
    """Issue 18: stress seed 24 (paper protocol, f_n 49.5 Hz at 1150 Hz, 80 dB). Its nonlinear stage
    starts while the specimen still moves; fitted with the equation-error estimate, the start had
    y'0 = 1.2e-3 against 6.8e-5 with the truth, and the polish held to it ended with delta 15 % off.
    Refitted with the polished model (finish.refine_start), every parameter is within 1 %."""
    from recon.estimator.finish import polish_and_validate
    from recon.estimator.result import ReconSettings as Settings

    run, truth = independent_stress_draw(24, 1150.0, 80.0)
    estimate = HystereticModel(excitation="base", c_m=21.8911, k_m=53567.2, alpha_m=38175.5, gamma=3215.67,
                               delta=-47.4058, fn_m={"y^2": 23100420.0, "y^3": 0.0})
    model, val = polish_and_validate(estimate, run, Settings(), {}, {}, True)
    pol = model.provenance["output_error_polish"]
    rounds = pol["start_refined"]
    assert any(r.get("cost_after", 1.0) < r.get("cost_before", 0.0) for r in rounds), rounds
    err = _worst_error(model, dict(truth) | {f"fn:{k}": v for k, v in truth["fn_m"].items()})
    assert max(err.values()) < 0.01, err


def _no_hysteresis_record():
    """(run, truth): an independent-generator record (paper protocol, 2 kHz, 60 dB) of a system with
    y^2 and y^3 and no hysteresis."""
    from recon.testing import independent as ind

    seed = 2
    system = ind.random_system(np.random.default_rng([seed, 39]), hysteresis=False, quadratic=True, cubic=True)
    rec = ind.add_noise(ind.simulate(system, "paper", 2000.0, seed=seed), 60.0, seed)
    return _as_run(rec, "independent:no hysteresis"), rec["truth"]


# acceptance tier: the simpler fits, the elastic kind among them, run in the fast tier's
# test_recon_simpler_fit_slack.py (the elastic model taken under a loose slack); this is stress #39
@pytest.mark.slow
def test_a_system_without_hysteresis_gets_the_elastic_simpler_model():
    """Diagnosis stress #39: a system with y^2 and no hysteresis, whose estimate was inadmissible,
    was answered by the Bouc-Wen law with lambda Y = 0.006 (a z that only adds stiffness) and no
    y^2. The simpler kinds now include the elastic model (c, k, y^2, y^3, no z)."""
    run, truth = _no_hysteresis_record()
    fits = {f.kind: f for f in simpler_models(run, ReconSettings(), None)}
    best = min(fits.values(), key=lambda f: f.held_out_nrmse)
    assert best.kind == "elastic", {k: f.held_out_nrmse for k, f in fits.items()}
    assert best.model.alpha_m == 0.0 and admissible(best.model)
    assert abs(best.model.k_m / truth["k_m"] - 1) < 0.01
    for term in ("y^2", "y^3"):
        assert abs(best.model.fn_m[term] / truth["fn_m"][term] - 1) < 0.02
    assert fits["elastic"].held_out_nrmse < 0.5 * fits["equivalent_linear"].held_out_nrmse


@pytest.mark.slow
def test_an_inadequate_full_model_gives_way_to_a_simpler_one_that_predicts_better():
    """Diagnosis stress #26: a system without hysteresis got an admissible estimate with a Bouc-Wen
    law that validated at 0.18; the simpler models reached the noise floor. An inadequate full model
    is now compared with them on the held-out stages and replaced when one halves its error."""
    import json

    from recon.estimator.finish import validate
    from recon.estimator.pipeline import _prefer_simpler
    from recon.estimator.result import ReconResult

    run, truth = _no_hysteresis_record()
    # admissible, but with a spurious hysteresis in place of the stiffness terms
    wrong = HystereticModel("base", c_m=truth["c_m"], k_m=0.7 * truth["k_m"], alpha_m=0.3 * truth["k_m"],
                            gamma=300.0, delta=200.0)
    assert admissible(wrong)
    s = ReconSettings()
    result = ReconResult.of_model(wrong, validate(wrong, run), s)
    before = result.validation["nrmse"]
    out = _prefer_simpler(result, run, s, True, {})
    fb = out.adequacy["fallback"]
    assert fb["used"] and fb["trigger"] == "inadequate" and fb["kind"] == "elastic", fb["chosen_by"]
    assert out.model.alpha_m == 0.0 and set(out.model.fn_m) == {"y^2", "y^3"}
    assert out.validation["nrmse"] < 0.1 * before
    assert fb["replaced_estimate"]["alpha_m"] == pytest.approx(wrong.alpha_m)
    d = json.loads(json.dumps(out.to_dict()))
    assert d["settings"]["simpler_model"] == "elastic" and d["adequacy"]["fallback"]["trigger"] == "inadequate"
    # judged by its figures: no "full model was not admissible" reason
    assert not any("not admissible" in r for r in out.adequacy["reasons"])


def test_a_hysteretic_simpler_model_has_its_terms_revised_by_output_error():
    """A Bouc-Wen law fitted from a generic start after an inadmissible estimate is the full model's
    form: its fn terms are revised by the output error as the full model's are. Recording: the
    independent generator's issue-76 corner (negative delta, a hardening cubic and y^2 y' damping,
    5 kHz, sub-micron noise), where the equation error misses the y^2 y' term and the estimate is
    inadmissible; without the revision the answer lacked the term (delta 52 % off, validation 3.3
    times its noise floor)."""
    import warnings

    from recon.testing.runs import to_run
    from recon.testing.stress import corner_draw, corner_recording
    warnings.filterwarnings("ignore")
    rec = corner_recording(corner_draw(0))
    assert rec["effect_parameters"] in ({}, None) and corner_draw(0)["effect"] == "none"
    r = reconstruct(to_run(rec))
    truth = rec["truth"]
    assert r.hysteresis_info.get("simpler_model") == "bouc_wen_fewer_terms"     # the path under test
    assert set(r.model.fn_m) == set(truth["fn_m"]), r.model.equation()
    for k in ("c_m", "gamma", "delta"):
        assert abs(getattr(r.model, k) / truth[k] - 1) < 0.05, (k, getattr(r.model, k), truth[k])
    assert r.adequacy["validation_nrmse"] < 2 * r.adequacy["noise_floor_nrmse"]



def _corner_fitting_part(i: int):
    """Corner recording i of issue 76 (negative delta, 5 kHz), as the diagnosis reconstructs its baseline."""
    import warnings

    from recon.diagnosis import rank
    from recon.diagnosis.settings import DEFAULTS
    from recon.testing.runs import to_run
    from recon.testing.stress import corner_draw, corner_recording
    warnings.filterwarnings("ignore")
    return rank.fitting_part(to_run(corner_recording(corner_draw(i))), DEFAULTS)


@pytest.mark.slow      # a whole reconstruction of a hard record (~5-11 s): the acceptance tier
def test_the_simpler_bouc_wen_fits_stay_in_the_admissible_region_and_compete_finished():
    """A corner record with a large friction (Fc 0.03 N/kg on a nearly linear loop) whose full estimate
    is inadmissible. Its hysteretic stand-ins, fitted freely, both ended with gamma + delta < 0 and
    were set aside, and reconstruct answered with an elastic model (held-out NRMSE 0.24). Held in the
    region's closure they end admissible; the better one, compared as it would answer (terms revised,
    both stages fitted together), predicts the held-out stage about ten times better and is the answer."""
    from recon.estimator.fallback import HYSTERETIC_KINDS
    run = _corner_fitting_part(164)
    res = reconstruct(run)
    fits = {c["kind"]: c for c in res.adequacy["fallback"]["candidates"]}
    for kind in HYSTERETIC_KINDS:
        assert fits[kind]["admissible"] and "failed" not in fits[kind], fits[kind]
    assert sum(bool(fits[k].get("finished")) for k in HYSTERETIC_KINDS) == 1
    assert res.adequacy["fallback"]["kind"] in HYSTERETIC_KINDS and admissible(res.model)
    assert res.validation["nrmse"] < 0.3 * fits["elastic"]["held_out_nrmse"], (res.validation, fits["elastic"])

"""Issue 13: honest before/after, a noise floor that averaged records cannot fool, physically
plausible effects with intervals.

- fit_before holds the baseline as given; a candidate is reported only when it beats the better
  of the baseline as given and the null model (the refit) on the held-out samples;
- the noise floor is the largest of the spectral floor, a difference-based floor and the sensor's
  resolution, and a candidate must cut the held-out NRMSE by a fraction of the reference's;
- implausible fits (negative delay, a gap outside the recorded range, an interval holding 0) are
  never reported, and every reported parameter has a 95 % interval.
"""
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.diagnose import diagnose, implausible, unexplained_mismatch
from recon.diagnosis.settings import DEFAULTS
from recon.testing.concealed import concealed_run


# ----------------------------------------------------------------- before / after
@pytest.mark.parametrize("effect,seed,name,true", [("coulomb_friction", 0, "mu", 0.02),
                                                   ("sensor_scale", 4, "tip_scale", 0.02)])
@pytest.mark.slow
def test_after_beats_the_baseline_as_given_when_the_refit_is_worse(effect, seed, name, true):
    # the truth without the effect as baseline: refitting it absorbs the effect (friction as viscous
    # damping, a scale error as stiffness) and does worse on the validation stage than as given
    run, _, _, baseline = concealed_run(effect, seed=seed, duration=2.0)
    d = diagnose(run, baseline)
    out = d.to_dict()
    fb = out["fit_before"]
    # fit_before is the baseline as given; the null model under refit_*
    am = AugmentedModel(baseline)
    data = rank.prepare(run, baseline)
    # each fitting stage recorded in motion started as the diagnosis starts it for this model
    as_given = rank.nrmse_per_stage(am, rank.own_starts(am, data))
    assert fb["nrmse"] == pytest.approx(as_given)
    assert fb["held_out_nrmse"] == pytest.approx(as_given["validation"])
    assert fb["held_out_nrmse_as_given"] == fb["held_out_nrmse"]
    assert fb["refit_held_out_nrmse"] == pytest.approx(d.null.nrmse_held)
    assert fb["refit_held_out_nrmse"] > fb["held_out_nrmse"]            # the case this test is about
    assert fb["compared_with"] == "as_given"
    ids = [m["id"] for m in out["missing_physics"]]
    assert ids and ids[0] == effect, out["candidates_tested"]
    after = out["fit_after"]["held_out_nrmse"]
    for m in out["missing_physics"]:
        ev = m["evidence"]
        assert ev["held_out_nrmse_before"] == fb["held_out_nrmse"]
        assert ev["held_out_nrmse_after"] < ev["held_out_nrmse_before"]
        assert ev["held_out_nrmse_after"] < ev["held_out_nrmse_refit"]
    assert after < fb["held_out_nrmse"] and after < fb["refit_held_out_nrmse"]
    assert out["fit_after"]["nrmse"]["validation"] < fb["nrmse"]["validation"]
    p = out["missing_physics"][0]["parameters"][name]
    assert abs(p["value"] / true - 1) < 0.15
    lo, hi = p["interval"]
    assert lo < p["value"] < hi and lo > 0


def test_a_mismatch_far_above_the_noise_that_nothing_explains_is_flagged():
    def result(nrmse):       # a held-out set of rms 1: NRMSE = sqrt(MSE)
        return rank.FitResult(model=None, cost_fit=0.0, mse_held=nrmse ** 2, nrmse={}, nrmse_held=nrmse,
                              n_held=10)
    noise_mse = 0.004 ** 2
    # below max(5 x 0.004, 0.01) = 0.02: nothing to flag; above: flagged with its figures
    assert unexplained_mismatch(result(0.019), noise_mse, []) is None
    u = unexplained_mismatch(result(0.3), noise_mse, [])
    assert u["held_out_nrmse"] == 0.3 and u["noise_nrmse"] == pytest.approx(0.004)
    assert u["nrmse_limit"] == pytest.approx(0.02) and u["named"] == []
    assert "no catalog candidate is significant" in u["note"]
    u = unexplained_mismatch(result(0.3), noise_mse, ["offset"])
    assert "with offset added" in u["note"]
    # a low noise floor: the 1 % floor of reconstruct's adequacy rule holds
    assert unexplained_mismatch(result(0.009), 1e-10, []) is None


# ----------------------------------------------------------------- noise floor
def test_difference_floor_measures_white_noise_under_a_smooth_signal():
    rng = np.random.default_rng(0)
    t = np.arange(20000) / 2000.0
    x = 1e-3 * np.sin(2 * np.pi * 20 * t) + 3e-4 * np.sin(2 * np.pi * 47 * t + 1)
    sigma = 2e-6
    est = rank.difference_noise(x + rng.normal(0, sigma, x.size))
    assert est == pytest.approx(sigma, rel=0.1)


def test_averaged_and_quantised_records_cannot_go_below_the_resolution():
    t = np.arange(20000) / 2000.0
    x = 1e-3 * np.sin(2 * np.pi * 20 * t)
    # an averaged record: all but noise-free; its floor is the resolution bound, 1e-5 of the peak
    f = rank.noise_floor(x + np.random.default_rng(1).normal(0, 1e-11, x.size), 1 / 2000.0)
    assert f["std"] >= rank.RESOLUTION_FRACTION * 1e-3 * 0.999
    assert f["std"] == f["resolution"]
    # a quantised channel: q / sqrt(12)
    q = 1e-5
    fq = rank.noise_floor(np.round(x / q) * q, 1 / 2000.0)
    assert fq["resolution"] == pytest.approx(q / math.sqrt(12), rel=1e-6)
    assert fq["std"] >= q / math.sqrt(12)


def _fr(mse, resid=None, pieces=True):
    """A fit result with held-out MSE ``mse``; ``pieces=False``: no residual kept, so the rule's route
    through blocks_improved is closed (the tests of the other routes)."""
    r = resid if resid is not None else np.random.default_rng(0).normal(0, math.sqrt(mse), 4000)
    return rank.FitResult(model=None, cost_fit=0.0, mse_held=mse, nrmse={}, nrmse_held=math.sqrt(mse), n_held=r.size,
                          resid_held=r if pieces else None)


def test_a_tiny_noise_floor_does_not_make_a_small_gain_significant():
    # averaged record: noise variance 1e-10 of the reference's MSE. A 3 % cut of the held-out NRMSE passes
    # the BIC and gain-over-noise tests trivially (gain over noise ~ 6e8) but is not a meaningful fraction
    ref = _fr(1.0)
    small = rank.score(ref, _fr(0.97 ** 2), 1, 1e-10)
    assert small["gain_over_noise"] > 1e8 and small["dbic"] < -DEFAULTS.rule.bic_margin
    assert small["relative_gain"] == pytest.approx(0.03)
    assert not small["significant"]
    big = rank.score(ref, _fr(0.5 ** 2), 1, 1e-10)
    assert big["significant"]


def test_a_gain_below_the_noise_needs_the_steady_route():
    # without held-out residuals (the route through blocks_improved closed) a candidate that leaves
    # the floor all but 5 % of an excess of 0.3 noise variances is not named: the floor tiers that
    # admitted it were removed on 2026-12-02 (clean stress #1002)
    floor = rank.score(_fr(1.3), _fr(1.005, pieces=False), 1, 1.0)
    assert floor["explained"] >= 0.95 and floor["gain_over_noise"] < DEFAULTS.rule.min_gain_noise
    assert floor["relative_gain"] >= DEFAULTS.rule.min_rel_gain and not floor["significant"]
    # clean stress #65's false candidate: 70 % of an excess of 2 noise variances (gain 1.4)
    part = rank.score(_fr(3.0), _fr(1.6, pieces=False), 1, 1.0)
    assert part["explained"] == pytest.approx(0.7) and part["gain_over_noise"] == pytest.approx(1.4)
    assert not part["significant"]
    # the same gain, better on every held-out piece: the steady route names it
    r = np.random.default_rng(7).normal(0, 1, 8000)
    r /= np.sqrt(np.mean(r ** 2))
    steady = rank.score(_fr(1.3, math.sqrt(1.3) * r), _fr(1.005, math.sqrt(1.005) * r), 1, 1.0)
    assert steady["blocks_improved"] == 1.0 and steady["significant"]
    # clean #1002's figures: 95 % of an excess of 0.29 noise variances, 11 % lower NRMSE, better
    # on 8 of the 10 pieces: not named (the old floor tier named it, a false alarm)
    assert not rank.passes(-20.0, 0.95, 0.278, 0.114, 0.8)
    assert rank.passes(-20.0, 0.95, 0.278, 0.114, 0.9)
    # from MIN_GAIN_NOISE on, the pieces do not matter
    big = rank.score(_fr(3.0), _fr(1.4, pieces=False), 1, 1.0)
    assert big["gain_over_noise"] >= DEFAULTS.rule.min_gain_noise and big["significant"]


# ----------------------------------------------------------------- plausibility
def test_implausible_fits_are_named_with_their_reasons():
    run, _, _, baseline = concealed_run(None, seed=3, duration=1.0)
    data = rank.prepare(run, baseline)
    ref = AugmentedModel(baseline)
    ymax = max(float(np.max(d.y)) for d in data)

    def fr(extras, added, stderr):
        m = AugmentedModel(baseline, dict(extras), [added])
        return rank.FitResult(model=m, cost_fit=0.0, mse_held=1.0, nrmse={}, nrmse_held=1.0, n_held=1, stderr=stderr)

    assert any("negative delay" in w for w in implausible("channel_delay", fr({"delay": -1e-4}, "channel_delay",
                                                                             {"x:delay": 1e-6}), ref, data))
    assert implausible("channel_delay", fr({"delay": 1e-4}, "channel_delay", {"x:delay": 1e-6}), ref, data) == []
    far = fr({"kc": 1000.0, "gap": 3.0 * ymax, "side": 1.0}, "contact_stiffness", {"x:kc": 1.0})
    assert any("outside the recorded displacement range" in w for w in implausible("contact_stiffness", far, ref, data))
    near = fr({"kc": 1000.0, "gap": 0.5 * ymax, "side": 1.0}, "contact_stiffness", {"x:kc": 1.0})
    assert implausible("contact_stiffness", near, ref, data) == []
    # an effect whose 95 % interval holds 0 is not established
    vague = fr({"mu": 0.01, "v0": 1e-4}, "coulomb_friction", {"x:mu": 0.01})
    assert any("holds 0" in w for w in implausible("coulomb_friction", vague, ref, data))
    # a second mode on top of the fundamental contradicts the one-mode part of the model
    w1 = math.sqrt(baseline.K_m)
    same = fr({"w2": 1.05 * w1, "zeta2": 0.02, "phi2": 0.1}, "higher_mode", {"x:w2": 1.0})
    assert any("fundamental" in w for w in implausible("higher_mode", same, ref, data))
    # a broad 'mode' whose half-power band reaches the fundamental's is not a second resonance,
    # wherever its centre lies; one as broad far above the fundamental is a separate resonance
    # whose tail the stages see (judged held out, like any candidate)
    for w2, zeta2 in ((1.25 * w1, 0.3), (1.4 * w1, 0.29), (0.78 * w1, 0.3)):
        broad = fr({"w2": w2, "zeta2": zeta2, "phi2": 1e-4}, "higher_mode", {"x:phi2": 1e-6})
        assert any("half-power band" in w for w in implausible("higher_mode", broad, ref, data)), (w2 / w1, zeta2)
    far = fr({"w2": 5.0 * w1, "zeta2": 0.29996, "phi2": 1e-4}, "higher_mode", {"x:phi2": 1e-6})
    assert implausible("higher_mode", far, ref, data) == []
    from recon.diagnosis.candidates.higher_mode import half_power_bands_overlap
    assert half_power_bands_overlap(100.0, 4.0, 140.0, 0.3)          # 98-182 reaches 98-102
    assert not half_power_bands_overlap(100.0, 4.0, 160.0, 0.3)      # 112-208 does not
    assert half_power_bands_overlap(100.0, 4.0, 70.0, 0.45)          # below: 38.5-101.5
    assert not half_power_bands_overlap(100.0, 4.0, 70.0, 0.3)       # 49-91
    # one held on the bottom of its damping range is not refused: one-tone stages leave a mode's
    # damping free, and the held-out comparison judges the mode (its entry marks the bound)
    held = fr({"w2": 5.0 * w1, "zeta2": 0.001, "phi2": 1e-4}, "higher_mode", {"x:phi2": 1e-6})
    assert implausible("higher_mode", held, ref, data) == []
    mode = fr({"w2": 5.0 * w1, "zeta2": 0.03, "phi2": 1e-4}, "higher_mode", {"x:phi2": 1e-6})
    assert implausible("higher_mode", mode, ref, data) == []


def test_a_parameter_on_the_end_of_its_fitted_range_is_marked_and_said_to_be_unfixed():
    from recon.diagnosis.candidates.higher_mode import ZETA2_RANGE
    from recon.diagnosis.diagnose import _params_of, on_bound
    from recon.diagnosis.wording import diagnosis_text
    assert on_bound(0.001, ZETA2_RANGE) == "lower"
    assert on_bound(0.00101, ZETA2_RANGE) == "lower"
    assert on_bound(0.0012, ZETA2_RANGE) is None
    assert on_bound(0.3, ZETA2_RANGE) == "upper"
    assert on_bound(0.02, ZETA2_RANGE) is None
    assert on_bound(1e-9, (0.0, math.inf)) is None          # a bound at 0: a share of the width
    assert on_bound(0.0, (0.0, math.inf)) == "lower"
    assert on_bound(5.0, (-math.inf, math.inf)) is None     # open ends hold nothing
    assert on_bound(5.0, None) is None
    from recon.model import HystereticModel
    model = AugmentedModel(HystereticModel("base", 1.0, 1e4, 0.0, 0.0, 0.0), {"w2": 400.0, "zeta2": 0.001, "phi2": 0.1},
                           ["higher_mode"])
    res = rank.FitResult(model=model, cost_fit=0.0, mse_held=1.0, nrmse={}, nrmse_held=1.0, n_held=1, stderr={})
    params = _params_of(res, ["x:zeta2", "x:w2"], {"x:zeta2": ZETA2_RANGE, "x:w2": (200.0, 800.0)})
    assert params["zeta2"]["at_bound"] == "lower" and "at_bound" not in params["w2"]
    d = {"missing_physics": [{"id": "higher_mode", "parameters": params,
                              "evidence": {"held_out_nrmse_before": 0.01, "held_out_nrmse_after": 0.002}}]}
    text = diagnosis_text(d)
    assert "zeta2 0.001 on the lower end of its fitted range" in text and "not fixed by the record" in text
    assert "w2" not in text


# ----------------------------------------------------------------- catalog additions
def _with_term(run, baseline, term, value, seed=0):
    """``run`` re-recorded through ``baseline`` plus fn term ``term`` (the augmented simulator)."""
    from shakerlab.run_data import Run, Stage
    truth = AugmentedModel(baseline.__class__.from_dict(baseline.to_dict()))
    truth.baseline.fn_m[term] = value
    data = rank.prepare(run, baseline)
    rng = np.random.default_rng(seed)
    stages = {}
    for d in data:
        st = run.stage(d.name)
        y = truth.simulate(d.t, d.u, d.x_in)[0]
        x_tip = st.channels["x_base"] + y
        x_tip = x_tip + rng.normal(0, 10 ** (-70 / 20) * np.std(x_tip), x_tip.size)
        stages[d.name] = Stage(name=d.name, t=st.t, channels={"x_base": st.channels["x_base"], "x_tip": x_tip},
                               excitation=st.excitation)
    return Run(stages=stages, source=f"test:{term}")


@pytest.mark.parametrize("cid,term,value", [("offset", "y^0", 0.4), ("amplitude_damping", "y^2*dy", 1.5e6)])
def test_new_catalog_entries_are_found(cid, term, value):
    from recon.diagnosis.catalog import CATALOG
    assert {"cubic_stiffness", "hysteresis", "offset", "amplitude_damping"} <= set(CATALOG)
    run0, _, _, baseline = concealed_run(None, seed=7, duration=2.0, snr_db=None)
    baseline.fn_m.pop(term, None)
    run = _with_term(run0, baseline, term, value)
    out = diagnose(run, baseline, candidates=[cid, "coulomb_friction", "quadratic_damping", "cubic_stiffness"]).to_dict()
    ids = [m["id"] for m in out["missing_physics"]]
    assert ids[:1] == [cid], out["candidates_tested"]
    p = out["missing_physics"][0]["parameters"][term]
    assert abs(p["value"] / value - 1) < 0.15 and p["interval"][0] > 0
    assert out["fit_after"]["held_out_nrmse"] < 0.5 * out["fit_before"]["held_out_nrmse"]


# ----------------------------------------------------------------- ambiguity
def test_ambiguous_pair_rule():
    from recon.diagnosis.ambiguity import ambiguous_pair
    ranked = [{"id": "coulomb_friction", "n_eff": 200.0}, {"id": "quadratic_damping", "n_eff": 200.0}]
    # 2 % apart in MSE: 200 ln(1.02) = 4 < 10, the held-out data cannot tell them apart
    assert ambiguous_pair(ranked, set(), {"coulomb_friction": 1.0, "quadratic_damping": 1.02}, 10.0) == \
        ["coulomb_friction", "quadratic_damping"]
    # 20 % apart: 200 ln(1.2) = 36 > 10: the first is clearly better
    assert ambiguous_pair(ranked, set(), {"coulomb_friction": 1.0, "quadratic_damping": 1.2}, 10.0) is None
    # the runner-up adds on top of the first (kept by the forward step): two effects, not rivals
    assert ambiguous_pair(ranked, {"quadratic_damping"}, {"coulomb_friction": 1.0, "quadratic_damping": 1.0},
                          10.0) is None


def test_ambiguous_pair_when_model_error_dominates():
    """A lead the BIC margin counts as clear (n_eff 5000: 5000 ln 1.05 = 244) is still ambiguous when
    it is small beside the mismatch the first candidate leaves over the noise floor."""
    from recon.diagnosis.ambiguity import ambiguous_pair
    ranked = [{"id": "parameter_drift", "n_eff": 5000.0}, {"id": "quadratic_damping", "n_eff": 5000.0}]
    mse = {"parameter_drift": 1.0, "quadratic_damping": 1.05}
    assert ambiguous_pair(ranked, set(), mse, 10.0) is None           # the BIC margin alone
    # half the first one's held-out MSE is model error: a lead of 0.05 is 10 % of it
    assert 0.05 < DEFAULTS.model_error_share * 0.5
    assert ambiguous_pair(ranked, set(), mse, 10.0, noise_mse=0.5) == ["parameter_drift", "quadratic_damping"]
    # the share is a setting: with 5 % of the excess, a lead of 10 % of it tells the two apart
    strict = dataclasses.replace(DEFAULTS, model_error_share=0.05)
    assert ambiguous_pair(ranked, set(), mse, 10.0, noise_mse=0.5, settings=strict) is None
    # near the floor (0.1 of model error left) the same lead is 50 % of it: the first is better
    assert ambiguous_pair(ranked, set(), mse, 10.0, noise_mse=0.9) is None
    # a runner-up kept by the forward step is never a rival
    assert ambiguous_pair(ranked, {"quadratic_damping"}, mse, 10.0, noise_mse=0.5) is None


@pytest.mark.parametrize("pair,stages", [(["coulomb_friction", "quadratic_damping"], ["validation_amplitude"]),
                                         (["sensor_scale", "parameter_drift"], ["validation_frequency"]),
                                         (["sensor_scale", "cubic_stiffness"],
                                          ["validation_amplitude", "validation_frequency"])])
def test_separating_protocol_is_accepted_by_acquire(tmp_path, pair, stages):
    # what `shakerlab acquire --protocol FILE` checks before anything moves: the protocol schema
    # (rig.protocol.load_protocol) and the rig config's limits (the simulated rig's default config)
    from recon.diagnosis.ambiguity import separating_stage
    from rig.config import load_config
    from rig.protocol import load_protocol
    sep = separating_stage(pair)
    assert sep["stages"] == stages and sep["reason"]
    path = tmp_path / "separate.toml"
    path.write_text(sep["protocol_toml"])
    proto = load_protocol(path)
    names = [v.get("name") for v in proto.validation]
    assert [n for n in names if n in stages] == stages
    proto.check_against_limits(load_config(None).limits)


def _friction_beside_absorbing_terms(also_free: list, also_scales: dict):
    """A friction recording, a baseline that absorbed the friction into y'^3, y'^5 (and the
    ``also_free`` terms of its own), and friction fitted next to them with c and k."""
    run, _, extras, baseline = concealed_run("coulomb_friction", duration=2.0, seed=0)
    data = rank.prepare(run, baseline)
    am = AugmentedModel(baseline)
    am.baseline.fn_m.update({"dy^3": 0.0, "dy^5": 0.0})
    absorbed = rank.fit(am, ["c_m", "k_m", *also_free, "fn:dy^3", "fn:dy^5"], data,
                        {"fn:dy^3": 1.0, "fn:dy^5": 1.0, **also_scales}, max_nfev=60).model
    given = rank.fit(absorbed, [], data)
    m = absorbed.copy()
    m.added = ["coulomb_friction"]
    m.extras.update(mu=0.01, v0=1e-3)
    sc, b = {"x:mu": 0.01}, {"x:mu": (0.0, np.inf)}
    fr = rank.fit(m, ["c_m", "k_m", "x:mu"], data, sc, max_nfev=30, bounds=b)
    return extras, baseline, data, absorbed, given, fr, sc, b


def test_a_candidate_is_refitted_without_the_baseline_terms_that_absorbed_it():
    # a baseline that absorbed friction into y'^3 and y'^5 (fitted to the friction recording, as a
    # reconstruction without friction in its library does): friction fitted next to them explains
    # little; refitted without them it recovers mu and predicts the held-out stage far better
    from recon.diagnosis.candidate_fit import CandidateFit
    from recon.diagnosis.refits import prune_absorbed

    extras, _, data, absorbed, given, fr, sc, b = _friction_beside_absorbing_terms([], {})
    assert abs(fr.model.get("mu") / extras["mu"] - 1) > 0.5          # next to y'^3, y'^5: far off
    pruned, drop, against = prune_absorbed(CandidateFit(fr, ["x:mu"], sc, b, ["c_m", "k_m"]), given, data, 30)
    best = pruned.fit
    # the absorbing terms go: dropped, or (kept and refitted beside the candidate) near 0
    assert drop and set(drop) <= {"dy^3", "dy^5"}
    for t in ("dy^3", "dy^5"):
        assert abs(best.model.baseline.fn_m.get(t, 0.0)) < 0.05 * abs(absorbed.baseline.fn_m[t])
    assert abs(best.model.get("mu") / extras["mu"] - 1) < 0.05
    assert best.nrmse_held < 0.2 * fr.nrmse_held
    # scored against the better of the reference and the baseline without the same terms
    assert against.mse_held <= given.mse_held
    assert rank.score(against, best, 1, given.mse_held * 1e-6)["significant"]
    # a candidate that explains little of the fitting mismatch is left as it is
    assert prune_absorbed(CandidateFit(given, ["x:mu"], sc, b, ["c_m", "k_m"]), given, data, 30)[1] == ()


def test_the_baseline_terms_kept_beside_the_absorbing_ones_are_refitted_with_the_candidate():
    # the baseline absorbed friction into y'^3, y'^5 and its own y^2 y' (moved from 3e6 to about
    # 4e6); once friction is in, y^2 y' is refitted with it and returns to its true value
    from recon.diagnosis.candidate_fit import CandidateFit
    from recon.diagnosis.refits import prune_absorbed

    extras, baseline, data, absorbed, given, fr, sc, b = _friction_beside_absorbing_terms(["fn:y^2*dy"],
                                                                                         {"fn:y^2*dy": 1e6})
    true_y2dy = baseline.fn_m["y^2*dy"]
    assert abs(absorbed.baseline.fn_m["y^2*dy"] / true_y2dy - 1) > 0.2
    pruned, drop, against = prune_absorbed(CandidateFit(fr, ["x:mu"], sc, b, ["c_m", "k_m"]), given, data, 30)
    best, free = pruned.fit, pruned.free
    assert drop and "fn:y^2*dy" in free and "y^2*dy" not in drop
    assert abs(best.model.baseline.fn_m["y^2*dy"] / true_y2dy - 1) < 0.05
    assert abs(best.model.get("mu") / extras["mu"] - 1) < 0.05
    assert best.nrmse_held < 0.2 * fr.nrmse_held
    # the reference refits the same baseline terms without the candidate: no credit for the refit
    assert against.mse_held <= given.mse_held


def test_drop_sets_take_out_each_parity_class_of_the_velocity_terms():
    from recon.diagnosis.refits import drop_sets

    terms = ["y^2", "y^3", "y^2*dy", "dy^3", "y^5", "y^4*dy", "dy^5"]
    sets = drop_sets(terms)
    assert ("y^2*dy", "dy^3", "y^4*dy", "dy^5") in sets          # the dissipative ones (odd in y')
    assert ("y^2", "y^3", "y^5") in sets                         # the elastic ones
    assert tuple(terms) in sets and all((t,) in sets for t in terms)
    assert len(sets) == len(set(sets))
    # a class that is a single term or the whole set is not repeated
    assert drop_sets(["y^2", "dy^3"]) == [("y^2",), ("dy^3",), ("y^2", "dy^3")]


def test_a_held_out_stage_recorded_in_motion_starts_from_a_fitted_state():
    # the validation stage cut to start 1.3 s in (in motion); its edge estimate is spoilt as a
    # noisy edge derivative spoils it (stress #10, rig protocol at 50 dB: the true model scored
    # 0.139 from the edge start, 0.0068 from a fitted one)
    from shakerlab.run_data import Run, Stage

    run, truth, _, _ = concealed_run(None, seed=5, duration=3.0)
    st = run.stage("validation")
    k = int(1.3 / st.dt)
    cut = Stage("validation", st.t[k:] - st.t[k], {c: v[k:] for c, v in st.channels.items()}, st.excitation,
                settings=dict(st.settings, source_t0=float(st.t[k])))
    run = Run({**{n: run.stage(n) for n in run.stages if n != "validation"}, "validation": cut})
    am = AugmentedModel(truth)
    data = rank.prepare(run, truth)
    d = next(x for x in data if x.name == "validation")
    assert any(d.initial) and not d.fit.any()
    y0, v0, z0 = d.initial
    d.initial = (1.5 * y0, 0.5 * v0 + 0.02 * d.rms * math.sqrt(truth.K_m), z0)
    edge = am.simulate(d.t, d.u, d.x_in, d.initial, step_factor=d.step_factor)[0]
    start = rank.held_start(am, d)
    fitted = am.simulate(d.t, d.u, d.x_in, start, step_factor=d.step_factor)[0]

    def nrmse(ys):
        return float(np.sqrt(np.mean((ys - d.y) ** 2)) / d.rms)

    assert nrmse(edge) > 10 * d.noise / d.rms                # the spoilt edge start: far above the noise
    assert nrmse(fitted) < 3 * d.noise / d.rms               # fitted: at the noise
    assert rank.fit(am, [], data).nrmse["validation"] == pytest.approx(nrmse(fitted), rel=1e-6)


def test_a_candidate_starts_stages_in_motion_from_its_own_force_balance():
    # z0 of a stage recorded in motion comes from the force balance at its first sample, so with the
    # baseline's terms it holds whatever the baseline leaves out. A candidate that models that force
    # (a constant one here) must take its own z0, not count the force twice (independent stress #22,
    # rig protocol: the true model with its offset scored 1.82 on the linear stage from the
    # baseline's z0, 0.083 from its own)
    from shakerlab.run_data import Run, Stage

    run0, _, _, baseline = concealed_run(None, seed=7, duration=2.0, snr_db=None)
    baseline.fn_m.pop("y^0", None)
    full = _with_term(run0, baseline, "y^0", 0.4)
    stages = {}
    for n in full.stages:
        st = full.stage(n)
        k = int(0.9 / st.dt)
        stages[n] = Stage(n, st.t[k:] - st.t[k], {c: v[k:] for c, v in st.channels.items()}, st.excitation,
                          settings=dict(st.settings, source_t0=float(st.t[k])))
    run = Run(stages)
    data = rank.prepare(run, baseline)
    truth = AugmentedModel(baseline.__class__.from_dict(baseline.to_dict()))
    truth.baseline.fn_m["y^0"] = 0.4
    moving = [d for d in data if any(d.initial)]
    assert moving
    for d in moving:
        assert rank.initial_for(truth, d)[2] == pytest.approx(d.initial[2] - 0.4, rel=1e-9, abs=1e-9)
        assert rank.initial_for(AugmentedModel(baseline), d) == d.initial
    fr = rank.fit(truth, [], data)
    for d in moving:
        if d.fit.any():     # a fitted stage starts from that state (a held-out one fits its own start)
            doubled = truth.simulate(d.t, d.u, d.x_in, d.initial)[0]
            before = float(np.sqrt(np.mean((doubled - d.y) ** 2)) / d.rms)
            assert fr.nrmse[d.name] < 0.5 * before, (d.name, fr.nrmse[d.name], before)
    assert fr.nrmse["nonlinear"] < 0.01 and fr.nrmse["validation"] < 0.01, fr.nrmse


def _stress6():
    """Independent stress recording #6 (a stiffness drift of -0.074 %/s, sweeps, 57.7 dB) as a run,
    the paper baseline reconstructed from it (its figures, stored), and the generator's record."""
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run

    rec = recording(draw(6))
    base = model_of({"c_m": 1.7967713009469042, "k_m": 1141.9717984012016, "alpha_m": 29.3597336404073,
                     "gamma": 0.407418370328729, "delta": 1187.1075854625265,
                     "fn_m": {"y^2": 64988.61889301294, "y^3": 59009157.822042435}})
    return to_run(rec), base, rec


def test_a_held_out_stage_in_motion_starts_from_its_edge_even_when_the_baseline_fits_it_badly():
    # stress #6: the validation stage begins 1 s after the nonlinear one, in its ringing. The paper
    # baseline reconstructed from that record is so wrong there that it simulates the stage better
    # from rest than from the edge estimate; the start must not be judged by it, or every model, the
    # truth too, scores 0.36-0.39 there
    run, base, rec = _stress6()
    from recon.testing.runs import true_model

    data = rank.prepare(run, base)
    val = next(x for x in data if x.name == "validation")
    assert any(val.initial) and not val.fit.any()
    am = AugmentedModel(base)
    rest = am.simulate(val.t, val.u, val.x_in)[0]
    edge = am.simulate(val.t, val.u, val.x_in, val.initial)[0]
    assert np.sum((rest - val.y) ** 2) < np.sum((edge - val.y) ** 2)    # the baseline would pick rest
    truth, _ = true_model(rec)
    fr = rank.fit(truth, [], data)
    assert fr.nrmse["validation"] < 2 * val.noise / val.rms, (fr.nrmse, val.noise / val.rms)


def test_a_held_out_start_finds_a_hysteretic_state_far_from_the_edge_and_from_zero():
    # stress #617 (the paper's protocol): the validation stage begins in motion with the true
    # model's z at -0.209; the edge estimate puts it at +0.048, and a start fit from there or from 0
    # stays near 0 (-0.0023), where the truth scores 0.10 on that stage against 0.0043 from its
    # true state. The start scans z0 across the law's reach first.
    from recon.testing.stress import draw, recording
    from recon.testing.runs import to_run, true_model

    rec = recording(draw(617))
    truth, _ = true_model(rec)
    data = rank.prepare(to_run(rec), truth.baseline)
    d = next(x for x in data if x.name == "validation")
    assert any(d.initial) and not d.fit.any()
    ts = rec["stages"]["validation"]["truth_states"]
    true_start = (float(ts["y"][0]), float(ts["dy"][0]), float(ts["z"][0]) / rec["system"]["m"])
    assert abs(d.initial[2] - true_start[2]) > 0.2 * rank.z_reach(truth.baseline, d.y)

    def nrmse(state):
        ys = truth.simulate(d.t, d.u, d.x_in, tuple(state))[0]
        return float(np.sqrt(np.mean((ys - d.y) ** 2)) / d.rms)

    start = rank.held_start(truth, d)
    assert start[2] == pytest.approx(true_start[2], rel=0.1)
    assert nrmse(start) < 1.2 * nrmse(true_start) < 2 * d.noise / d.rms
    assert nrmse(d.initial) > 10 * nrmse(start)


@pytest.mark.slow
def test_an_equation_step_that_points_the_wrong_way_is_not_the_start():
    # stress #6 against its paper baseline: from the refit, the equation-error step put the drift at
    # +0.0016/s (truth -0.00074/s) and the output-error fit stayed in that valley (held-out 0.065,
    # named beside contact_stiffness at 0.059); from no step the fit reaches the truth
    run, base, rec = _stress6()
    dg = diagnose(run, baseline=base, candidates=["parameter_drift"])
    c = dg.candidates[0]
    assert c["significant"] and c["explained"] > 0.95, c
    drift = dg.best.get("drift")
    assert drift == pytest.approx(rec["effect_parameters"]["drift_rate"], rel=0.05)


def test_a_candidate_whose_term_does_nothing_gets_no_credit_for_where_its_fit_ended():
    # stress #26 (clean): the null model's refit stopped short, and friction at mu = 5e-6 m/s^2 (nothing
    # beside a restoring force of 28 m/s^2) was named for the better baseline parameters its own fit
    # reached. Here: a clean independent recording, a baseline 4 % stiff as the reference, and a
    # "friction" fit whose mu is nil but whose c and k are the truth's
    from recon.testing.runs import model_of, to_run
    from recon.diagnosis.candidate_fit import CandidateFit
    from recon.diagnosis.refits import nested_null
    from recon.testing import independent as ind

    system = ind.random_system(np.random.default_rng(3), hysteresis=False, quadratic=False, cubic=False)
    rec = ind.add_noise(ind.simulate(system, "paper", 2000.0, "none", 1.0, seed=3), 60.0, 3)
    run = to_run(rec)
    truth = model_of(ind.truth_per_unit_mass(system))
    wrong = model_of({**ind.truth_per_unit_mass(system), "k_m": 1.04 * truth.k_m})
    data = rank.prepare(run, wrong)
    ref = rank.fit(AugmentedModel(wrong), [], data)
    idle = AugmentedModel(truth, {"mu": 1e-9 * truth.k_m, "v0": 1e-3}, ["coulomb_friction"])
    fr = rank.fit(idle, ["x:mu", "c_m", "k_m"], data, max_nfev=5)
    noise = rank.held_noise_mse(data)
    assert rank.score(ref, fr, 1, noise)["significant"]       # against the reference it "explains" a lot
    nn = nested_null(CandidateFit(fr, ["x:mu"], {}, {}, ["c_m", "k_m"]), "coulomb_friction", ref.model, data, 30)
    assert "mu" not in nn.model.extras and "v0" not in nn.model.extras
    assert "coulomb_friction" not in nn.model.added
    assert nn.mse_held < 1.05 * fr.mse_held
    assert not rank.score(nn, fr, 1, noise)["significant"]


def test_a_candidate_keeps_its_score_from_before_its_nested_null():
    # the score that made a nested null be fitted decides whether that null exists (and so what every
    # candidate is scored against again): kept in the entry, so a change of the rule can be judged on
    # stored rows. A real offset against the true system with its k 4 % off: the reference is the
    # refit, whose c and k took up some of the offset; the offset's fit moves c and k back, and its
    # nested null (that fit with the offset off, c and k refitted from there) predicts the held-out
    # samples better than the reference, so the candidate is scored again against it
    from recon.testing.runs import model_of, to_run
    from recon.diagnosis import diagnose as D
    from recon.testing import independent as ind

    system = ind.random_system(np.random.default_rng(3), hysteresis=False, quadratic=False, cubic=False)
    rec = ind.add_noise(ind.simulate(system, "paper", 2000.0, "offset", 1.0, seed=3), 60.0, 3)
    run = to_run(rec)
    params = ind.truth_per_unit_mass(system)
    dg = D.diagnose(run, baseline=model_of({**params, "k_m": 1.04 * params["k_m"]}), candidates=["offset"])
    c = dg.candidates[0]
    assert c["compared_with_nested_null"]
    # scored against the nested null, which beats the reference
    assert c["compared_with_held_out_nrmse"] < dg.reference.nrmse_held
    first = c["before_nested_null"]
    assert first["significant"] and first["explained"] > 0.99 and first["blocks_improved"] == 1.0
    assert set(first) == set(D.SCORE_KEYS)
    # the entry's score is the one against the nested null, not the one kept
    assert c["gain_over_noise"] < first["gain_over_noise"]
    assert "before_nested_null" in dg.to_dict()["candidates_tested"][0]


@pytest.mark.slow
def test_friction_fits_its_smoothing_velocity_where_a_small_stage_moves_in_pre_sliding():
    # independent sweeps whose small stage moves at about the generator's v_eps: there the friction acts
    # as a viscous damper mu / v0, and a v0 held at one of the starts (1-20 % of that stage's rms
    # velocity) cannot fit it (stress #119: that stage stayed at NRMSE 0.50). v0 is fitted with mu
    from recon.testing.runs import model_of, to_run, true_model
    from recon.testing import independent as ind

    system = ind.random_system(np.random.default_rng(2), hysteresis=False, quadratic=False, cubic=True)
    rec = ind.add_noise(ind.simulate(system, "sweep", 2000.0, "coulomb_friction", 1.0, seed=2), 60.0, 2)
    run = to_run(rec)
    truth, _ = true_model(rec)
    small = min(np.std(np.gradient(s.channels["x_tip"] - s.channels["x_base"], s.t)) for s in run.stages.values())
    assert truth.get("v0") > 0.5 * small            # the smallest stage is in pre-sliding
    dg = diagnose(run, baseline=model_of(ind.truth_per_unit_mass(system)), candidates=["coulomb_friction"])
    assert dg.candidates[0]["significant"], dg.candidates[0]
    assert dg.best.get("mu") == pytest.approx(truth.get("mu"), rel=0.02)
    assert dg.best.get("v0") == pytest.approx(truth.get("v0"), rel=0.02)
    assert set(dg.missing[0]["parameters"]) == {"mu", "v0"}


@pytest.mark.slow
def test_a_contact_starts_on_the_side_whose_step_stiffens():
    # stress #60 (a one-sided stop on a multisine, 50.7 dB) against its paper baseline, which holds a
    # y^2 term where the stop's asymmetry went. The equation residuals of the six contact starts
    # (two sides, three gaps) differ by 3 % at most; the lowest was the wrong side, stepped to a
    # negative kc, and the fit from there ended worse than no contact. A start whose step stays
    # inside kc >= 0 is taken first
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(60))
    base = model_of({"c_m": 6.76807713542047, "k_m": 54444.32164214024, "alpha_m": 34110.598553708565,
                     "gamma": 2965.9304137720283, "delta": -663.8022471776521,
                     "fn_m": {"y^2": 936317.1033636947, "y^3": 9829048364.107658}})
    dg = diagnose(to_run(rec), baseline=base, candidates=["contact_stiffness"])
    c = dg.candidates[0]
    assert c["significant"], c
    truth, _ = true_model(rec)
    assert dg.best.get("side") == truth.get("side")
    assert dg.best.get("gap") == pytest.approx(truth.get("gap"), rel=0.02)
    assert dg.best.get("kc") == pytest.approx(truth.get("kc"), rel=0.05)


@pytest.mark.slow
def test_a_contact_the_baseline_took_up_as_even_stiffness_is_fitted_without_it():
    # stress #801 (a one-sided stop at 0.23 mm on the paper protocol, 41 dB) against its paper
    # baseline, whose y^4 took up the stop's asymmetry: it fits the fitting stages better than the
    # truth and predicts the held-out stage worse. The contact fitted beside the y^4 stayed near 0;
    # from the baseline without its even stiffness terms it is named, against that core as a null
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model
    from recon.diagnosis.references import even_stiffness_terms

    rec = recording(draw(801))
    base = model_of({"c_m": 5.83743725285157, "k_m": 20647.266580348132, "alpha_m": 29064.499749910967,
                     "gamma": 1485.674425390101, "delta": 3981.454020949859,
                     "fn_m": {"y^4": 21736695874103.07, "y^3": 78745821489.23776}})
    assert even_stiffness_terms(AugmentedModel(base)) == ["y^4"]
    dg = diagnose(to_run(rec), baseline=base, candidates=["contact_stiffness", "sensor_scale"])
    out = dg.to_dict()
    assert [m["id"] for m in out["missing_physics"]] == ["contact_stiffness"], out["candidates_tested"]
    c = next(t for t in out["candidates_tested"] if t["id"] == "contact_stiffness")
    assert c["started_from"] == "without_even_stiffness" and "y^4" in c["baseline_terms_dropped"]
    # scored against the core without the y^4, which predicts the held-out stage better than the
    # baseline as given: no credit for the drop
    assert c["compared_with_held_out_nrmse"] < out["fit_before"]["held_out_nrmse"]
    truth, _ = true_model(rec)
    assert dg.best.get("side") == truth.get("side")
    assert dg.best.get("gap") == pytest.approx(truth.get("gap"), rel=0.3)
    # the scale, named first before the change (a tip-sensor error the record does not hold), is
    # not significant against that core
    s = next(t for t in out["candidates_tested"] if t["id"] == "sensor_scale")
    assert not s["significant"]


@pytest.mark.slow
def test_a_sensor_scale_the_baseline_took_up_as_hysteresis_is_fitted_without_it():
    # stress #813 (a -0.92 % tip-sensor scale on the rig protocol, 64 dB, no loop in the truth)
    # against its paper baseline, which got a Bouc-Wen law (alpha 820) the truth does not have.
    # Fitted from that baseline (as given, refitted, or with the scale alone free) the scale ended
    # at held-out 0.0073 or worse against 0.0035 as given and was not named; from the baseline
    # without its law it reaches the truth's scale and held-out figure
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(813))
    base = model_of({"c_m": 4.291391800363192, "k_m": 16973.194851877826, "alpha_m": 820.0482406801569,
                     "gamma": 7.691925114272635e-05, "delta": 360726.39226081973,
                     "fn_m": {"y^2": 4505325.292742443, "y^3": 16931459159.70444}})
    dg = diagnose(to_run(rec), baseline=base, candidates=["sensor_scale"])
    out = dg.to_dict()
    assert [m["id"] for m in out["missing_physics"]] == ["sensor_scale"], out["candidates_tested"]
    c = out["candidates_tested"][0]
    assert c["started_from"] == "without_hysteresis" and c["hysteresis_dropped"]
    truth, _ = true_model(rec)
    assert dg.best.get("tip_scale") == pytest.approx(truth.get("tip_scale"), rel=0.05)
    assert dg.best.baseline.alpha_m == 0.0
    # the held-out error falls by more than half against the better of the baseline as given and
    # the core without the law (a null model too: no credit for the drop alone)
    assert c["held_out_nrmse"] < 0.5 * min(c["compared_with_held_out_nrmse"], out["fit_before"]["held_out_nrmse"])


@pytest.mark.slow
def test_hysteresis_is_fitted_inside_the_admissible_bouc_wen_range():
    # stress #194 (paper protocol, 60 dB), the truth without its Bouc-Wen law as the baseline: the
    # hysteresis fit started at alpha = 0 without a bound went to alpha = -414 beside a stiffer k
    # (inadmissible, never reported, and cubic_stiffness was named instead). alpha is bounded at 0 and
    # starts inside the bound
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(194))
    dg = diagnose(to_run(rec), baseline=model_of(rec["baseline"]), candidates=["hysteresis"])
    assert dg.candidates[0]["significant"], dg.candidates[0]
    truth, _ = true_model(rec)
    assert dg.best.baseline.alpha_m == pytest.approx(truth.baseline.alpha_m, rel=0.02)
    assert dg.best.baseline.k_m == pytest.approx(truth.baseline.k_m, rel=0.01)


@pytest.mark.slow
def test_hysteresis_starts_with_part_of_the_baselines_stiffness_in_its_loop():
    # stress #1247 (sweeps, 78.8 dB): the baseline, the truth without its Bouc-Wen law, keeps the
    # law's small-amplitude stiffness in k (K = 2273 against the truth's k 2002 + alpha 271). From
    # alpha = 0 beside that k the fit ended in a narrow loop (gamma 5219, held-out 0.228 against
    # the truth's 0.00068) and quadratic damping was named first; from a start with 10 % of K in
    # the loop and k lowered by as much it reaches the truth
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(1247))
    base = model_of(rec["baseline"])
    assert base.alpha_m == 0.0
    dg = diagnose(to_run(rec), baseline=base, candidates=["hysteresis"])
    c = dg.candidates[0]
    assert c["significant"] and c["held_out_nrmse"] < 0.01 * c["compared_with_held_out_nrmse"], c
    truth, _ = true_model(rec)
    assert dg.best.baseline.alpha_m == pytest.approx(truth.baseline.alpha_m, rel=0.02)
    assert dg.best.baseline.k_m == pytest.approx(truth.baseline.k_m, rel=0.01)
    assert dg.best.baseline.gamma == pytest.approx(truth.baseline.gamma, rel=0.05)


def test_a_fitting_stage_at_rest_off_centre_starts_where_each_model_puts_it():
    # stress #191 (a constant force, the paper's protocol, 66.5 dB): the linear stage is recorded at
    # rest at the offset's static displacement. The paper baseline, without the offset, simulates it
    # as badly from rest as from the edge estimate (1.374 against 1.378) and chose rest for every
    # model: the truth scored 0.357 there, and the offset fitted from rest ended worse than the null
    # model. Each fit now judges the start with its own model
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(191))
    run = to_run(rec)
    base = model_of({"c_m": 9.399100290606215, "k_m": 3794.7378726303514, "alpha_m": 0.0, "gamma": 0.0,
                     "delta": 0.0, "fn_m": {}})
    truth, _ = true_model(rec)
    data = rank.prepare(run, base)
    lin = next(d for d in data if d.name == "linear")
    assert lin.edge is not None and not any(lin.initial)        # the baseline chose rest
    fr = rank.fit(truth, [], data)
    assert fr.nrmse["linear"] < 0.01, fr.nrmse                  # the truth starts from the edge
    # and the cost the diagnosis compares starts with is the fit's own (the stage from the edge)
    assert rank.fit_cost(truth, data) == pytest.approx(fr.cost_fit, rel=1e-12)
    assert rank.fit_cost(truth, data) < 0.01 * float(np.sum(rank.fit_residual(truth, data) ** 2))
    dg = diagnose(run, baseline=base, candidates=["offset"])
    assert dg.candidates[0]["significant"], dg.candidates[0]
    assert dg.best.baseline.fn_m["y^0"] == pytest.approx(truth.baseline.fn_m["y^0"], rel=0.01)


# about 150 s on one core of the 2-core machine; past the 300 s default when the suite's two workers
# share it with other work (CI of 2026-11-29: a timeout, the diagnosis itself unchanged)
@pytest.mark.slow
@pytest.mark.timeout(900)
def test_friction_is_found_where_the_paper_baseline_misses_the_response():
    # stress #171 (friction on sweeps, 67.4 dB) against its paper baseline: reconstruct's library has
    # no friction term; it put the friction of the small stage, which moves in pre-sliding (below
    # v0), into c (762 against 7.6) and that of the large ones into opposite-signed y^3 and y^2 y'
    # terms (held-out NRMSE 0.985, the null model the same). No fit moved from there. Friction's
    # starts now include v0 above the small stage's velocity, where its equation step moves c and mu
    # together, and candidates also start from the baseline's linear core (fn terms at 0, c and k
    # refitted)
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(171))
    run = to_run(rec)
    base = model_of({"c_m": 762.4432212923356, "k_m": 39649.54264901493, "alpha_m": 0.0, "gamma": 0.0,
                     "delta": 0.0, "fn_m": {"y^3": -20711203813804.46, "y^2*dy": -135856550628.99509}})
    dg = diagnose(run, baseline=base, candidates=["coulomb_friction"])
    c = dg.candidates[0]
    assert dg.fit_before["held_out_nrmse"] > 0.9
    assert dg.fit_before["linear_core_held_out_nrmse"] > 0.9
    assert c["significant"], c
    truth, _ = true_model(rec)
    assert dg.best.get("mu") == pytest.approx(truth.get("mu"), rel=0.02)
    assert dg.best.get("v0") == pytest.approx(truth.get("v0"), rel=0.05)
    assert dg.best.baseline.c_m == pytest.approx(truth.baseline.c_m, rel=0.1)
    assert c["held_out_nrmse"] < 1.5 * rank.fit(truth, [], rank.prepare(run, base)).nrmse_held


@pytest.mark.slow
def test_two_effects_neither_enough_alone_are_named_together():
    # stress #99 (a contact on sweeps, 45.9 dB) against its paper baseline, which lacks the truth's
    # y^2 and holds y^4, y^5 instead: held-out 0.00905, the contact alone 0.0070, y^2 alone 0.0075,
    # neither significant before the rule's steady route (2026-11-28b), which passes the contact alone
    # (it helps on 9 of 10 held-out pieces, 22 % lower NRMSE); with that route asking 25 %, as when
    # neither passed alone, fitted together (the contact on top of the y^2 fit, each side of the stop
    # fitted) they reach the truth's figure (the pair over y^2 alone: 31 % lower, 9 of 10 pieces)
    settings = dataclasses.replace(DEFAULTS, rule=dataclasses.replace(DEFAULTS.rule, steady_rel_gain=0.25))
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(99))
    run = to_run(rec)
    base = model_of({"c_m": 11.7001577133738, "k_m": 40610.18688167713, "alpha_m": 60820.44292600348,
                     "gamma": 1554.9743494079798, "delta": 3035.3745078802367,
                     "fn_m": {"y^4": 94735987934030.47, "y^5": 1.5106721897868547e+17}})
    dg = diagnose(run, baseline=base, candidates=["contact_stiffness", "quadratic_stiffness"], settings=settings)
    assert [m["id"] for m in dg.missing] == ["contact_stiffness", "quadratic_stiffness"]
    by_id = {c["id"]: c for c in dg.candidates}
    assert not by_id["contact_stiffness"]["alone"]["significant"]
    assert not by_id["quadratic_stiffness"]["alone"]["significant"]
    assert by_id["contact_stiffness"]["jointly_with"] == "quadratic_stiffness"
    assert all(by_id[i]["significant"] and not by_id[i].get("implausible") for i in by_id)
    truth, _ = true_model(rec)
    assert dg.best.get("side") == truth.get("side")
    assert dg.best.get("gap") == pytest.approx(truth.get("gap"), rel=0.02)
    assert dg.best.get("kc") == pytest.approx(truth.get("kc"), rel=0.1)
    assert dg.best_fit.nrmse_held < 1.05 * rank.fit(truth, [], rank.prepare(run, base)).nrmse_held
    assert dg.best_fit.nrmse_held < dg.fit_before["held_out_nrmse"]


def test_a_pair_on_top_of_the_cheapest_fit_takes_only_members_plausible_alone():
    # the real bolted beam with its paper baseline (docs/diagnosis.md, 2026-11-27, sixth): a one-sided stop
    # whose stiffness interval held 0 when fitted alone was fitted on top of exciter_distortion and
    # named with it, a stop the beam does not have. Far above the floor, only the candidates
    # plausible alone are fitted on top of the one that lowers the fitting cost most
    from recon.diagnosis.candidate_fit import CandidateFit
    from recon.diagnosis.refits import joint_pair
    from recon.model import HystereticModel

    base = HystereticModel("base", c_m=2.0, k_m=1.0e4, alpha_m=0.0, gamma=0.0, delta=0.0)

    def fr(cost, held):
        return rank.FitResult(AugmentedModel(base), cost_fit=cost, mse_held=held ** 2, nrmse={},
                              nrmse_held=held, n_held=100)

    ref = fr(1.0, 0.20)
    tested = [{"id": "exciter_distortion", "compared_with_held_out_nrmse": 0.20},
              {"id": "coulomb_friction", "compared_with_held_out_nrmse": 0.20},
              {"id": "contact_stiffness", "compared_with_held_out_nrmse": 0.20,
               "implausible": ["the 95 % interval of kc [-19.68, 91.78] holds 0"]}]
    fits = {"exciter_distortion": CandidateFit(fr(0.5, 0.197), [], {}, {}, []),
            "coulomb_friction": CandidateFit(fr(0.9, 0.203), [], {}, {}, []),
            "contact_stiffness": CandidateFit(fr(0.8, 0.206), [], {}, {}, [])}
    tried = []

    def refit_on(cid, first):
        tried.append(cid)
        raise ValueError("not fitted in this test")

    assert joint_pair(tested, fits, [ref], ref.model, [], 1e-8, 5, refit_on, far_from_floor=True) == ([], None)
    assert tried == ["coulomb_friction"]


@pytest.mark.slow
def test_friction_found_with_every_parameter_where_c_and_k_alone_predict_a_little_better():
    # stress #353 (friction on the paper protocol, 57.6 dB) against its paper baseline: the refit is
    # 3 x worse on the held-out stage than the baseline as given (0.0219 against 0.0067); friction
    # fitted with c and k free took 93 % of the fitting cost and reached 0.00639, not significant.
    # Refitted from there with every parameter free it reaches the truth's figure (0.00232)
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(353))
    run = to_run(rec)
    base = model_of({"c_m": 17.273255616863473, "k_m": 41891.15087663554, "alpha_m": 38092.52445971657,
                     "gamma": 429.51037942841964, "delta": 645.9803612254512,
                     "fn_m": {"y^2": 5255463.249607476, "y^3": 1087655916.0302486}})
    dg = diagnose(run, baseline=base, candidates=["coulomb_friction"])
    c = dg.candidates[0]
    assert dg.fit_before["refit_held_out_nrmse"] > 2 * dg.fit_before["held_out_nrmse"]
    # found with every baseline parameter free: from the null model, or refitted from the fit with c
    # and k free (which of the two ends lower on the held-out samples is a matter of the fits' ends)
    assert c["significant"] and c["started_from"] in ("as_given_then_refit", "refit"), c
    truth, _ = true_model(rec)
    assert dg.best.get("mu") == pytest.approx(truth.get("mu"), rel=0.02)
    assert c["held_out_nrmse"] < 1.05 * rank.fit(truth, [], rank.prepare(run, base)).nrmse_held


@pytest.mark.slow
def test_a_sensor_error_on_the_rig_protocol_is_found_with_its_size_once_the_start_transient_is_left_out():
    # stress #7 (a 0.77 % tip-sensor error on the rig protocol, 65.6 dB) against its paper baseline.
    # Before the burn-in (rank.burn_in, 2026-12-01b) the refit was 5.6 x worse on the held-out samples
    # than the baseline as given: with c and k free the fits traded the nonlinear stage for the
    # resonance search's start transient, and the scale was found only fitted alone, at 0.3-1.5 x its
    # size. With that transient out of the fit the refit costs less than 2 x, and the scale is found
    # with c and k free, its size within 2 %
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(7))
    run = to_run(rec)
    base = model_of({"c_m": 0.6373475269908123, "k_m": 1158.8580677126845, "alpha_m": 335.2494452732517,
                     "gamma": 2572.864908547995, "delta": 943.490532152942, "fn_m": {"y^3": 214760618.80700168}})
    dg = diagnose(run, baseline=base, candidates=["sensor_scale"])
    c = dg.candidates[0]
    assert dg.fit_before["refit_held_out_nrmse"] < 2 * dg.fit_before["held_out_nrmse"]
    assert c["significant"], c
    assert c["held_out_nrmse"] < 0.2 * dg.fit_before["held_out_nrmse"]
    truth, _ = true_model(rec)
    assert dg.best.get("tip_scale") == pytest.approx(truth.get("tip_scale"), rel=0.02)


@pytest.mark.slow
def test_a_mode_above_the_input_band_is_found_from_a_start_above_it():
    # stress #213 (a 104.6 Hz second mode, sweeps that end at 42 Hz, 68.9 dB) against its paper baseline:
    # the mode answers the sweep quasi-statically, with no peak in the residual, and the scan's starts
    # (49-54 Hz, the hardening baseline's misfit) never reached it. A start twice above the input's band does
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(213))
    run = to_run(rec)
    base = model_of({"c_m": 4.7074261151607635, "k_m": 30005.0332240132, "alpha_m": 11774.945984970831,
                     "gamma": 2689.404564241297, "delta": -647.9868289578399,
                     "fn_m": {"y^3": 14313272292.393688, "dy^3": 101.8317642459877}})
    dg = diagnose(run, baseline=base, candidates=["higher_mode"])
    c = dg.candidates[0]
    top = dg.context["mode_start_above_band"] / 2.0
    assert 35.0 < top < 50.0, top      # the sweeps' band ends near 42 Hz
    assert all(f < 70.0 for f, _ in dg.context["mode_starts"][:3])
    assert c["significant"], c
    truth, _ = true_model(rec)
    assert dg.best.get("w2") == pytest.approx(truth.get("w2"), rel=0.03)
    assert dg.best.get("phi2") == pytest.approx(truth.get("phi2"), rel=0.1)
    assert c["held_out_nrmse"] < 0.25 * dg.fit_before["held_out_nrmse"]


@pytest.mark.slow
def test_friction_beside_a_stiffness_the_linear_baseline_lacks():
    # stress #80 (friction on sweeps, 72.6 dB): the reconstructed baseline is linear with c 223
    # (truth 8.0) and no y^3 (truth 4.87e9): friction alone ends at held-out 1.41 (k takes the
    # hardening), y^3 alone at 0.96, the reference 0.95. Far above the noise floor, every candidate
    # is also fitted on top of the one that lowers the fitting cost most (friction)
    from recon.testing.stress import draw, recording
    from recon.testing.runs import model_of, to_run, true_model

    rec = recording(draw(80))
    run = to_run(rec)
    base = model_of({"c_m": 222.80106048457654, "k_m": 26326.985798769903, "alpha_m": 0.0, "gamma": 0.0,
                     "delta": 0.0, "fn_m": {}})
    dg = diagnose(run, baseline=base, candidates=["coulomb_friction", "cubic_stiffness"])
    assert [m["id"] for m in dg.missing] == ["coulomb_friction", "cubic_stiffness"]
    assert dg.fit_before["held_out_nrmse"] > 0.9
    truth, _ = true_model(rec)
    assert dg.best.get("mu") == pytest.approx(truth.get("mu"), rel=0.01)
    assert dg.best.baseline.fn_m["y^3"] == pytest.approx(truth.baseline.fn_m["y^3"], rel=0.01)
    assert dg.best_fit.nrmse_held < 2.0 * rank.fit(truth, [], rank.prepare(run, base)).nrmse_held


def test_blocks_improved_counts_the_held_out_pieces_a_candidate_helps():
    r = np.random.default_rng(2).normal(0, 1, 4000)
    assert rank.blocks_improved(r, 0.5 * r) == 1.0
    # better on the first half, worse on the second: a fit of a passing error
    mixed = np.concatenate([0.5 * r[:2000], 2.0 * r[2000:]])
    assert rank.blocks_improved(r, mixed) == pytest.approx(0.5)
    assert rank.blocks_improved(r, r[:100]) is None
    assert rank.score(_fr(1.6, r), _fr(1.05, 0.8 * r), 1, 1.0)["blocks_improved"] == 1.0


def test_a_candidate_that_helps_throughout_the_held_out_record_needs_less_of_the_excess():
    # noise variance 1, reference MSE 1.4047, candidate 1.0625: 84.5 % of the excess, gain 0.34
    # noise variances (the figures of clean stress #365's higher mode)
    r = np.random.default_rng(3).normal(0, 1, 8000)
    r /= np.sqrt(np.mean(r ** 2))
    ref = _fr(1.4047, math.sqrt(1.4047) * r)
    steady = rank.score(ref, _fr(1.0625, math.sqrt(1.0625) * r), 1, 1.0)
    assert steady["explained"] < 0.9 and steady["blocks_improved"] == 1.0
    assert steady["significant"]
    # the same mean-square errors, but better on the first half of the held-out samples and worse on
    # the second (#365 itself: 5 of 10 pieces): not significant
    half = r.size // 2
    lo = np.sqrt(np.mean(r[:half] ** 2))
    hi = np.sqrt(np.mean(r[half:] ** 2))
    first = 0.6 * math.sqrt(1.4047) * r[:half] / lo
    second_ms = 2 * 1.0625 - np.mean(first ** 2)
    mixed = np.concatenate([first, math.sqrt(second_ms) * r[half:] / hi])
    assert np.mean(mixed ** 2) == pytest.approx(1.0625)
    split = rank.score(ref, _fr(1.0625, mixed), 1, 1.0)
    assert split["blocks_improved"] == pytest.approx(0.5)
    assert not split["significant"]
    # and a steady candidate that stays above the floor tiers needs STEADY_GAIN and
    # STEADY_REL_GAIN: clean #105's sensor scale (10 of 10 pieces, 2.1 % and 0.05 noise variances) fails
    small = rank.score(ref, _fr(1.345, math.sqrt(1.345) * r), 1, 1.0)
    assert small["blocks_improved"] == 1.0 and small["relative_gain"] < DEFAULTS.rule.steady_rel_gain
    assert not small["significant"]


def test_a_small_term_that_helps_throughout_the_held_out_record_is_named():
    # the figures of stress #120 (quadratic damping at 0.93 of the scale on the paper's protocol):
    # reference 1.22 noise variances, candidate 1.11: 50 % of the excess, gain 0.11, 4.6 % lower NRMSE
    r = np.random.default_rng(5).normal(0, 1, 8000)
    r /= np.sqrt(np.mean(r ** 2))
    ref = _fr(1.22, math.sqrt(1.22) * r)
    steady = rank.score(ref, _fr(1.11, math.sqrt(1.11) * r), 1, 1.0)
    assert steady["relative_gain"] < DEFAULTS.rule.min_rel_gain and steady["gain_over_noise"] < 0.25
    assert steady["relative_gain"] >= DEFAULTS.rule.steady_rel_gain and steady["blocks_improved"] == 1.0
    assert steady["significant"]
    # the same mean squares, better on the first half and worse on the second (clean #326's
    # friction: 6.6 %, 0.18 noise variances, 5 of 10 pieces): not significant
    half = r.size // 2
    first = 0.8 * math.sqrt(1.22) * r[:half] / np.sqrt(np.mean(r[:half] ** 2))
    second = math.sqrt(2 * 1.11 - np.mean(first ** 2)) * r[half:] / np.sqrt(np.mean(r[half:] ** 2))
    split = rank.score(ref, _fr(1.11, np.concatenate([first, second])), 1, 1.0)
    assert split["blocks_improved"] == pytest.approx(0.5) and not split["significant"]
    # nor is a steady one under STEADY_GAIN noise variances (a reference at 1.061 noise variances,
    # the candidate at 0.965: a gain of 0.096)
    faint = rank.score(_fr(12.2, math.sqrt(12.2) * r), _fr(11.1, math.sqrt(11.1) * r), 1, 11.5)
    assert faint["blocks_improved"] == 1.0 and faint["relative_gain"] >= DEFAULTS.rule.steady_rel_gain
    assert faint["explained"] >= DEFAULTS.rule.min_explained and faint["dbic"] < -DEFAULTS.rule.bic_margin
    assert faint["gain_over_noise"] < DEFAULTS.rule.steady_gain and not faint["significant"]


def test_a_term_that_brings_the_model_near_the_floor_on_every_piece_is_named():
    # the figures of stress #1095 (quadratic damping at 1.45 of the scale, rig protocol, 54 dB, a
    # y^2 + y^3 specimen): reference 1.085 noise variances, candidate 1.015: 83 % of the excess, a
    # gain of 0.07 noise variances, a 3.3 % lower held-out NRMSE, better on 10 of 10 pieces
    r = np.random.default_rng(7).normal(0, 1, 8000)
    r /= np.sqrt(np.mean(r ** 2))
    ref = _fr(1.085, math.sqrt(1.085) * r)
    near = rank.score(ref, _fr(1.015, math.sqrt(1.015) * r), 1, 1.0)
    assert near["relative_gain"] < DEFAULTS.rule.steady_rel_gain and near["gain_over_noise"] < DEFAULTS.rule.steady_gain
    assert near["explained"] >= DEFAULTS.rule.complete_explained and near["blocks_improved"] == 1.0
    assert near["significant"]
    # the same figures on 9 of 10 pieces: the steady route's pieces, but not every one: not named
    nine = math.sqrt(1.015) * r.copy()
    k = r.size // 10
    nine[-k:] *= math.sqrt(1.2)
    nine *= math.sqrt(1.015 / np.mean(nine ** 2))
    split = rank.score(ref, _fr(1.015, nine), 1, 1.0)
    assert split["blocks_improved"] == pytest.approx(0.9) and not split["significant"]
    # clean #1041's channel delay (rig, 41 dB): 82 % of an excess of 0.032 noise variances, 1.25 %,
    # every piece better: under COMPLETE_REL_GAIN and COMPLETE_GAIN, not named
    clean = rank.score(_fr(1.032, math.sqrt(1.032) * r), _fr(1.006, math.sqrt(1.006) * r), 1, 1.0)
    assert clean["explained"] >= DEFAULTS.rule.complete_explained and clean["blocks_improved"] == 1.0
    assert clean["relative_gain"] < DEFAULTS.rule.complete_rel_gain and not clean["significant"]
    # a candidate below the noise floor (the floor overestimated; clean #781's delay explained 1.67
    # of its excess) has no near-floor route: the steady route's figures decide
    below = rank.score(_fr(1.05, math.sqrt(1.05) * r), _fr(0.99, math.sqrt(0.99) * r), 1, 1.0)
    assert below["explained"] > 1.0 and below["relative_gain"] < DEFAULTS.rule.steady_rel_gain
    assert not below["significant"]


def test_a_term_that_helps_on_every_piece_with_part_of_the_excess_is_named():
    # the unanimous route's share (COMPLETE_EXPLAINED 0.4): stress #1097 (a higher mode on the rig
    # protocol, 40 dB): reference 1.173 noise variances, candidate 1.0986: 43 % of the excess, a gain
    # of 0.074 noise variances, 3.2 % lower, better on every piece
    r = np.random.default_rng(11).normal(0, 1, 8000)
    r /= np.sqrt(np.mean(r ** 2))
    ref = _fr(1.173, math.sqrt(1.173) * r)
    part = rank.score(ref, _fr(1.0986, math.sqrt(1.0986) * r), 1, 1.0)
    assert part["blocks_improved"] == 1.0 and 0.4 <= part["explained"] < 0.8
    assert part["gain_over_noise"] < DEFAULTS.rule.steady_gain and part["relative_gain"] < DEFAULTS.rule.steady_rel_gain
    assert part["significant"]
    # clean #105's sensor scale (paper, 63 dB): 22 % of the excess, 2.1 %, every piece: not named
    clean = rank.score(_fr(1.236, math.sqrt(1.236) * r), _fr(1.184, math.sqrt(1.184) * r), 1, 1.0)
    assert clean["blocks_improved"] == 1.0 and clean["relative_gain"] >= DEFAULTS.rule.complete_rel_gain
    assert clean["explained"] < DEFAULTS.rule.complete_explained and not clean["significant"]


@pytest.mark.slow
def test_a_fitting_stage_in_motion_may_start_with_the_law_at_rest():
    # stress #542 (sweeps): a constant force beside a Bouc-Wen law; the linear stage starts at the
    # force's static deflection with z = 0. prepare() takes the edge's z0 from the force balance of
    # a baseline without the force, which puts the force into z0 (-0.43): from there the true model
    # scored 0.48 on that stage, and the offset candidate's fit traded the offset against it
    from recon.testing.stress import draw, recording
    from recon.testing.runs import to_run, true_model
    from recon.diagnosis.references import without_terms

    rec = recording(draw(542))
    truth, _ = true_model(rec)
    assert "y^0" in truth.baseline.fn_m and truth.baseline.alpha_m > 0
    data = rank.prepare(to_run(rec), without_terms(truth, ("y^0",)).baseline)
    d = next(x for x in data if x.name == "linear")
    assert d.fit.any() and d.edge is not None and abs(d.initial[2]) > 0.1

    def nrmse(x):
        ys = truth.simulate(x.t, x.u, x.x_in, rank.initial_for(truth, x))[0]
        return float(np.sqrt(np.mean((ys[x.fit] - x.y[x.fit]) ** 2)) / x.rms)

    own = next(x for x in rank.own_starts(truth, data) if x.name == "linear")
    assert own.initial[2] == 0.0 and own.initial[:2] == pytest.approx(d.edge[:2])
    assert nrmse(own) < 0.1 < 0.3 < nrmse(d)


@pytest.mark.slow
def test_starts_that_differ_in_the_contact_gap_are_ranked_by_where_a_short_fit_leads():
    # stress #658 (the paper's protocol): a weak one-sided contact (kc 7 % of k) at a gap of 0.65 mm,
    # against the paper baseline reconstructed from it (a y^5 term and a spurious Bouc-Wen law stand in
    # for the contact). Of the stepped starts at 0.52, 0.81 and 1.11 mm, the one at 1.11 mm simulated
    # best as stepped; fitted from there the gap stayed at 1.15 mm and nothing was named (held-out
    # 0.0042 against 0.0032). A short fit of kc and the gap from each start ranks them by where they lead
    import json

    from recon.testing.stress import draw, recording
    from recon.testing.runs import to_run
    from recon.model import HystereticModel

    rec = recording(draw(658))
    base = HystereticModel.from_dict(json.loads((Path(__file__).parent / "data" / "stress658_paper_baseline.json").read_text()))
    assert "y^5" in base.fn_m
    dg = diagnose(to_run(rec), baseline=base, candidates=["contact_stiffness"])
    c = dg.candidates[0]
    assert c["significant"] and c["held_out_nrmse"] < 0.5 * c["compared_with_held_out_nrmse"], c
    truth = rec["effect_parameters"]
    assert dg.best.get("gap") == pytest.approx(truth["gap"], rel=0.02)
    assert dg.best.get("kc") == pytest.approx(truth["kc"] / rec["system"]["m"], rel=0.05)


def test_a_fitting_stage_recorded_in_motion_leaves_its_start_transient_out_of_the_fit():
    # stress #641 (the rig protocol, a 0.31 ms channel delay): the resonance search starts in the
    # linear stage's ringing with a Bouc-Wen state no fit's start knows. The truth, started as the
    # fits start it, erred most in that stage's first seconds, and that transient held most of its
    # fitting cost (29.25); without the first 3 decay times of the mode the cost is the model's
    from recon.testing.stress import draw, recording
    from recon.testing.runs import to_run, true_model

    rec = recording(draw(641))
    run = to_run(rec)
    truth, _ = true_model(rec)
    assert DEFAULTS.burn_in_decays == 3.0                        # on by default (docs/diagnosis.md)
    data = rank.prepare(run, truth.baseline)
    cut = DEFAULTS.burn_in_decays / (truth.baseline.c_m / 2.0)
    whole = rank.prepare(run, truth.baseline, dataclasses.replace(DEFAULTS, burn_in_decays=0.0))
    search = next(d for d in data if d.name == "resonance_search")
    search0 = next(d for d in whole if d.name == "resonance_search")
    assert search.edge is not None
    left_out = search0.fit & ~search.fit
    assert left_out.any() and np.all(search.t[left_out] < search.t[0] + cut + search.dt)
    assert search.fit.sum() > DEFAULTS.burn_in_keep * search0.fit.sum()
    for d, d0 in zip(data, whole):          # stages recorded from rest, and held-out samples, as they were
        assert np.array_equal(d.held, d0.held)
        if d.edge is None:
            assert np.array_equal(d.fit, d0.fit)
    # a model without hysteresis knows the whole state at the edge (y, y'): nothing is left out
    linear = dataclasses.replace(truth.baseline, alpha_m=0.0, gamma=0.0, delta=0.0)
    assert np.array_equal(rank.burn_in(search.t, search0.fit, truth.baseline, decays=3.0), search.fit)
    assert np.array_equal(rank.burn_in(search.t, search0.fit, linear, decays=3.0, hysteresis_only=False),
                          search.fit)
    assert np.array_equal(rank.burn_in(search.t, search0.fit, linear, decays=3.0), search0.fit)
    with_cut, without = rank.fit(truth, [], data), rank.fit(truth, [], whole)
    assert with_cut.cost_fit < 0.1 * without.cost_fit, (with_cut.cost_fit, without.cost_fit)
    assert with_cut.nrmse_held == pytest.approx(without.nrmse_held, rel=1e-9)   # the truth's own start


def test_a_fit_whose_jacobian_overflows_gets_no_standard_errors_and_does_not_hang():
    # a candidate fit on a 6 kHz multisine record ended where its last Jacobian's J^T J overflowed:
    # LAPACK's SVD of that matrix ran for minutes (a diagnosis of 25 s took over 10 minutes), and
    # on this one it gives standard errors of 0 (intervals of no width). No covariance exists
    # there: the fit gets no standard errors, at once
    class Solution:
        jac = np.array([[1e200, 1.0], [3.0, 2e190], [1.0, 1.0]])
        fun = np.zeros(3)
    assert rank._standard_errors(Solution(), ["a", "b"], np.ones(2), 1.0, None, np.zeros(2), np.ones(2)) == {}
    Solution.jac = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    se = rank._standard_errors(Solution(), ["a", "b"], np.ones(2), 1.0, None, np.zeros(2), np.ones(2))
    assert set(se) == {"a", "b"} and all(v > 0 for v in se.values())


def test_each_stage_is_integrated_finely_enough_that_the_simulator_s_error_cannot_pass_the_rule():
    # a simulator error of mean square below the least gain the rule counts cannot make a
    # candidate significant; the stage's step is halved until the change it makes is below that
    share = math.sqrt(DEFAULTS.rule.smallest_gain())
    assert share == pytest.approx(0.2)
    run, truth, _, _ = concealed_run(None, seed=5, duration=3.0, snr_db=80.0)
    data = rank.prepare(run, truth)
    am = AugmentedModel(truth)

    def change(d, f):
        a = rank.stage_output(am, dataclasses.replace(d, step_factor=f))
        b = rank.stage_output(am, dataclasses.replace(d, step_factor=2 * f))
        return float(np.sqrt(np.mean((a - b) ** 2))) / d.noise

    for d in data:
        assert change(d, d.step_factor) <= share, d.name
        if d.step_factor > 1:
            assert change(d, d.step_factor // 2) > share, d.name
    assert max(d.step_factor for d in data) > 1      # this record's default step is too coarse
    # every simulation of the stage (the fits' thinned samples too) keeps its factor
    assert all(d.thinned().step_factor == d.step_factor for d in data)

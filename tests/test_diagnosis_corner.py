"""Issue 76's corner, on recordings of the independent generator (recon.testing.stress.corner_draw):
a Bouc-Wen law with negative delta beside a hardening cubic and y^2 y' damping, f_n near 24 Hz,
5 kHz, sub-micron sensor noise, the paper's one-tone stages with the validation stage above the
resonance, a second mode above 3 f_n. One test per miss class of the issue's table; each is a
full diagnosis of a 5 kHz record (slow tier)."""
import warnings

import pytest

from recon.diagnosis.candidates.higher_mode import ZETA2_RANGE
from recon.diagnosis.diagnose import diagnose
from recon.testing.runs import to_run, true_model
from recon.testing.stress import corner_draw, corner_recording


def _diagnose(i: int, candidates=None) -> dict:
    warnings.filterwarnings("ignore")
    d = corner_draw(i)
    return diagnose(to_run(corner_recording(d)), candidates=candidates).to_dict()


@pytest.mark.slow
def test_corner_clean_names_nothing():
    """The issue's clean row named coulomb_friction with a fit worse than the baseline's."""
    out = _diagnose(1)
    assert out["missing_physics"] == [], out["result"]


@pytest.mark.slow
def test_corner_friction_is_named_friction():
    """The issue's friction row named channel_delay (better on validation, worse on the nonlinear stage)."""
    out = _diagnose(2)
    assert [m["id"] for m in out["missing_physics"]][:1] == ["coulomb_friction"], out["result"]


@pytest.mark.slow
def test_corner_friction_held_by_the_baselines_damping_is_fitted_to_its_size():
    """A corner draw whose baseline holds the friction as viscous damping (c 2.5 times the true). The
    friction's fit from the equation step had to trade c for mu along a ridge: its trust region
    gained a hundred-thousandth of a unit per step and the fit stopped where it started (held-out
    worse than the baseline). The stop now asks the fit's local model, which still promised far more:
    the fit goes on to the true friction and damping."""
    rec = corner_recording(corner_draw(47))
    out = diagnose(to_run(rec), candidates=["coulomb_friction"]).to_dict()
    fr = next(c for c in out["candidates_tested"] if c["id"] == "coulomb_friction")
    assert fr["significant"] and fr["explained"] > 0.9, fr
    named = out["missing_physics"][0]
    assert named["id"] == "coulomb_friction"
    true_mu = true_model(rec)[0].get("mu")
    assert abs(named["parameters"]["mu"]["value"] / true_mu - 1) < 0.05, (named["parameters"], true_mu)


@pytest.mark.slow
def test_corner_second_mode_is_named_and_a_scale_that_is_worse_on_a_stage_is_not():
    """The issue's second-mode row named sensor_scale: validation better, the nonlinear stage 18 x worse.
    With the whole catalog the mode is named; with the sensor scale alone it is never named where it
    predicts a held-out stage worse than the baseline as given beyond that stage's noise band."""
    out = _diagnose(4)
    assert [m["id"] for m in out["missing_physics"]][:1] == ["higher_mode"], out["result"]
    alone = _diagnose(4, candidates=["sensor_scale"])
    scale = next(c for c in alone["candidates_tested"] if c["id"] == "sensor_scale")
    for stage, f in (scale.get("held_out_stages") or {}).items():
        if f["worse"]:
            assert alone["missing_physics"] == [] and alone["result"].startswith("partly explained")


@pytest.mark.slow
def test_corner_quadratic_damping_gets_no_false_name():
    """The issue's quadratic-damping row named nothing. On this record the truth itself does not pass the
    rule (the reconstructed baseline's c and y^2 y' take the effect up on one-tone stages, and the validation
    stage above the resonance hardly shows damping): nothing else may be named in its place."""
    out = _diagnose(3)
    assert [m["id"] for m in out["missing_physics"]] in ([], ["quadratic_damping"]), out["result"]


@pytest.mark.slow
def test_corner_friction_over_a_baseline_with_wrong_terms_is_named_with_the_terms_chosen_again():
    """A corner draw whose reconstructed baseline holds y y'^2, y'^3 and y^5 where the truth has y^3
    and y^2 y': friction fitted beside those terms halved the held-out error but left the nonlinear
    stage worse than the baseline ("partly explained"). With the baseline's terms chosen again under
    the friction (recon.diagnosis.term_revision), the true terms come back and friction is named at
    its size."""
    rec = corner_recording(corner_draw(20))
    out = diagnose(to_run(rec), candidates=["coulomb_friction"]).to_dict()
    named = out["missing_physics"]
    assert [m["id"] for m in named] == ["coulomb_friction"], out["result"]
    revised = named[0]["baseline_terms_revised"]
    assert set(revised["terms_after"]) == {"y^3", "y^2*dy"}, revised
    # the size as fitted beside the terms as reconstructed is kept (the closed loop judges whether the
    # size hangs on the terms); here it differs from the revised one
    before = revised["parameters_before"]["mu"]["value"]
    assert before != named[0]["parameters"]["mu"]["value"] and before > 0, revised
    true_mu = true_model(rec)[0].get("mu")
    assert abs(named[0]["parameters"]["mu"]["value"] / true_mu - 1) < 0.05, (named[0]["parameters"], true_mu)


@pytest.mark.slow
def test_corner_second_mode_is_found_once_the_thinned_input_no_longer_folds_noise_into_the_band():
    """A corner draw (5 kHz, fitted at 2.5 kHz) whose second mode the mode's fit never found: taking
    every other sample of the linear stage's input (a short Savitzky-Golay window, a quarter of it
    noise) folded noise into the response band, and the thinned simulation of every model, the true
    one included, sat 2 noise stds from its full-rate one on that stage. The fit then traded the
    mode for that error (explained -0.002). With the input low-passed before it is thinned
    (recon.simulation.resampling.thinned_input) the mode is named: explained 0.82, w2 within 2 %
    (measured)."""
    rec = corner_recording(corner_draw(31))
    out = diagnose(to_run(rec), candidates=["higher_mode"]).to_dict()
    assert [m["id"] for m in out["missing_physics"]] == ["higher_mode"], out["candidates_tested"]
    assert out["candidates_tested"][0]["explained"] > 0.5
    w2 = out["missing_physics"][0]["parameters"]["w2"]["value"]
    assert abs(w2 / true_model(rec)[0].get("w2") - 1) < 0.05


@pytest.mark.slow
def test_each_candidate_that_explains_enough_gets_its_revision_of_the_baseline_terms():
    """A corner quadratic damping (c2 1.16) that the baseline's spurious y'^3 partly takes up: alone
    it explains 18 % of the held-out excess, a tip scale 23 %, neither passes. Only the candidate that
    explained most used to have the baseline's terms chosen again under it (the scale, which gains
    nothing by it), so the damping was never named. Each candidate over the rule's share now gets
    its revision in turn, and the damping passes under its own (32 %)."""
    out = _diagnose(264, candidates=["quadratic_damping", "sensor_scale"])
    assert [m["id"] for m in out["missing_physics"]] == ["quadratic_damping"], out["result"]
    qd = out["missing_physics"][0]
    assert qd.get("baseline_terms_revised"), qd


@pytest.mark.slow
def test_corner_friction_whose_equation_step_lands_in_its_basin_is_fitted_from_there():
    """A corner friction (mu 0.0135, v0 5.3e-5) named channel_delay. The equation step of each
    smoothing-velocity start put mu near 0.01, and the step at the v0 nearest the truth had the
    lowest output error of the steps; but a start whose term alone was given a short output-error
    fit (the sharpest v0, mu to 0.0014) ended lower still, and the full fit from there stayed in
    that shallow basin. Each step now gets the same short fit before the two are compared (a step
    is judged by where it leads, as a start is), and friction is named near its size."""
    rec = corner_recording(corner_draw(470))
    out = diagnose(to_run(rec), candidates=["coulomb_friction", "channel_delay"]).to_dict()
    named = out["missing_physics"]
    assert [m["id"] for m in named][:1] == ["coulomb_friction"], out["result"]
    true_mu = true_model(rec)[0].get("mu")
    assert abs(named[0]["parameters"]["mu"]["value"] / true_mu - 1) < 0.1, (named[0]["parameters"], true_mu)


@pytest.mark.slow
def test_corner_second_mode_whose_damping_the_stages_leave_free_is_named():
    """One-tone stages drive a second mode (truth 105.6 Hz, zeta 0.021) off its resonance, where its
    response hardly depends on its damping: the candidate's fit beside the baseline's terms as
    reconstructed finds the frequency and the size, and its damping ends on the bottom of its range.
    Such a fit was refused as an undamped line; it is now judged on the held-out samples like every
    candidate, named, and with the baseline's terms chosen again under it the damping is fitted
    inside its range, its interval holding the truth."""
    rec = corner_recording(corner_draw(571))
    out = diagnose(to_run(rec)).to_dict()
    assert [m["id"] for m in out["missing_physics"]][:1] == ["higher_mode"], out["result"]
    named = out["missing_physics"][0]
    p = named["parameters"]
    truth = true_model(rec)[0]
    assert abs(p["w2"]["value"] / truth.get("w2") - 1) < 0.05, (p, truth.extras)
    assert abs(p["phi2"]["value"] / truth.get("phi2") - 1) < 0.15, (p, truth.extras)
    before = named["baseline_terms_revised"]["parameters_before"]["zeta2"]
    assert before["value"] <= 1.01 * ZETA2_RANGE[0], before
    lo, hi = p["zeta2"]["interval"]
    assert lo <= truth.get("zeta2") <= hi and "at_bound" not in p["zeta2"], (p["zeta2"], truth.extras)


@pytest.mark.slow
def test_corner_delay_that_explains_more_than_a_named_stand_in_gets_its_revision_first():
    """A channel delay whose candidate explains more of the mismatch than a second mode standing in
    for it, but fails the nonlinear held-out stage beside the baseline's terms as reconstructed,
    while the mode passes: the delay gets the revision of the baseline's terms it would get if
    nothing were named, and with its terms chosen again it is named first."""
    out = _diagnose(582)
    assert [m["id"] for m in out["missing_physics"]][:1] == ["channel_delay"], out["result"]
    assert "baseline_terms_revised" in out["missing_physics"][0], out["missing_physics"][0].keys()


@pytest.mark.slow
def test_corner_second_mode_seen_by_its_tail_is_named_with_its_tail_and_its_unfixed_damping_marked():
    """One-tone stages far below a second mode (truth 84.9 Hz, zeta 0.029, phi2 0.33) show only its
    tail: its share of the static response phi2 / w2^2 and a phase. The fit slides along the valley
    of equal tails to the top of its damping range, far above the true frequency. Such a mode was
    refused as having no resonance; it is a separate resonance whose half-power band stays clear of
    the fundamental's, so it is named, with its damping marked as not fixed by the record, and the
    tail it reports is the truth's."""
    rec = corner_recording(corner_draw(238))
    out = diagnose(to_run(rec)).to_dict()
    assert [m["id"] for m in out["missing_physics"]][:1] == ["higher_mode"], out["result"]
    p = out["missing_physics"][0]["parameters"]
    assert p["zeta2"].get("at_bound") == "upper", p["zeta2"]
    from recon.diagnosis.wording import diagnosis_text
    assert "zeta2 0.3 on the upper end of its fitted range" in diagnosis_text(out), diagnosis_text(out)
    truth = true_model(rec)[0]
    tail, true_tail = p["phi2"]["value"] / p["w2"]["value"] ** 2, truth.get("phi2") / truth.get("w2") ** 2
    assert abs(tail / true_tail - 1) < 0.1, (p, truth.extras)

"""Issue 13: honest before/after, a noise floor that averaged records cannot fool, physically
plausible effects with intervals.

- fit_before holds the baseline as given; a candidate is reported only when it beats the better
  of the baseline as given and the null model (the refit) on the held-out samples;
- the noise floor is the largest of the spectral floor, a difference-based floor and the sensor's
  resolution, and a candidate must cut the held-out NRMSE by a fraction of the reference's;
- implausible fits (negative delay, a gap outside the recorded range, an interval holding 0) are
  never reported, and every reported parameter has a 95 % interval.
"""
import math

import numpy as np
import pytest

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.diagnose import diagnose, implausible
from recon.testing.concealed import concealed_run


# ----------------------------------------------------------------- before / after
@pytest.mark.parametrize("effect,seed,name,true", [("coulomb_friction", 0, "mu", 0.02),
                                                   ("sensor_scale", 4, "tip_scale", 0.02)])
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
    as_given = rank.nrmse_per_stage(am, data)
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


def test_nothing_found_reports_the_better_of_as_given_and_refit():
    run, _, _, baseline = concealed_run(None, seed=11, duration=2.0)
    out = diagnose(run, baseline).to_dict()
    fb = out["fit_before"]
    assert out["missing_physics"] == []
    assert out["fit_after"]["held_out_nrmse"] == pytest.approx(min(fb["held_out_nrmse"], fb["refit_held_out_nrmse"]))


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


def _fr(mse, resid=None):
    r = resid if resid is not None else np.random.default_rng(0).normal(0, math.sqrt(mse), 4000)
    return rank.FitResult(model=None, cost_fit=0.0, mse_held=mse, nrmse={}, nrmse_held=math.sqrt(mse), n_held=r.size,
                          resid_held=r)


def test_a_tiny_noise_floor_does_not_make_a_small_gain_significant():
    # averaged record: noise variance 1e-10 of the reference's MSE. A 3 % cut of the held-out NRMSE passes
    # the BIC and gain-over-noise tests trivially (gain over noise ~ 6e8) but is not a meaningful fraction
    ref = _fr(1.0)
    small = rank.score(ref, _fr(0.97 ** 2), 1, 1e-10)
    assert small["gain_over_noise"] > 1e8 and small["dbic"] < -rank.BIC_MARGIN
    assert small["relative_gain"] == pytest.approx(0.03)
    assert not small["significant"]
    big = rank.score(ref, _fr(0.5 ** 2), 1, 1e-10)
    assert big["significant"]


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

"""The diagnosis on the paper's own protocol: one harmonic per stage (a small linear stage near half
the resonance, a large stage just below it, a validation stage at another frequency and amplitude,
each with its amplitude ramps), recorded by the independent generator (recon/testing/independent.py,
scipy solve_ivp on its own equations, no code shared with the estimator), 2 kHz, 60 dB.

The baseline is the generator's own truth without the concealed effect (the physical effects sit
outside the paper's model; for the structural ones the generator states the model without the term),
so each test asks one thing: does the diagnosis name the right id from one tone per stage, and does
the named model predict the held-out stage better than both the baseline as given and the refit.
One test per catalog id (every effect the generator makes: the eight physical ones, the three
structural ones and amplitude-dependent damping), and a clean recording that reports nothing."""
from __future__ import annotations

import numpy as np
import pytest

from recon.diagnosis.diagnose import diagnose
from recon.diagnosis.settings import DEFAULTS
from recon.testing import independent as ind
from recon.testing.runs import model_of, to_run

# one TMP-like system for every effect: f_n drawn in 8-20 Hz, hysteresis, y^2 and y^3
SYSTEM = ind.random_system(np.random.default_rng(2026), hysteresis=True, quadratic=True, cubic=True,
                           fn_range=(8.0, 20.0))


def _recording(effect: str, seed: int):
    rec = ind.simulate(SYSTEM, "paper", 2000.0, effect, 1.0, seed=seed)
    rec = ind.add_noise(rec, 60.0, seed)
    baseline = model_of(rec["baseline"] if "baseline" in rec else rec["truth"])
    return to_run(rec), baseline, rec


@pytest.mark.slow
def test_a_clean_harmonic_recording_reports_nothing():
    run, baseline, _ = _recording("none", 0)
    out = diagnose(run, baseline).to_dict()
    assert out["missing_physics"] == [], out["candidates_tested"]
    assert out["result"].startswith("nothing found")
    assert not out.get("ambiguous")


# seed 1 for every effect. The contact's gap sits at the clean nonlinear stage's peak: the validation
# tone reaches only 34 % of it, so the diagnosis holds out the nonlinear stage's end too
# (rank.uncovered_stages), where the stop is reached (checked below). Before that (to 2026-11-27)
# this test took seed 4, whose validation tone reaches 135 %; seed 1 named nothing.
@pytest.mark.slow
@pytest.mark.parametrize("effect", [e for e in ind.EFFECTS if e != "none"])
def test_each_effect_is_named_from_one_tone_per_stage(effect):
    run, baseline, rec = _recording(effect, 1)
    if effect == "contact_stiffness":
        from recon.diagnosis import rank
        e = rec["effect_parameters"]

        def reach(name, start=0.0):
            st = rec["stages"][name]
            y = e["side"] * (np.asarray(st["x_tip"]) - np.asarray(st["x_base"]))
            return float(np.max(y[int(start * y.size):])) / e["gap"]
        assert reach("validation") < 0.5 and rank.uncovered_stages(run) == {"nonlinear"}
        assert reach("nonlinear", 1 - DEFAULTS.hold_fraction) > 1.0
    out = diagnose(run, baseline).to_dict()
    ids = [m["id"] for m in out["missing_physics"]]
    amb = out.get("ambiguous") or []
    # right first, or reported as one of an ambiguous pair (with the stage that would separate them)
    assert (effect in amb) if amb else (ids[:1] == [effect]), (ids, amb, out["candidates_tested"])
    fb, fa = out["fit_before"], out["fit_after"]
    if effect == "contact_stiffness":
        assert fb["held_out_share"]["validation"] == 1.0
        assert fb["held_out_share"]["nonlinear"] == pytest.approx(DEFAULTS.hold_fraction, abs=1e-3)
    assert fa["held_out_nrmse"] < fb["held_out_nrmse_as_given"]
    assert fa["held_out_nrmse"] < fb["refit_held_out_nrmse"]


@pytest.mark.slow
def test_a_resonance_riding_on_the_tip_is_named_with_its_drive():
    # the second mode driven by the tip's absolute acceleration (a sensor-mount resonance; the foreign
    # set's c05), not by the base: the input-driven scan and starts did not find it, and with each
    # stage weighed by its rms the fit left the true mode for one that fitted the small linear
    # stage's noise
    rec = ind.simulate(SYSTEM, "paper", 2000.0, "higher_mode", 1.0, seed=1, mode_drive=1.0)
    rec = ind.add_noise(rec, 60.0, 1)
    out = diagnose(to_run(rec), model_of(rec["truth"])).to_dict()
    ids = [m["id"] for m in out["missing_physics"]]
    assert ids[:1] == ["higher_mode"], (ids, out["candidates_tested"])
    e = rec["effect_parameters"]
    assert out["augmented_model"]["extras"].get("drive2") == 1.0
    assert out["missing_physics"][0]["parameters"]["w2"]["value"] == pytest.approx(e["w2"], rel=0.01)
    assert out["fit_after"]["held_out_nrmse"] < 0.5 * out["fit_before"]["held_out_nrmse_as_given"]


@pytest.mark.slow
def test_a_tip_resonance_far_above_the_fundamental_is_not_fitted_beside_it():
    # stress #460 (paper protocol, 6355 Hz, 57 dB): a mode riding on the tip at 63.5 Hz, 3.3 times the
    # 19.1 Hz fundamental, against the paper baseline reconstructed from the record. The input-driven
    # starts won the screening and their fit settled beside the fundamental (20.25 Hz, refused), so
    # the point-driven start was never fitted and the sensor scale was named. Each drive is now
    # fitted, a plausible fit kept before a cheaper refused one, and the mode's frequency is kept on
    # its start's side of the refused band
    from recon.testing.stress import draw, recording
    rec = recording(draw(460))
    out = diagnose(to_run(rec), "paper", candidates=["higher_mode"]).to_dict()
    assert [m["id"] for m in out["missing_physics"]] == ["higher_mode"], out["candidates_tested"]
    e = rec["effect_parameters"]
    assert out["augmented_model"]["extras"].get("drive2") == 1.0
    assert out["missing_physics"][0]["parameters"]["w2"]["value"] == pytest.approx(e["w2"], rel=0.01)
    assert out["missing_physics"][0]["parameters"]["zeta2"]["value"] == pytest.approx(e["zeta2"], rel=0.1)


@pytest.mark.slow
def test_quadratic_damping_a_baseline_took_up_as_a_hysteresis_loop_is_named_without_it():
    # stress #16: reconstructed from a record with quadratic damping and no hysteresis, the paper
    # baseline had a Bouc-Wen law (alpha 880, gamma 25.7) that dissipated in its place, and from there
    # c2 stayed at 0. Here the baseline is the truth without the effect, 40 % of its stiffness moved
    # into a made-up loop: the named model must have dropped the loop and found c2
    system = ind.random_system(np.random.default_rng(16), hysteresis=False, quadratic=False, cubic=True,
                               fn_range=(8.0, 20.0))
    rec = ind.add_noise(ind.simulate(system, "paper", 2000.0, "quadratic_damping", 1.0, seed=1), 60.0, 1)
    p = dict(rec["baseline"] if "baseline" in rec else rec["truth"])
    a = 0.4 * p["k_m"]
    p.update(k_m=p["k_m"] - a, alpha_m=a, gamma=0.5 / system["Y"], delta=0.0)
    out = diagnose(to_run(rec), model_of(p), candidates=["quadratic_damping", "coulomb_friction",
                                                        "cubic_stiffness"]).to_dict()
    ids = [m["id"] for m in out["missing_physics"]]
    assert ids[:1] == ["quadratic_damping"], (ids, out["candidates_tested"])
    named = out["missing_physics"][0]
    assert named["hysteresis_dropped"] is True
    assert out["augmented_model"]["baseline"]["parameters"]["alpha_m"] == 0.0
    lo, hi = named["parameters"]["c2"]["interval"]
    c2 = rec["effect_parameters"]["c2"] / system["m"]
    assert lo <= c2 <= hi or named["parameters"]["c2"]["value"] == pytest.approx(c2, rel=0.1)
    assert out["fit_after"]["held_out_nrmse"] < out["fit_before"]["held_out_nrmse_as_given"]
    assert out["fit_after"]["held_out_nrmse"] < out["fit_before"]["refit_held_out_nrmse"]

"""Friction named as friction (issue 76): a Bouc-Wen loop fitted where the record slides and presides
is read as a friction law, its parameters as a presliding stiffness and a sliding force."""
import math

from recon.diagnosis.wording import diagnosis_text, friction_reading


def test_a_saturating_loop_within_the_travel_reads_as_a_friction_law():
    # Dahl's friction model is a Bouc-Wen loop with n = 1: sliding force alpha / (gamma + delta)
    f = friction_reading(alpha_m=4e4, gamma=600.0, delta=400.0, travel=0.02)
    assert f["presliding_stiffness_m"] == 4e4
    assert f["sliding_force_m"] == 40.0
    assert abs(f["sliding_after_m"] + math.log(0.05) / 1000.0) < 1e-12
    d = {"missing_physics": [{"id": "hysteresis", "evidence": {"held_out_nrmse_before": 0.26,
                                                                "held_out_nrmse_after": 0.055},
                              "as_friction": f}]}
    text = diagnosis_text(d)
    assert "missing physics: hysteresis" in text and "friction law" in text and "presliding stiffness" in text


def test_a_loop_that_never_slides_or_stiffens_is_not_called_friction():
    # a travel shorter than the sliding distance: presliding only
    assert friction_reading(alpha_m=4e4, gamma=600.0, delta=400.0, travel=1e-3) is None
    # Dahl's law (gamma = delta), fitted a hair either side of it, reads as friction both ways
    assert friction_reading(4e4, 1242.36, 1242.53, 0.02) and friction_reading(4e4, 1242.53, 1242.36, 0.02)
    # the Bouc-Wen benchmark's hardening loop (gamma + delta < 0) does not saturate
    assert friction_reading(alpha_m=5e4, gamma=800.0, delta=-1100.0, travel=0.02) is None

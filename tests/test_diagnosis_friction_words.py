"""Friction named as friction (issue 76): a Bouc-Wen loop fitted where the record slides and presides
is read as a friction law, its parameters as a presliding stiffness and a sliding force."""
import math

import pytest

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


@pytest.mark.slow
def test_a_presliding_friction_against_a_linear_baseline_is_said_to_be_a_friction_law():
    """Dahl's friction (a Bouc-Wen loop with gamma = delta that slides within the stroke) on a linear
    system, diagnosed against the linear baseline (the issue's positioning-system case): the loop is
    named, read as a presliding stiffness and a sliding force near the truth's, and coulomb_friction
    is fitted from the loop's fit too (it loses: a velocity law has no presliding stiffness)."""
    import warnings

    import numpy as np

    from recon.diagnosis.diagnose import diagnose
    from recon.testing import independent as ind
    from recon.testing.runs import to_run

    warnings.filterwarnings("ignore")
    s = ind.random_system(np.random.default_rng([2, 78]), hysteresis=False, quadratic=False, cubic=False)
    alpha, lam = 0.3 * s["k"], 6.0 / s["Y"]
    s.update(alpha=alpha, k=s["k"] - alpha, gamma=0.5 * lam, delta=0.5 * lam)
    rec = ind.add_noise(ind.simulate(s, "paper", 1000.0, "none", 1.0, seed=2), 60.0, 2)
    out = diagnose(to_run(rec), baseline="linear", candidates=["coulomb_friction", "hysteresis"]).to_dict()
    assert [m["id"] for m in out["missing_physics"]] == ["hysteresis"], out["result"]
    f = out["missing_physics"][0]["as_friction"]
    assert f["sliding_force_m"] == pytest.approx(alpha / s["m"] / lam, rel=0.05)
    assert f["presliding_stiffness_m"] == pytest.approx(alpha / s["m"], rel=0.05)
    assert "friction law" in diagnosis_text(out)


@pytest.mark.slow
def test_a_dry_friction_held_as_a_sharp_loop_is_read_as_its_sliding_force(tmp_path, capsys):
    """A large dry friction on the simulated rig (0.276 m/s^2 per unit mass, one level): the
    reconstruction holds it as a sharp Bouc-Wen loop in place of the specimen's own. `reconstruct`
    says so and gives the loop's sliding force; `diagnose` says the same of its baseline, and names
    the friction in the loop's place (the loop dropped, the friction started at its sliding force) at
    the concealed size."""
    import json

    from shakerlab.cli import main
    from test_closed_loop import SHORT_PROTOCOL, short_run_args

    args = short_run_args(tmp_path, "[effects]\ncoulomb_friction = 0.276\n", seed=41)
    (tmp_path / "p.toml").write_text(SHORT_PROTOCOL.replace("start_vpp = 0.5", "start_vpp = 4.0"))
    assert main(args) == 0
    capsys.readouterr()
    run = str(tmp_path / "run.h5")
    assert main(["reconstruct", run, "--quiet"]) == 0
    assert "the loop acts as a friction law" in capsys.readouterr().out
    assert main(["reconstruct", run, "--json", "--quiet"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["loop_as_friction"]["sliding_force_m"] == pytest.approx(0.276, rel=0.3)
    assert main(["diagnose", run, "--json", "--quiet"]) == 0
    out = json.loads(capsys.readouterr().out)
    loop = out["baseline_loop_as_friction"]
    named = {m["id"]: m for m in out["missing_physics"]}
    assert loop is not None and "coulomb_friction" in named, out["result"]
    fr = named["coulomb_friction"]
    assert fr["hysteresis_dropped"], fr
    assert fr["parameters"]["mu"]["value"] == pytest.approx(0.276, rel=0.1)

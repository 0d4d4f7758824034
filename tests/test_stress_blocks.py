"""The stress bench's blocks apart from the random one (issue 74): two effects concealed together
(recon.testing.stress.pair_draw) and a linear stage at 0-10 dB (weak_linear_draw), their scoring
and their report apart. No diagnosis is run here."""
from __future__ import annotations

import numpy as np
import pytest

from recon.testing import independent as ind
from recon.testing.diagnosis_stress import block_of, report_apart, score_pair, score_weak_linear
from recon.testing.runs import true_model
from recon.testing.stress import (PAIRS, concealed_effects, draw, pair_draw, pair_recording, weak_linear_draw,
                                  weak_linear_recording)


def _same(a, b):
    """Two draws equal, arrays and nested dicts included."""
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], dict):
            _same(a[k], b[k])
        else:
            assert a[k] == b[k], k


@pytest.mark.parametrize("make, block", [(pair_draw, "pairs"), (weak_linear_draw, "weak_linear")])
def test_draws_are_reproducible_from_their_index_and_apart_from_the_random_block(make, block):
    for i in range(len(PAIRS) + 2):
        _same(make(i), make(i))
    assert make(0)["system"] != make(1)["system"]
    # not the random block's rows under another name
    assert make(3)["system"] != draw(3)["system"]
    assert {block_of(make(i)) for i in range(4)} == {block}


def test_pair_draws_cycle_through_the_pairs_at_their_strengths_and_snr():
    for i in range(2 * len(PAIRS)):
        d = pair_draw(i)
        assert (d["effect"], d["also"][0][0]) == PAIRS[i % len(PAIRS)]
        assert concealed_effects(d) == list(PAIRS[i % len(PAIRS)])
        assert 0.5 <= d["strength"] <= 1.5 and 0.5 <= d["also"][0][1] <= 1.5
        assert 50.0 <= d["snr"] <= 80.0
    # every pair is one the generator conceals together (the second a physical effect, not the contact)
    for first, second in PAIRS:
        assert first in ind.PHYSICAL_EFFECTS and second in ind.PHYSICAL_EFFECTS
        assert second not in (first, "contact_stiffness")


def test_pair_recording_conceals_both_effects():
    # pair #2: a contact with a tip sensor's scale error (the contact's gap is calibrated on the motion,
    # and the second effect must survive that)
    d = pair_draw(2)
    assert (d["effect"], d["also"][0][0]) == ("contact_stiffness", "sensor_scale")
    rec = pair_recording(d)
    e = rec["effect_parameters"]
    assert {"kc", "gap", "side", "tip_scale"} <= set(e)
    assert abs(e["tip_scale"]) == pytest.approx(0.02 * d["also"][0][1])
    assert rec["also"] == d["also"]
    alone = ind.add_noise(ind.simulate(d["system"], d["protocol"], d["fs"], d["effect"], d["strength"],
                                       seed=d["index"]), d["snr"], d["index"], d["quantisation"])
    assert "tip_scale" not in alone["effect_parameters"]
    a, b = alone["stages"]["validation"]["x_tip"], rec["stages"]["validation"]["x_tip"]
    assert np.std(a - b) > 0.3 * abs(e["tip_scale"]) * np.std(a)
    # the truth the bench scores against holds both
    am, k = true_model(rec)
    assert {"kc", "gap", "side", "tip_scale"} <= set(am.extras) and k == 3


def _snr(clean, noisy):
    return 20 * np.log10(np.sqrt(np.mean(clean ** 2)) / np.std(noisy - clean))


def test_weak_linear_recording_lowers_the_linear_stage_only():
    d = weak_linear_draw(0)
    assert 0.0 <= d["linear_snr"] <= 10.0 and 40.0 <= d["snr"] <= 80.0
    clean = ind.simulate(d["system"], d["protocol"], d["fs"], d["effect"], d["strength"], seed=d["index"],
                         mode_drive=d["mode_drive"])
    rec = weak_linear_recording(d)
    lin = _snr(clean["stages"]["linear"]["x_tip"], rec["stages"]["linear"]["x_tip"])
    assert 0.0 <= lin <= 10.0 and lin == pytest.approx(d["linear_snr"], abs=1.0)
    # the other stages: the noise they get without the option, to the bit
    usual = ind.add_noise(clean, d["snr"], d["index"], d["quantisation"])
    for name in rec["stages"]:
        if name != "linear":
            for ch in ("x_base", "x_tip"):
                np.testing.assert_array_equal(rec["stages"][name][ch], usual["stages"][name][ch])
            assert _snr(clean["stages"][name]["x_tip"], rec["stages"][name]["x_tip"]) >= 40.0 - 1.0
    assert rec["stage_snr_db"] == {"linear": d["linear_snr"]}
    np.testing.assert_array_equal(weak_linear_recording(d)["stages"]["linear"]["x_tip"],
                                  rec["stages"]["linear"]["x_tip"])


def _pair_row(**kw):
    row = {"index": 0, "block": "pairs", "effect": "coulomb_friction", "also": [["parameter_drift", 1.0]],
           "strength": 1.0, "protocol": "paper", "status": "ok", "first": "none", "named": [], "ambiguous": None}
    return {**row, **kw}


@pytest.mark.parametrize("kw, right_first, both, wrong", [
    ({"first": "parameter_drift", "named": ["parameter_drift"]}, True, False, []),
    ({"first": "coulomb_friction", "named": ["coulomb_friction", "parameter_drift"]}, True, True, []),
    ({"first": "quadratic_damping", "named": ["quadratic_damping", "coulomb_friction"]}, False, False,
     ["quadratic_damping"]),
    ({"first": "ambiguous", "named": [], "ambiguous": ["coulomb_friction", "quadratic_damping"]}, True, False,
     ["quadratic_damping"]),
    ({"first": "none"}, False, False, []),
    ({"status": "refused", "error": "UserFacingError: ..."}, False, False, []),
])
def test_a_pair_row_is_right_first_on_either_effect_and_both_on_both(kw, right_first, both, wrong):
    s = score_pair(_pair_row(**kw))
    assert s["pair"] == ["coulomb_friction", "parameter_drift"]
    assert (s["right_first"], s["both"], s["wrong_names"]) == (right_first, both, wrong)


def test_a_weak_linear_row_says_whether_it_was_diagnosed_and_the_linear_stage_said_too_noisy():
    base = {"index": 0, "block": "weak_linear", "effect": "none", "baseline": "paper", "linear_snr": 4.0}
    ok = score_weak_linear({**base, "status": "ok",
                            "baseline_warnings": ["linear stage 'linear' too noisy for c and K (...)"]})
    assert ok == {"diagnosed": True, "exit": 0, "refusal": None, "linear_reported_noisy": True}
    assert score_weak_linear({**base, "status": "ok", "baseline_warnings": []})["linear_reported_noisy"] is False
    given = score_weak_linear({**base, "status": "ok", "baseline": "truth without the term"})
    assert given["linear_reported_noisy"] is None
    refused = score_weak_linear({**base, "status": "refused", "error": "NoisyLinearStage: too noisy"})
    assert refused == {"diagnosed": False, "exit": 2, "refusal": "NoisyLinearStage: too noisy",
                       "linear_reported_noisy": None}
    assert score_weak_linear({**base, "status": "failed", "error": "ValueError"})["exit"] == 1


def test_the_report_counts_each_block_apart():
    clean = {"index": 0, "effect": "none", "protocol": "paper", "status": "ok", "first": "none", "named": [],
             "right": True, "strength": 1.0, "held_out": {}, "seconds": 1.0, "sim_seconds": 1.0, "snr": 60.0}
    pair = _pair_row(first="coulomb_friction", named=["coulomb_friction", "parameter_drift"], seconds=2.0,
                     sim_seconds=1.0, held_out={})
    weak = {**clean, "block": "weak_linear", "linear_snr": 4.0, "baseline": "paper", "status": "refused",
            "error": "NoisyLinearStage: too noisy", "right": False}
    assert [block_of(r) for r in (clean, pair, weak, {"corner": "issue76"})] == ["random", "pairs", "weak_linear",
                                                                                  "corner"]
    text = "\n".join(report_apart([pair, clean, weak]))
    random_part = text.split("== two effects")[0]
    assert "== the random block: 1 rows ==" in random_part
    assert "coulomb_friction" not in random_part          # the pair row stays out of its confusion table
    assert "false alarms on clean recordings: 0/1" in random_part
    assert "| coulomb_friction + parameter_drift | 1 |" in text
    assert "one of the two concealed effects named first: 1/1" in text and "both named: 1/1" in text
    assert "== a linear stage at 0-10 dB SNR: 1 rows ==" in text
    assert "diagnosed 0/1, refused 1/1" in text and "NoisyLinearStage: too noisy" in text


def test_true_model_of_a_pair_holds_both_effects():
    rec = {"effect": "coulomb_friction", "also": [["parameter_drift", 1.0]], "system": {"m": 2.0},
           "effect_parameters": {"Fc": 0.4, "v_eps": 1e-3, "drift_rate": 5e-4},
           "truth": {"c_m": 1.0, "k_m": 1000.0, "alpha_m": 0.0, "gamma": 0.0, "delta": 0.0, "fn_m": {}}}
    am, k = true_model(rec)
    assert am.extras == {"mu": 0.2, "v0": 1e-3, "drift": 5e-4} and k == 2

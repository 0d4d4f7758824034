"""The diagnosis's settings (recon.diagnosis.settings): validated, described, and used by diagnose."""
import dataclasses

import pytest
from hypothesis import given, settings as hyp_settings, strategies as st

from recon.diagnosis import rank
from recon.diagnosis.diagnose import diagnose
from recon.diagnosis.settings import DEFAULTS, DiagnosisSettings, SignificanceRule, describe
from recon.testing.concealed import concealed_run


@pytest.mark.parametrize("field,value,match", [
    ("bic_margin", -1.0, "bic_margin = -1.0 is outside"),
    ("min_explained", 1.5, "min_explained = 1.5 is outside"),
    ("steady_rel_gain", float("nan"), "steady_rel_gain must be finite numbers"),
    ("held_blocks", 2.5, "held_blocks must be a whole number"),
    ("held_blocks", 0, "held_blocks = 0 is outside"),
    ("complete_gain", "0.1", "complete_gain must be finite numbers"),
])
def test_a_rule_out_of_range_is_refused_naming_the_field(field, value, match):
    with pytest.raises(ValueError, match=match):
        SignificanceRule(**{field: value})


def test_settings_out_of_range_are_refused_and_the_rule_must_be_a_rule():
    with pytest.raises(ValueError, match=r"hold_fraction = 0.0 is outside \(0, 1\]"):
        DiagnosisSettings(hold_fraction=0.0)
    with pytest.raises(ValueError, match="burn_in_decays"):
        DiagnosisSettings(burn_in_decays=-3.0)
    with pytest.raises(ValueError, match="sliding_share must be below 1"):
        DiagnosisSettings(sliding_share=1.0)
    with pytest.raises(ValueError, match="time_segments must be a whole number"):
        DiagnosisSettings(time_segments=2.5)
    with pytest.raises(ValueError, match="rule must be a SignificanceRule"):
        DiagnosisSettings(rule={"bic_margin": 10.0})
    with pytest.raises(dataclasses.FrozenInstanceError):
        DEFAULTS.hold_fraction = 0.5
    with pytest.raises(TypeError, match="settings must be a DiagnosisSettings"):
        diagnose(None, settings={"hold_fraction": 0.3})


def test_every_setting_says_its_meaning_unit_and_range():
    rows = describe(DEFAULTS)
    names = {r["name"] for r in rows}
    assert {"hold_fraction", "cover_share", "top_reach", "burn_in_decays", "burn_in_keep", "fit_model_share",
            "rule.bic_margin", "rule.min_gain_noise", "rule.steady_rel_gain", "rule.held_blocks"} <= names
    n_fields = len(dataclasses.fields(DiagnosisSettings)) - 1 + len(dataclasses.fields(SignificanceRule))
    assert len(rows) == n_fields
    for r in rows:
        assert r["meaning"] and r["unit"] and r["range"][0] <= r["value"] <= r["range"][1], r


figures = st.tuples(st.floats(-1e4, 1e3), st.floats(-1.0, 2.0), st.floats(0.0, 100.0), st.floats(-1.0, 1.0),
                    st.one_of(st.none(), st.sampled_from([0.0, 0.5, 0.8, 0.9, 1.0])))
THRESHOLDS = ["bic_margin", "min_explained", "min_gain_noise", "min_rel_gain", "consistent_blocks", "steady_gain",
              "steady_rel_gain", "complete_blocks", "complete_explained", "complete_gain", "complete_rel_gain"]


@hyp_settings(max_examples=300, deadline=None)
@given(figures, st.sampled_from(THRESHOLDS), st.floats(0.0, 1.0))
def test_a_stricter_rule_never_passes_what_a_looser_one_fails(fig, name, raise_by):
    """Each threshold of the rule only ever asks more as it grows: raising one cannot turn a
    failing candidate into a passing one."""
    loose = DEFAULTS.rule
    limit = {"bic_margin": 1e3}.get(name, 1.0 if "blocks" in name or "explained" in name or "rel" in name else 1e6)
    strict = dataclasses.replace(loose, **{name: min(getattr(loose, name) + raise_by, limit)})
    if strict.passes(*fig):
        assert loose.passes(*fig)
    assert rank.score.__defaults__[-1] is DEFAULTS.rule


def test_diagnose_uses_the_settings_it_is_given():
    """A concealed quadratic damping is named under the calibrated rule and not under a rule whose
    BIC margin no record of this length can meet; the held-out split follows hold_fraction (with
    top_reach 0: no top level is asked to be fitted)."""
    run, _, _, baseline = concealed_run("quadratic_damping", seed=6, duration=3.0)
    del run.stages["validation"]          # every stage's end is held out: the split is the setting's
    cands = ["quadratic_damping", "cubic_stiffness"]
    named = diagnose(run, baseline, candidates=cands)
    assert [m["id"] for m in named.missing][:1] == ["quadratic_damping"]
    strict = dataclasses.replace(DEFAULTS, rule=dataclasses.replace(DEFAULTS.rule, bic_margin=999.0),
                                 hold_fraction=0.5, top_reach=0.0)
    none = diagnose(run, baseline, candidates=cands, settings=strict)
    assert none.missing == []
    assert none.fit_before["held_out_share"]["nonlinear"] == pytest.approx(0.5, abs=1e-3)
    cut = rank.hold_cut(run.stage("nonlinear").y)          # the calibrated split of the same stage
    assert named.fit_before["held_out_share"]["nonlinear"] == pytest.approx(1 - cut / run.stage("nonlinear").y.size,
                                                                            abs=1e-3)

"""Never an improvement that is worse on one held-out stage (issue 76; recon/diagnosis/stagewise.py).

A model better on the held-out samples as a whole but worse than the baseline as given on one held-out
stage beyond that stage's noise band is not named: the answer is "partly explained" with that stage."""
import types

import numpy as np

from recon.diagnosis import stagewise
from recon.diagnosis.diagnose import Diagnosis
from recon.diagnosis.wording import diagnosis_text


def _stage(name, y, noise, held_from=0):
    held = np.zeros(y.size, bool)
    held[held_from:] = True
    return types.SimpleNamespace(name=name, y=y, held=held, noise=noise)


def _fit(sims):
    return types.SimpleNamespace(sims=sims)


def _record(rng, n=4000, noise=1e-6):
    t = np.arange(n) / 1000.0
    s1 = 1e-3 * np.sin(2 * np.pi * 20 * t)
    s2 = 1e-3 * np.sin(2 * np.pi * 30 * t + 0.3)
    data = [_stage("nonlinear", s1 + rng.normal(0, noise, n), noise, held_from=int(0.7 * n)),
            _stage("validation", s2 + rng.normal(0, noise, n), noise)]
    return data, s1, s2


def test_a_model_better_as_a_whole_but_worse_on_one_stage_fails_there():
    """The issue's second-mode row: validation 0.0315 -> 0.0067, the nonlinear stage 0.0003 -> 0.0056.
    As a whole the candidate is far better; on the nonlinear stage it is worse by many noise bands."""
    rng = np.random.default_rng(1)
    data, s1, s2 = _record(rng)
    miss = 0.03 * 1e-3 * np.sin(2 * np.pi * 90 * np.arange(s2.size) / 1000.0)
    given = _fit([s1 + 2e-7, s2 + miss])                      # good on nonlinear, misses validation
    cand = _fit([s1 + 4e-6 * np.cos(2 * np.pi * 20 * np.arange(s1.size) / 1000.0), s2 + 0.2 * miss])
    figs = stagewise.held_stage_figures(given, cand, data)
    assert stagewise.worse_stages(figs) == ["nonlinear"]
    assert figs["validation"]["nrmse_after"] < figs["validation"]["nrmse_before"]
    assert figs["nonlinear"]["rise_noise_variances"] > figs["nonlinear"]["band_noise_variances"] > 0


def test_a_model_that_differs_by_less_than_the_noise_is_not_called_worse():
    """Two models equally far from the truth on every stage, on either side of it: called worse on
    some stage at most about as often as the band's level says (the rule's stage_level over every held-out stage)."""
    rng = np.random.default_rng(2)
    calls = 0
    trials = 200
    for _ in range(trials):
        data, s1, s2 = _record(rng, n=1000)
        tone = np.sin(2 * np.pi * 20 * np.arange(s1.size) / 1000.0)
        given = _fit([s1 - 3e-7 * tone, s2 + 3e-7 * tone])
        cand = _fit([s1 + 3e-7 * tone, s2 - 3e-7 * tone])      # as good as the baseline
        calls += bool(stagewise.worse_stages(stagewise.held_stage_figures(given, cand, data)))
    assert calls <= 0.01 * trials + 3


def test_partly_explained_in_the_json_and_the_words():
    """The JSON keeps every key of the contract and adds ``partly_explained``; the one-line result and the
    sentence name the stage where the model fails."""
    rng = np.random.default_rng(3)
    data, s1, s2 = _record(rng)
    given = _fit([s1, s2 + 3e-5])
    cand = _fit([s1 + 2e-5, s2])
    figs = stagewise.held_stage_figures(given, cand, data)
    from recon.diagnosis.diagnose import partly_entry
    fr = types.SimpleNamespace(nrmse_held=0.01, nrmse={"nonlinear": 0.01}, model=None)
    p = partly_entry(["sensor_scale"], figs, fr, types.SimpleNamespace(nrmse_held=0.02))
    assert p["worse_on_stages"] == ["nonlinear"]
    model = types.SimpleNamespace(equation=lambda: "eq", to_dict=lambda: {},
                                  baseline=types.SimpleNamespace(provenance={}))
    d = Diagnosis(baseline=model, baseline_kind="paper", fit_before={}, null=fr, mismatch=[], candidates=[],
                  missing=[], best=model, best_fit=fr, partly=p)
    out = d.to_dict()
    assert out["missing_physics"] == [] and out["partly_explained"]["ids"] == ["sensor_scale"]
    assert out["result"].startswith("partly explained: sensor_scale") and "nonlinear" in out["result"]
    assert "stage 'nonlinear'" in diagnosis_text(out)

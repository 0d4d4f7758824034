"""Parameter intervals (recon.output_error.uncertainty) on ground truth with known parameters."""
import numpy as np
import pytest

from recon import reconstruct
from recon.testing.truth import sdof_run
from recon.output_error.uncertainty import (UncertaintySettings, covers, fitted_stages, parameter_intervals, reconstruct_capturing,
                               term_inclusion)
from shakerlab.errors import UserFacingError

S = UncertaintySettings(n_resamples=100)


@pytest.fixture(scope="module")
def fitted():
    run, truth = sdof_run("base", snr_db=80.0, fs=1000.0, duration=4.0, seed=1)
    result, problem = reconstruct_capturing(run)
    return run, truth, result, problem


def _widths(unc):
    iv = unc["intervals"]
    w = {k: iv[k][1] - iv[k][0] for k in ("c_m", "k_m", "alpha_m", "gamma", "delta")}
    w.update({f"fn:{k}": v[1] - v[0] for k, v in iv["fn_m"].items()})
    return w


def test_intervals_cover_truth_at_80_db(fitted):
    run, truth, result, _ = fitted
    unc = parameter_intervals(result.model, run, S)
    p = result.to_dict()["parameters"]
    assert unc["stages"] == fitted_stages(result.model)
    assert unc["at_optimum"]
    for k in ("c_m", "k_m", "alpha_m", "gamma", "delta"):
        lo, hi = unc["intervals"][k]
        assert lo < p[k] < hi
        assert (hi - lo) < 0.2 * abs(p[k])             # informative, not a blanket
    assert set(unc["intervals"]["fn_m"]) == set(p["fn_m"])
    # 95 % intervals on seven parameters: all seven hold the truth on about 70 % of records, so
    # one record is asked for at most one miss, and that one close (bench/uncertainty_coverage.py
    # measures the calibration over repetitions: 90-100 % per parameter at 80 dB)
    tp = truth.to_dict()["parameters"]
    c = covers(unc, tp)
    missed = [k for k, ok in c.items() if not ok]
    assert len(missed) <= 1, c
    for k in missed:
        name = k[len("fn_m["):-1] if k.startswith("fn_m[") else None
        lo, hi = unc["intervals"]["fn_m"][name] if name else unc["intervals"][k]
        v = tp["fn_m"][name] if name else tp[k]
        assert lo - (hi - lo) / 2 <= v <= hi + (hi - lo) / 2, (k, lo, hi, v)
    # reproducible with the same seed, different with another
    again = parameter_intervals(result.model, run, S)
    assert again["intervals"] == unc["intervals"]
    other = parameter_intervals(result.model, run, UncertaintySettings(n_resamples=100, seed=5))
    assert other["intervals"]["k_m"] != unc["intervals"]["k_m"]


def test_width_follows_the_noise_and_the_input_noise_counts():
    """Intervals around the true model: 20 dB more noise makes every one wider (not a full 10
    times: at 80 dB part of the residual is the differentiated input's remaining error and the
    estimated start, which do not scale with the noise; measured ratios 1.2-5.4, median 2.0),
    and leaving the input noise out of the ensemble makes them too narrow. (Since the input is
    cleared above its band, recon.input_band, the input noise is a smaller part: c_m's interval
    without it is 0.64 of the full width here, 0.09 with the Savitzky-Golay input, whose full
    interval was 8 times wider.)"""
    w = {}
    for snr in (80.0, 60.0):
        run, truth = sdof_run("base", snr_db=snr, fs=1000.0, duration=4.0, seed=2)
        w[snr] = _widths(parameter_intervals(truth, run, S))
    ratio = {k: w[60.0][k] / w[80.0][k] for k in w[80.0]}
    assert all(1.15 < r < 25.0 for r in ratio.values()), ratio
    assert np.median(list(ratio.values())) > 1.5, ratio
    narrow = _widths(parameter_intervals(truth, run, UncertaintySettings(n_resamples=100, input_noise=False)))
    assert narrow["c_m"] < 0.8 * w[60.0]["c_m"]


def test_covers_and_bad_settings(fitted):
    unc = {"intervals": {"c_m": [1.0, 2.0], "k_m": [0.0, 1.0], "fn_m": {"y^3": [1.0, 3.0], "y^5": [-1.0, 1.0]}}}
    c = covers(unc, {"c_m": 1.5, "k_m": 2.0, "fn_m": {"y^3": 2.0, "y^2*dy": 1.0}})
    assert c == {"c_m": True, "k_m": False, "fn_m[y^3]": True, "fn_m[y^2*dy]": False, "fn_m[y^5]": True}
    run, _, result, _ = fitted
    with pytest.raises(UserFacingError, match="level"):
        parameter_intervals(result.model, run, UncertaintySettings(level=1.5))
    with pytest.raises(UserFacingError, match="at least 50 resamples"):
        parameter_intervals(result.model, run, UncertaintySettings(n_resamples=10))
    with pytest.raises(UserFacingError, match="none of the fitting stages"):
        parameter_intervals(result.model, run, UncertaintySettings(stages=("sweep",)))


def test_term_inclusion(fitted):
    run, truth, result, problem = fitted
    # the captured reconstruction is the plain one
    assert result.to_dict()["parameters"] == reconstruct(run).to_dict()["parameters"]
    ti = term_inclusion(problem, n_models=6)
    assert ti["available"] and ti["selected"] == sorted(truth.fn_m) and ti["failed_models"] == 0
    assert all(ti["inclusion"][t] >= 0.8 for t in truth.fn_m)
    assert all(0.0 <= f <= 1.0 for f in ti["inclusion"].values())
    # fewer rows per member: the selection gets less stable, never more
    thin = term_inclusion(problem, n_models=6, keep=0.3)
    assert min(thin["inclusion"][t] for t in truth.fn_m) <= min(ti["inclusion"][t] for t in truth.fn_m)
    assert term_inclusion(None)["available"] is False

"""A Bouc-Wen law with gamma + delta < 0 (a loop that hardens; the Bouc-Wen benchmark's own law)
is a hysteresis within a bounded motion, not an inadmissible one. Records simulated by scipy's
solve_ivp on their own equations, not by recon."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline

from recon import diagnose
from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.candidates.hysteresis import HARDENING_LIMIT, LOOP_MIN_OPENING
from recon.diagnosis.diagnose import implausible
from recon.model import HystereticModel
from shakerlab.run_data import Run, Stage

# the benchmark's system (Noel & Schoukens 2016): m y'' + c y' + k y + z = u,
# z' = alpha y' - beta (gamma |y'| z + delta y' |z|)
M, C, K, ALPHA, BG, BD = 2.0, 10.0, 5.0e4, 5.0e4, 800.0, -1100.0
FS = 750.0


def _stage(name: str, rms: float, seed: int, seconds: float) -> Stage:
    rng = np.random.default_rng(seed)
    f = np.arange(5.0, 150.0, 0.25)
    phase = rng.uniform(0, 2 * np.pi, f.size)
    tf = np.arange(0.0, seconds + 0.01, 1.0 / (8 * FS))
    u = np.cos(2 * np.pi * f[None, :] * tf[:, None] + phase[None, :]).sum(axis=1)
    u *= rms / np.sqrt(np.mean(u ** 2))
    us = CubicSpline(tf, u)

    def rhs(t, s):
        y, v, z = s
        return [v, (us(t) - C * v - K * y - z) / M, ALPHA * v - BG * abs(v) * z - BD * v * abs(z)]

    t = np.arange(0.0, seconds, 1.0 / FS)
    sol = solve_ivp(rhs, (0.0, t[-1]), [0.0, 0.0, 0.0], t_eval=t, rtol=1e-8, atol=1e-11, max_step=1.0 / FS)
    y = sol.y[0] + rng.normal(0.0, 2e-6, t.size)
    return Stage(name, t, {"x": y, "force": us(t)}, excitation="force")


@pytest.mark.slow
def test_a_hardening_loop_is_named_hysteresis_with_its_parameters():
    run = Run({"linear": _stage("linear", 5.0, 1, 4.0), "nonlinear": _stage("nonlinear", 50.0, 2, 8.0),
               "validation": _stage("validation", 40.0, 3, 4.0)}, source="solve_ivp Bouc-Wen benchmark law")
    d = diagnose(run, baseline="linear", candidates=["hysteresis", "cubic_stiffness", "quadratic_damping"]).to_dict()
    assert [m["id"] for m in d["missing_physics"]][:1] == ["hysteresis"], d["result"]
    p = d["missing_physics"][0]["parameters"]
    assert abs(p["alpha_m"]["value"] / (ALPHA / M) - 1) < 0.05
    assert p["gamma"]["value"] + p["delta"]["value"] < 0
    assert abs((p["gamma"]["value"] + p["delta"]["value"]) / (BG + BD) - 1) < 0.2
    assert d["fit_after"]["held_out_nrmse"] < 0.2 * d["fit_before"]["held_out_nrmse"]


def _fit_of(law: HystereticModel) -> rank.FitResult:
    return rank.FitResult(model=AugmentedModel(law, {}, ["hysteresis"]), cost_fit=0.0, mse_held=0.0, nrmse={},
                          nrmse_held=0.0, n_held=1)


def test_a_loop_that_stiffens_beyond_the_limit_across_the_record_is_refused():
    ref = AugmentedModel(HystereticModel("force", 5.0, 2.5e4, 0.0, 0.0, 0.0, inv_m=0.5))
    data = [SimpleNamespace(displacement=np.array([-0.002, 0.002]))]      # a 4 mm range
    lam_ok = -0.9 * math.log(HARDENING_LIMIT) / 0.004
    lam_bad = -1.1 * math.log(HARDENING_LIMIT) / 0.004
    ok = HystereticModel("force", 5.0, 2.5e4, 2.5e4, 800.0, lam_ok - 800.0, inv_m=0.5)
    bad = HystereticModel("force", 5.0, 2.5e4, 2.5e4, 800.0, lam_bad - 800.0, inv_m=0.5)
    assert implausible("hysteresis", _fit_of(ok), ref, data, intervals=False) == []
    why = implausible("hysteresis", _fit_of(bad), ref, data, intervals=False)
    assert why and "stiffens" in why[0], why
    neg = HystereticModel("force", 5.0, 2.5e4, -10.0, 800.0, 100.0, inv_m=0.5)
    assert implausible("hysteresis", _fit_of(neg), ref, data, intervals=False)


def test_a_law_whose_loop_does_not_open_over_the_record_is_refused():
    # stress #958: alpha at 99 % of K, gamma -0.21 and delta 0.29 per m over a 0.66 mm range: a
    # linear spring whose per-stage start z0 is a constant force
    ref = AugmentedModel(HystereticModel("base", 10.5, 1.15e5, 0.0, 0.0, 0.0))
    data = [SimpleNamespace(displacement=np.array([-0.00033, 0.00033]))]
    flat = HystereticModel("base", 10.5, 880.0, 1.142e5, -0.21, 0.29)
    why = implausible("hysteresis", _fit_of(flat), ref, data, intervals=False)
    assert why and "does not open" in why[0], why
    # the same law with a loop that opens by 2 % over the range is kept
    lam = 2 * LOOP_MIN_OPENING / 0.00033
    opened = HystereticModel("base", 10.5, 880.0, 1.142e5, 0.6 * lam, 0.4 * lam)
    assert implausible("hysteresis", _fit_of(opened), ref, data, intervals=False) == []

"""Issue 17: a failing candidate is recorded and left out of the ranking; a failing null model is a
clear UserFacingError; no exception reaches the user. Every failure is brought about by a real input
(a run, a baseline model, the settings), never by replacing a recon function."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from recon import diagnose
from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.settings import DiagnosisSettings
from recon.model import HystereticModel
from recon.testing.concealed import concealed_run
from shakerlab.errors import UserFacingError
from shakerlab.run_data import Run

CANDIDATES = ["coulomb_friction", "quadratic_damping"]


@pytest.fixture(scope="module")
def concealed():
    return concealed_run("coulomb_friction", duration=2.0, seed=3)


@pytest.fixture(scope="module")
def run(concealed):
    return concealed[0]


@pytest.fixture(scope="module")
def baseline(concealed):
    """The concealed run's baseline: the truth without its friction."""
    return concealed[3]


def without_validation(run: Run) -> Run:
    """``run`` without its validation stage: the last share of every stage is held out instead."""
    return Run({n: st for n, st in run.stages.items() if not n.startswith("validation")}, dict(run.attrs),
               run.source)


@pytest.fixture(scope="module")
def stiff_damping():
    """(run, truth, diagnosis against the linear baseline) of a quadratic damping 30 000 times the
    concealed size (c2 = 9e5 1/m), recorded without a validation stage: the generator's fine
    integration records it, while at the record's 1 kHz the diagnosis's RK4 (substeps chosen from the
    stiffness, not from c2 |y'|) is unstable at the top of the ramped nonlinear stage. The quadratic
    damping candidate's fit, which reaches such a c2, diverges on that stage's held-out end."""
    r, truth, extras, _ = concealed_run("quadratic_damping", strength=3.0e4, duration=2.0, seed=3)
    r = without_validation(r)
    return r, AugmentedModel(truth, extras), diagnose(r, baseline="linear", candidates=CANDIDATES).to_dict()


def test_the_stiff_damping_truth_diverges_only_at_the_top_of_the_ramp(stiff_damping):
    # the premise of the two tests below: the recording is finite, the truth's own simulation at
    # the default step for the record's rate is not, and only near the top of the ramped nonlinear
    # stage (the step the stage is integrated with, rank.integration_step_factor, is set by the
    # baseline without the damping term; a fit that raises the term goes past it again)
    r, truth, _ = stiff_damping
    assert all(np.all(np.isfinite(st.y)) for st in r.stages.values())
    for d in rank.prepare(r, truth.baseline):
        bad = np.flatnonzero(~np.isfinite(rank.stage_output(truth, dataclasses.replace(d, step_factor=1))))
        if d.name == "nonlinear":
            assert bad.size and bad[0] > 0.8 * d.t.size and d.held.any(), (d.name, bad[:1])
        else:
            assert not bad.size, d.name


def test_a_diverging_candidate_simulation_is_recorded_not_raised(stiff_damping):
    d = stiff_damping[2]
    tested = {t["id"]: t for t in d["candidates_tested"]}
    assert "FloatingPointError" in tested["quadratic_damping"]["failed"]
    assert not tested["quadratic_damping"]["significant"]
    assert "quadratic_damping" not in [m["id"] for m in d["missing_physics"]]
    assert "failed" not in tested["coulomb_friction"]          # the other candidate was still ranked
    assert np.isfinite(tested["coulomb_friction"]["held_out_nrmse"])


def test_a_non_finite_candidate_mse_is_recorded_not_raised(stiff_damping):
    tested = {t["id"]: t for t in stiff_damping[2]["candidates_tested"]}
    assert "mean-square error is inf" in tested["quadratic_damping"]["failed"]


def test_an_empty_held_out_set_is_a_clear_error(run, baseline):
    # without a validation stage the last hold_fraction of each stage is held out; a share so small
    # that (1 - hold_fraction) n rounds to n holds out no sample of any stage (any stage length
    # keeps at least one sample held out at a share the float arithmetic resolves)
    settings = DiagnosisSettings(hold_fraction=1e-17)
    short = without_validation(run)
    assert sum(int(d.held.sum()) for d in rank.prepare(short, baseline, settings)) == 0
    with pytest.raises(UserFacingError, match="no held-out samples"):
        diagnose(short, baseline="linear", candidates=CANDIDATES, settings=settings)


def test_a_diverging_null_model_names_the_stage(run, baseline):
    # a baseline whose cubic stiffness softens so much (y^3 at -1e10 1/(m^2 s^2) beside k + alpha =
    # 9000 1/s^2) that it escapes its well at the amplitudes of the nonlinear and validation stages;
    # the small linear stage stays inside it. Refitting cannot move it (every trial diverges)
    params = baseline.to_dict()
    params["parameters"]["fn_m"]["y^3"] = -1.0e10
    softening = HystereticModel.from_dict(params)
    with pytest.raises(UserFacingError, match=r"does not simulate stage\(s\) nonlinear, validation \(the simulation"):
        diagnose(run, baseline=softening, candidates=CANDIDATES)


def test_score_never_raises_on_degenerate_mse():
    r = rank.FitResult(model=None, cost_fit=0.0, mse_held=float("inf"), nrmse={}, nrmse_held=float("nan"), n_held=10,
                       resid_held=np.ones(10))
    ok = dataclasses.replace(r, mse_held=1.0)
    for null, cand in ((r, ok), (ok, r), (dataclasses.replace(ok, mse_held=0.0), ok)):
        s = rank.score(null, cand, 1, 0.1)
        assert s["significant"] is False


def test_a_baseline_force_that_overflows_on_the_recorded_path_takes_its_scale_from_the_measurements(baseline):
    # a reconstructed baseline once integrated z to NaN along the measured y' (stress recording #28,
    # gamma 3.5e5), and the equation-error scales of every candidate were NaN. z is now integrated
    # exactly (bounded, test below); a force that still overflows (here a y^12 term on a path of 1e30)
    # gives the scale of the measured force per unit mass, g u - y'', never NaN
    from recon.diagnosis.locate import equation_residual

    params = baseline.to_dict()
    params["parameters"]["fn_m"]["y^12"] = 1.0
    steep = AugmentedModel(HystereticModel.from_dict(params))
    n = 200
    t = np.arange(n) * 1e-3
    y = np.full(n, 1.0e30)
    dy = np.zeros(n)
    ddy = 3.0 * np.sin(2 * np.pi * 5 * t)
    u = 2.0 * np.cos(2 * np.pi * 5 * t)
    with np.errstate(over="ignore", invalid="ignore"):
        _, _, e, _, scale = equation_residual(steep, (t, y, dy, ddy, u, 1e-3))
    assert not np.all(np.isfinite(e))          # the premise: the force overflowed
    measured = steep.baseline.input_gain * u - ddy
    assert scale == pytest.approx(float(np.sqrt(np.mean(measured ** 2))), rel=1e-12)


def test_a_stiff_bouc_wen_law_integrates_z_along_the_measured_velocity():
    # stress #256: a reconstructed baseline with alpha_m 3e-5 and gamma 1.4e5 at 2 kHz; RK2 on the
    # samples (gamma |y'| dt about 13) grew z to 1e50 and every candidate's scale with it
    from types import SimpleNamespace

    from scipy.integrate import solve_ivp

    from recon.diagnosis.locate import z_from_velocity

    law = SimpleNamespace(alpha_m=3.0e-5, gamma=1.35e5, delta=-4.0e3)
    dt = 1.0 / 2086.0
    t = np.arange(0.0, 0.5, dt)
    v = 0.2 * np.sin(2 * np.pi * 30.0 * t)
    z = z_from_velocity(law, v, dt)

    def rhs(tt, zz):
        vv = 0.2 * np.sin(2 * np.pi * 30.0 * tt)
        return law.alpha_m * vv - law.gamma * abs(vv) * zz - law.delta * vv * np.abs(zz)

    ref = solve_ivp(rhs, (t[0], t[-1]), [0.0], method="Radau", t_eval=t, rtol=1e-9, atol=1e-16).y[0]
    assert np.all(np.isfinite(z))
    # bounded by the law's own ceiling, and close to the accurate solution (the sign changes at
    # y' = 0, a sample wide, keep the pointwise error there large)
    assert np.max(np.abs(z)) <= 1.01 * np.max(np.abs(ref)), (np.max(np.abs(z)), np.max(np.abs(ref)))
    assert np.sqrt(np.mean((z - ref) ** 2)) < 0.1 * np.sqrt(np.mean(ref ** 2))


def test_a_mild_bouc_wen_law_along_the_measured_velocity_matches_an_accurate_solution():
    # the RK2 branch of the (numba) z loop: a law with gamma |y'| dt about 0.05
    from types import SimpleNamespace

    from scipy.integrate import solve_ivp

    from recon.diagnosis.locate import z_from_velocity

    law = SimpleNamespace(alpha_m=400.0, gamma=900.0, delta=-300.0)
    dt = 1.0 / 2000.0
    t = np.arange(0.0, 1.0, dt)
    v = 0.1 * np.sin(2 * np.pi * 5.0 * t) + 0.03 * np.sin(2 * np.pi * 17.0 * t)
    z = z_from_velocity(law, v, dt)

    def rhs(tt, zz):
        vv = 0.1 * np.sin(2 * np.pi * 5.0 * tt) + 0.03 * np.sin(2 * np.pi * 17.0 * tt)
        return law.alpha_m * vv - law.gamma * abs(vv) * zz - law.delta * vv * np.abs(zz)

    ref = solve_ivp(rhs, (t[0], t[-1]), [0.0], method="DOP853", t_eval=t, rtol=1e-10, atol=1e-12).y[0]
    assert np.sqrt(np.mean((z - ref) ** 2)) < 1e-3 * np.sqrt(np.mean(ref ** 2))


def test_correlation_tests_on_a_residual_shorter_than_their_lags_give_no_test_and_no_error():
    # a reference whose resonance is far below the stage's band thins the equation residual to a few
    # samples (locate decimates it to about 8 per resonance period): fewer than the 20 lags
    import numpy as np
    from recon.diagnosis.locate import billings_voon

    rng = np.random.default_rng(0)
    short = billings_voon(rng.normal(size=15), rng.normal(size=15))      # raised a broadcast error
    assert short["n"] == 15 and "phi_ee" in short                          # lags up to 15 // 4
    tiny = billings_voon(rng.normal(size=6), rng.normal(size=6))
    assert tiny["n"] == 6 and not [k for k, v in tiny.items() if isinstance(v, dict)]
    e = rng.normal(size=400)
    full = billings_voon(e, rng.normal(size=400))
    assert {k for k, v in full.items() if isinstance(v, dict)} == {"phi_ee", "phi_ue", "phi_e_eu", "phi_u2_e",
                                                                   "phi_u2_e2"}
    assert full["phi_ee"]["outside_95"] < 0.2        # white noise: about 5 % of the lags outside the band
    # a coloured residual fails its autocorrelation test
    coloured = np.convolve(e, np.ones(8) / 8, mode="same")
    assert billings_voon(coloured, rng.normal(size=400))["phi_ee"]["outside_95"] > 0.1

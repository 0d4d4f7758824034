"""Issue 17: a failing candidate is recorded and left out of the ranking; a failing null model is a
clear UserFacingError; no exception reaches the user."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from recon import diagnose
from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.testing.concealed import concealed_run
from shakerlab.errors import UserFacingError

CANDIDATES = ["coulomb_friction", "quadratic_damping"]


@pytest.fixture(scope="module")
def run():
    r = concealed_run("coulomb_friction", duration=2.0, seed=3)
    return r[0] if isinstance(r, tuple) else r


def _is_candidate(am) -> bool:
    return any(c in getattr(am, "added", []) for c in CANDIDATES)


def test_a_diverging_candidate_simulation_is_recorded_not_raised(run, monkeypatch):
    real = AugmentedModel.simulate

    def diverging(self, *a, **k):
        if "coulomb_friction" in self.added:
            raise FloatingPointError("overflow in the simulation (forced by the test)")
        return real(self, *a, **k)

    monkeypatch.setattr(AugmentedModel, "simulate", diverging)
    d = diagnose(run, baseline="linear", candidates=CANDIDATES).to_dict()
    tested = {t["id"]: t for t in d["candidates_tested"]}
    assert "FloatingPointError" in tested["coulomb_friction"]["failed"]
    assert not tested["coulomb_friction"]["significant"]
    assert "coulomb_friction" not in [m["id"] for m in d["missing_physics"]]
    assert "failed" not in tested["quadratic_damping"]          # the other candidate was still ranked


def test_a_non_finite_candidate_mse_is_recorded_not_raised(run, monkeypatch):
    real = rank.fit

    def inf_fit(am, keys, data, *a, **k):
        fr = real(am, keys, data, *a, **k)
        if _is_candidate(am) and "quadratic_damping" in am.added:
            fr = dataclasses.replace(fr, mse_held=float("inf"))
        return fr

    monkeypatch.setattr(rank, "fit", inf_fit)
    d = diagnose(run, baseline="linear", candidates=CANDIDATES).to_dict()
    tested = {t["id"]: t for t in d["candidates_tested"]}
    assert "mean-square error is inf" in tested["quadratic_damping"]["failed"]


def test_an_empty_held_out_set_is_a_clear_error(run, monkeypatch):
    real = rank.prepare

    def no_held(*a, **k):
        data = real(*a, **k)
        for dd in data:
            dd.held = np.zeros_like(dd.held)
        return data

    monkeypatch.setattr(rank, "prepare", no_held)
    with pytest.raises(UserFacingError, match="no held-out samples"):
        diagnose(run, baseline="linear", candidates=CANDIDATES)


def test_a_diverging_null_model_names_the_stage(run, monkeypatch):
    real = rank.fit

    def null_diverges(am, keys, data, *a, **k):
        fr = real(am, keys, data, *a, **k)
        if not getattr(am, "added", []):
            fr = dataclasses.replace(fr, mse_held=float("inf"), nrmse={**fr.nrmse, "nonlinear": float("inf")})
        return fr

    monkeypatch.setattr(rank, "fit", null_diverges)
    with pytest.raises(UserFacingError, match="does not simulate stage.*nonlinear"):
        diagnose(run, baseline="linear", candidates=CANDIDATES)


def test_score_never_raises_on_degenerate_mse():
    r = rank.FitResult(model=None, cost_fit=0.0, mse_held=float("inf"), nrmse={}, nrmse_held=float("nan"), n_held=10,
                       resid_held=np.ones(10))
    ok = dataclasses.replace(r, mse_held=1.0)
    for null, cand in ((r, ok), (ok, r), (dataclasses.replace(ok, mse_held=0.0), ok)):
        s = rank.score(null, cand, 1, 0.1)
        assert s["significant"] is False


def test_a_baseline_force_that_overflows_on_the_recorded_path_leaves_candidates_ranked(run, monkeypatch):
    # stress recording #28 (44 dB): a reconstructed baseline with gamma 3.5e5 integrated z on the
    # measured y' to NaN; the equation-error step and the candidates' scales were NaN and every
    # linear-in-parameter candidate failed ("SVD did not converge", "initial guess outside bounds")
    from recon.diagnosis import locate

    real = locate.model_force

    def overflowing(am, t, y, dy, dt):
        f = np.array(real(am, t, y, dy, dt), float)
        f[f.size // 3:] = np.nan
        return f

    monkeypatch.setattr(locate, "model_force", overflowing)
    d = diagnose(run, baseline="linear", candidates=CANDIDATES).to_dict()
    tested = {t["id"]: t for t in d["candidates_tested"]}
    for cid in CANDIDATES:
        assert "failed" not in tested[cid], tested[cid]
        assert np.isfinite(tested[cid]["held_out_nrmse"])


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

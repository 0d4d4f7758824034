"""The exciter between a recorded drive and the force (recon.exciter; reconstruct --drive): the
law itself, its place in the model JSON, and its recovery on a ground-truth run driven through it."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from recon import ReconSettings, reconstruct
from recon.exciter import drive_force
from recon.model import HystereticModel
from recon.output_error.problem import parameter_keys
from recon.testing.truth import sdof_run, sdof_truth
from shakerlab.errors import UserFacingError
from shakerlab.run_data import Run, Stage

FS = 2000.0


def _tone(f, n=40000, amp=1.0):
    t = np.arange(n) / FS
    return t, amp * np.sin(2 * np.pi * f * t)


def _harmonic(x, t, f):
    return 2.0 / x.size * np.sum(x * np.exp(-2j * np.pi * f * t))


def test_no_exciter_is_the_input_itself_and_a_constant_is_high_passed_to_zero():
    t, u = _tone(7.0)
    assert drive_force(u, 1 / FS) is u
    assert np.all(drive_force(np.full(5000, 0.3), 1 / FS, 0.0, 2 * np.pi * 2.0) == pytest.approx(0.0, abs=1e-12))


def test_the_distortion_makes_a_second_harmonic_and_the_roll_off_leads_the_phase():
    t, u = _tone(5.0)
    f = drive_force(u, 1 / FS, u2=-0.3)
    # sin^2 = (1 - cos 2wt) / 2: a second harmonic of size u2 / 2
    assert abs(_harmonic(f, t, 10.0)) == pytest.approx(0.15, rel=1e-3)
    hp = 2 * np.pi * 1.6
    g = drive_force(u, 1 / FS, hp=hp)[4000:]            # past the start transient (1/hp = 0.1 s)
    ratio = _harmonic(g, t[4000:], 5.0) / _harmonic(u[4000:], t[4000:], 5.0)
    w = 2 * np.pi * 5.0
    assert math.degrees(np.angle(ratio)) == pytest.approx(math.degrees(math.atan2(hp, w)), abs=0.2)
    assert abs(ratio) == pytest.approx(w / math.hypot(w, hp), rel=2e-3)


def test_the_model_json_keeps_the_exciter_and_a_model_without_one_is_unchanged():
    plain = sdof_truth("force")
    d = plain.to_dict()
    assert "drive_u2" not in d["parameters"] and "F = HP" not in d["equation"]
    assert "drive_u2" not in parameter_keys(plain)
    m = HystereticModel.from_dict(dict(d, parameters=dict(d["parameters"], drive_u2=-0.02, drive_hp=9.0)))
    assert (m.drive_u2, m.drive_hp) == (-0.02, 9.0) and parameter_keys(m)[-2:] == ["drive_u2", "drive_hp"]
    back = HystereticModel.from_dict(m.to_dict())
    assert (back.drive_u2, back.drive_hp) == (-0.02, 9.0) and "F = HP(u - 0.02 u^2)" in back.equation()
    with pytest.raises(UserFacingError, match="force excitation"):
        HystereticModel.from_dict(dict(sdof_truth("base").to_dict(), parameters=dict(
            sdof_truth("base").to_dict()["parameters"], drive_u2=0.1)))
    with pytest.raises(UserFacingError, match="drive_hp"):
        HystereticModel.from_dict(dict(d, parameters=dict(d["parameters"], drive_hp="fast")))


@pytest.fixture(scope="module")
def driven_run():
    """sdof_run's force stages, the response made through a known exciter: the recorded force
    channel is the drive (1-2 % second-harmonic distortion at the peak, roll-off at 1.5 Hz)."""
    run, truth = sdof_run("force", snr_db=60.0, duration=6.0, seed=3)
    true = HystereticModel.from_dict(dict(truth.to_dict(), parameters=dict(
        truth.to_dict()["parameters"], drive_u2=-0.012, drive_hp=2 * np.pi * 1.5)))
    rng = np.random.default_rng(5)
    stages = {}
    for n, st in run.stages.items():
        y = true.simulate(st.t, st.settings["truth"]["u"])[0]
        x = y + rng.normal(0.0, np.std(y) / 1000.0, y.size)
        stages[n] = Stage(n, st.t, {"force": st.channels["force"], "x": x}, st.excitation)
    return Run(stages, source="driven through an exciter"), true


@pytest.mark.slow
def test_reconstruct_drive_recovers_the_exciter_and_predicts_better(driven_run):
    run, true = driven_run
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        plain = reconstruct(run, ReconSettings())
        drv = reconstruct(run, ReconSettings(drive=True))
    info = drv.model.provenance["drive_fit"]
    assert info["applied"]
    assert drv.model.drive_u2 == pytest.approx(true.drive_u2, rel=0.15)
    assert drv.model.drive_hp == pytest.approx(true.drive_hp, rel=0.15)
    assert drv.validation["nrmse"] < 0.5 * plain.validation["nrmse"]
    assert "drive_fit" not in plain.model.provenance and plain.model.drive_u2 is None
    d = drv.to_dict()
    assert d["parameters"]["drive_u2"] == drv.model.drive_u2 and d["settings"]["drive"] is True
    assert d["settings"]["drive_fit"]["held_out_nrmse_with"] < d["settings"]["drive_fit"]["held_out_nrmse_without"]
    assert "drive" not in plain.to_dict()["settings"]


def test_drive_is_refused_under_base_excitation():
    run, _ = sdof_run("base", snr_db=60.0, duration=2.0, seed=1)
    with pytest.raises(UserFacingError, match="--drive needs force excitation"):
        reconstruct(run, ReconSettings(drive=True))
    with pytest.raises(UserFacingError, match="drive"):
        ReconSettings(drive="yes")


@pytest.mark.slow
def test_diagnose_names_the_exciter_only_where_there_is_one(driven_run):
    from recon import diagnose

    run, true = driven_run
    plain = HystereticModel.from_dict(dict(true.to_dict(), parameters={
        k: v for k, v in true.to_dict()["parameters"].items() if not k.startswith("drive_")}))
    assert not plain.has_drive
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        found = diagnose(run, baseline=plain, candidates=["exciter_distortion", "coulomb_friction"]).to_dict()
        clean, _ = sdof_run("force", snr_db=60.0, duration=6.0, seed=3)
        none = diagnose(clean, baseline=plain, candidates=["exciter_distortion"]).to_dict()
    assert [m["id"] for m in found["missing_physics"]][:1] == ["exciter_distortion"]
    got = found["missing_physics"][0]["parameters"]
    assert got["drive_u2"]["value"] == pytest.approx(true.drive_u2, rel=0.15)
    assert got["drive_u2"]["interval"][1] < 0
    assert found["fit_after"]["held_out_nrmse"] < found["fit_before"]["held_out_nrmse"]
    # a measured force (the stages as sdof_run records them): nothing to name
    assert none["missing_physics"] == []


@pytest.mark.slow
def test_the_exciter_refit_of_a_model_without_hysteresis_keeps_it_without(driven_run):
    # a simpler kind answered (alpha = 0): the refit leaves its Bouc-Wen parameters at 0 and is kept
    from recon.estimator.drive import fit_drive

    run, true = driven_run
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        result = reconstruct(run, ReconSettings())
    result.model = HystereticModel("force", c_m=true.c_m, k_m=true.K_m, alpha_m=0.0, gamma=0.0, delta=0.0,
                                   inv_m=true.inv_m)
    out = fit_drive(result, run, ReconSettings(drive=True))
    info = out.model.provenance["drive_fit"]
    assert info["applied"], str(info)
    assert (out.model.alpha_m, out.model.gamma, out.model.delta) == (0.0, 0.0, 0.0)
    assert info["held_out_nrmse_with"] < info["held_out_nrmse_without"]
    assert out.model.drive_hp > 0 and out.validation["nrmse"] == pytest.approx(info["held_out_nrmse_with"])

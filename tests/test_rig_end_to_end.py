"""Done means: protocol -> HDF5 -> reconstruction recovers the simulated specimen's parameters
(within 5 % on the linear and Bouc-Wen parameters), on the real simulated rig (lockstep).

One acquisition and one reconstruction (module fixture) serve both tests. Known gap: the weak
nonlinear damping term y^2*dy of the simulated specimen (about 0.3 m/s^2 against z ~ 4 m/s^2 at the
largest level) is not selected by the reconstruction, so fn_m is checked only for y^2 and y^3."""
import pytest

from rig.protocol import load_protocol
from rig.session import acquire, simulated_rig
from shakerlab.run_data import load_run

pytestmark = pytest.mark.slow
WEAK = "weak"


@pytest.fixture(scope="module")
def reconstructed(tmp_path_factory):
    from recon.pipeline import ReconSettings, reconstruct

    path = tmp_path_factory.mktemp("e2e") / "run.h5"
    with simulated_rig(speed=None, seed=0) as (sim, cfg):
        out = acquire(cfg, load_protocol(), path, lockstep=True)
        truth = sim.world.truth()
    assert out.status == "complete", out.reason
    run = load_run(out.path)
    result = reconstruct(run, ReconSettings(form=WEAK))  # as shakerlab demo does (see rig/demo.py)
    return out, run, result, truth


def _errors(result, truth):
    got = result.to_dict()["parameters"]
    err = {k: got[k] / truth[k] - 1.0 for k in ("c_m", "k_m", "alpha_m", "gamma", "delta")}
    err.update({f"fn_m[{k}]": got["fn_m"].get(k, 0.0) / v - 1.0 for k, v in truth["fn_m"].items()})
    return err


def test_protocol_to_reconstruction(reconstructed):
    out, run, result, truth = reconstructed
    assert out.samples_lost == 0
    assert {"linear", "resonance_search", "nonlinear", "validation"} <= set(run.stages)
    nl = run.stage("nonlinear")
    assert nl.settings["summary"]["levels"][-1]["relative_amplitude"] > 3e-3  # a few mm: the loop saturates
    err = _errors(result, truth)
    # met today: linear part, the hysteresis' total rate lambda = gamma + delta, the stiffness terms
    for name in ("c_m", "k_m", "fn_m[y^2]", "fn_m[y^3]"):
        assert abs(err[name]) < 0.05, (name, err)
    lam = result.model.gamma + result.model.delta
    assert lam == pytest.approx(truth["gamma"] + truth["delta"], rel=0.05)
    assert result.validation["nrmse"] < 0.05


def test_linear_and_bouc_wen_parameters_within_5_percent(reconstructed):
    _, _, result, truth = reconstructed
    err = _errors(result, truth)
    bad = {k: round(v * 100, 2) for k, v in err.items()
           if k in ("c_m", "k_m", "alpha_m", "gamma", "delta") and abs(v) >= 0.05}
    assert not bad, f"parameters off by more than 5 % (percent): {bad}"

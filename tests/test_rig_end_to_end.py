"""Done means: protocol -> HDF5 -> reconstruction recovers the simulated specimen's parameters
(within 5 % on the linear and Bouc-Wen parameters and the fn terms, the weak nonlinear damping
term y^2*dy found, no spurious terms), on the real simulated rig (lockstep).

One acquisition and one reconstruction (module fixture) serve the tests. Seed 1: there the
equation-error structure alone (before recon/term_selection.py) missed y^2*dy and kept the
spurious y*dy^2 and y*dy^4 (alpha +5.7 %, gamma -7.6 %). One seed only to keep the suite fast
(measured ~95 s at a load average of ~8 on 2 shared cores); seeds 0..5 are in docs/method.md."""
import pytest

from rig.protocol import load_protocol
from rig.session import acquire, simulated_rig
from shakerlab.runfile.reader import load_run

pytestmark = pytest.mark.slow
WEAK = "weak"


@pytest.fixture(scope="module", params=[1])
def reconstructed(request, tmp_path_factory):
    from recon import ReconSettings, reconstruct

    path = tmp_path_factory.mktemp("e2e") / "run.h5"
    with simulated_rig(speed=None, seed=request.param) as (sim, cfg):
        out = acquire(cfg, load_protocol(), path, lockstep=True)
        truth = sim.world.truth()
    assert out.status == "complete", out.reason
    run = load_run(out.path)
    result = reconstruct(run, ReconSettings(form=WEAK))  # as shakerlab demo does (see workflows/demo.py)
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
    lam = result.model.gamma + result.model.delta
    assert lam == pytest.approx(truth["gamma"] + truth["delta"], rel=0.05)
    assert result.validation["nrmse"] < 0.05


def test_linear_and_bouc_wen_parameters_within_5_percent(reconstructed):
    _, _, result, truth = reconstructed
    err = _errors(result, truth)
    bad = {k: round(v * 100, 2) for k, v in err.items()
           if k in ("c_m", "k_m", "alpha_m", "gamma", "delta") and abs(v) >= 0.05}
    assert not bad, f"parameters off by more than 5 % (percent): {bad}"


def test_fn_structure_exact_and_terms_within_5_percent(reconstructed):
    _, _, result, truth = reconstructed
    got = result.model.fn_m
    assert sorted(got) == sorted(truth["fn_m"]), (got, result.model.provenance.get("term_selection"))
    err = _errors(result, truth)
    bad = {k: round(v * 100, 2) for k, v in err.items() if k.startswith("fn_m") and abs(v) >= 0.05}
    assert not bad, f"fn terms off by more than 5 % (percent): {bad}"

"""Done means: protocol -> HDF5 -> reconstruction recovers the simulated specimen's parameters
(within 5 % on the linear and Bouc-Wen parameters and the fn terms, the weak nonlinear damping
term y^2*dy found, no spurious terms), on the real simulated rig (lockstep).

One acquisition and one reconstruction per protocol (module fixture) serve the tests: the shipped
protocol (generator volts) and rig/base_target_protocol.toml (every amplitude a base displacement
target, closed loop: issue 19), with the same criteria, so the closed-loop experiment must
reconstruct as accurately as the open-loop one. Seed 1: there the equation-error structure alone
(before recon/term_selection.py) missed y^2*dy and kept the spurious y*dy^2 and y*dy^4 (alpha
+5.7 %, gamma -7.6 %), and the base-target run gave y^2*dy +30 % and a validation NRMSE of 3.5 %
until the start state of a stage that begins while the specimen rings was fitted
(recon/simulation/start_state.py, docs/acquisition.md). One seed only to keep the suite fast
(measured ~95 s per protocol at a load average of ~8 on 2 shared cores); seeds 0..5 are in
docs/method.md. The base-target run is recorded by `shakerlab acquire` itself (its embedded
simulated rig, --seed 1), the volts run by the library (rig.session.acquire): both ways in to the
same rig."""
import contextlib
import io
from pathlib import Path

import pytest

from rig.protocol import load_protocol
from rig.session import acquire, simulated_rig
from shakerlab.runfile.reader import load_run

pytestmark = pytest.mark.slow
WEAK = "weak"


PROTOCOLS = {"volts": None, "base_targets": Path(__file__).resolve().parents[1] / "rig" / "base_target_protocol.toml"}


@pytest.fixture(scope="module", params=[("volts", 1), ("base_targets", 1)], ids=lambda p: f"{p[0]}-seed{p[1]}")
def reconstructed(request, tmp_path_factory):
    from recon import ReconSettings, reconstruct
    from shakerlab.cli import main
    from sim_backend.rig import SimulatedRig

    protocol, seed = request.param
    path = tmp_path_factory.mktemp("e2e") / "run.h5"
    if protocol == "volts":
        with simulated_rig(speed=None, seed=seed) as (sim, cfg):
            out = acquire(cfg, load_protocol(PROTOCOLS[protocol]), path, lockstep=True)
            truth = sim.world.truth()
        assert out.status == "complete", out.reason
        lost = out.samples_lost
    else:
        # issue 19's proof, literally: `shakerlab acquire` with the shipped base-target protocol
        with contextlib.redirect_stdout(io.StringIO()) as printed:
            assert main(["acquire", "--sim-speed", "0", "--seed", str(seed), "--protocol",
                         str(PROTOCOLS[protocol]), "-o", str(path)]) == 0
        truth = SimulatedRig(None, speed=None, seed=seed).world.truth()
        lost = 0 if "samples lost: 0" in printed.getvalue() else None
    run = load_run(path)
    result = reconstruct(run, ReconSettings(form=WEAK))  # as shakerlab demo does (see workflows/demo.py)
    return protocol, lost, run, result, truth


def _errors(result, truth):
    got = result.to_dict()["parameters"]
    err = {k: got[k] / truth[k] - 1.0 for k in ("c_m", "k_m", "alpha_m", "gamma", "delta")}
    err.update({f"fn_m[{k}]": got["fn_m"].get(k, 0.0) / v - 1.0 for k, v in truth["fn_m"].items()})
    return err


def _beyond(result, truth, main=None, fn=None) -> dict:
    """{parameter: error in percent} of those off by at least ``main`` (c, k, alpha, gamma, delta)
    or ``fn`` (fn terms); a bound of None leaves that group out."""
    out = {}
    for k, v in _errors(result, truth).items():
        bound = fn if k.startswith("fn_m") else main
        if bound is not None and abs(v) >= bound:
            out[k] = round(v * 100, 2)
    return out


def test_protocol_to_reconstruction(reconstructed):
    protocol, lost, run, result, truth = reconstructed
    assert lost == 0
    if protocol == "base_targets":          # closed loop on the base displacement in every stage
        assert all(run.stage(n).settings["control"] == "base_displacement"
                   for n in ("linear", "resonance_search", "nonlinear", "validation"))
    assert {"linear", "resonance_search", "nonlinear", "validation"} <= set(run.stages)
    nl = run.stage("nonlinear")
    assert nl.settings["summary"]["levels"][-1]["relative_amplitude"] > 3e-3  # a few mm: the loop saturates
    lam = result.model.gamma + result.model.delta
    assert lam == pytest.approx(truth["gamma"] + truth["delta"], rel=0.05)
    assert result.validation["nrmse"] < 0.05


def test_linear_and_bouc_wen_parameters_within_5_percent(reconstructed):
    *_, result, truth = reconstructed
    bad = _beyond(result, truth, main=0.05)
    assert not bad, f"parameters off by more than 5 % (percent): {bad}"


def test_fn_structure_exact_and_terms_within_5_percent(reconstructed):
    *_, result, truth = reconstructed
    got = result.model.fn_m
    assert sorted(got) == sorted(truth["fn_m"]), (got, result.model.provenance.get("term_selection"))
    bad = _beyond(result, truth, fn=0.05)
    assert not bad, f"fn terms off by more than 5 % (percent): {bad}"


def test_as_accurate_closed_loop_as_open_loop(reconstructed):
    # the same bound for both protocols. Measured (bench/sine_control.py --recon 0 1 2): every main
    # parameter within 0.15 %, y^2*dy within 0.53 %, validation NRMSE 0.05 % for both; before the
    # fitted start the base-target run of seed 1 had alpha -2.3 %, gamma +2.8 %, NRMSE 3.5 % (volts 0.6 %)
    *_, result, truth = reconstructed
    bad = _beyond(result, truth, main=0.01)
    assert not bad, f"parameters off by more than 1 % (percent): {bad}"
    assert result.validation["nrmse"] < 0.003, result.validation

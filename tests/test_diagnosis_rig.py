"""Diagnosis on the simulated rig's own physics (sim_backend.physics in-process: signal generator ->
current amplifier -> armature -> specimen, 10 kHz, read at 1 kHz), an integrator independent of
recon's. The baseline is the rig's specimen model without the switched-on effect."""
import numpy as np
import pytest

from recon.diagnosis.diagnose import diagnose
from recon.model import HystereticModel
from shakerlab.run_data import Run, Stage
from sim_backend import physics as ph
from sim_backend.config import load_config

PLAN = (("linear", {"sweep": (5.0, 45.0), "vpp": 0.3}), ("nonlinear", {"freq": 13.0, "vpp": 0.8}),
        ("validation", {"sweep": (8.0, 25.0), "vpp": 0.6}))


def rig_run(effects=None, seed=0, fs=1000.0, duration=4.0, decim=10):
    """Three stages on one session clock, each from rest; the sensors read every ``decim``-th step."""
    cfg = load_config({"effects": dict(effects or {}), "clock": {"sample_rate": fs * decim}})
    P = ph.parameter_vector(cfg, seed)
    n = int(duration * fs * decim)
    stages, step0 = {}, 0
    for name, s in PLAN:
        X = np.zeros(ph.N_X)
        X[ph.X_T] = cfg["amplifier"]["ambient_temperature"]
        G = np.zeros(ph.N_G)
        A = np.zeros(ph.N_A)
        A[ph.A_LIMIT] = cfg["amplifier"]["current_limit"]
        A[ph.A_ENABLE] = A[ph.A_GAIN] = G[ph.G_OUT] = 1.0
        G[ph.G_VPP] = s["vpp"]
        if "sweep" in s:
            G[ph.G_SWEEP] = 1.0
            G[ph.G_F0], G[ph.G_F1] = s["sweep"]
            G[ph.G_TSWEEP] = duration
        else:
            G[ph.G_FREQ] = s["freq"]
        xb, xt = np.zeros(n), np.zeros(n)
        ph.advance(P, X, G, A, step0, n, xb, xt)
        assert A[ph.A_CLIP] == 0.0 and A[ph.A_OC] == 0.0
        t = (step0 + np.arange(n)) / (fs * decim)
        stages[name] = Stage(name, t[::decim], {"x_base": xb[::decim], "x_tip": xt[::decim]})
        step0 += n
    sp = cfg["specimen"]
    model = HystereticModel("base", sp["c_m"], sp["k_m"], sp["alpha_m"], sp["gamma"], sp["delta"], dict(sp["fn_m"]))
    return Run(stages, source="sim_backend.physics in-process"), model


@pytest.mark.parametrize("effects, expected, key, true, tol", [
    ({}, None, None, None, None),
    ({"coulomb_friction": 0.03}, "coulomb_friction", "mu", 0.03, 0.1),
    ({"tip_scale_error": 0.02}, "sensor_scale", "tip_scale", 0.02, 0.25),
    ({"contact_gap": 1.0e-3, "contact_stiffness": 1500.0}, "contact_stiffness", "gap", 1.0e-3, 0.1),
])
@pytest.mark.slow
def test_rig_physics_effect_found(effects, expected, key, true, tol):
    run, model = rig_run(effects, seed=3)
    d = diagnose(run, model).to_dict()
    ids = [m["id"] for m in d["missing_physics"]]
    if expected is None:
        assert ids == [], d["candidates_tested"]
        return
    assert ids and ids[0] == expected, d["candidates_tested"]
    first = d["missing_physics"][0]
    assert abs(first["parameters"][key]["value"] / true - 1) < tol
    assert first["evidence"]["held_out_nrmse_after"] < 0.7 * first["evidence"]["held_out_nrmse_before"]

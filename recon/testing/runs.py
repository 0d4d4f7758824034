"""Recordings of the independent generator (recon/testing/independent.py) as shakerlab runs.

The generator returns plain dicts and knows nothing of shakerlab; this is the bridge the
stress benches (bench/recon_stress.py, bench/diagnose_stress.py) and the tests use to call
recon.reconstruct / recon.diagnose in-process, and to score an estimate against the truth. A stage is built
the way `shakerlab import` builds one from a CSV: time from zero, the original start kept in
``settings["source_t0"]`` (the session clock a stiffness drift runs on).
"""
from __future__ import annotations

import math

import numpy as np

from recon.diagnosis.augmented import AugmentedModel
from recon.model import HystereticModel
from shakerlab.run_data import Run, Stage

KEYS = ("c_m", "k_m", "alpha_m", "gamma", "delta")


def to_run(rec: dict) -> Run:
    stages = {}
    for name, st in rec["stages"].items():
        t = np.asarray(st["t"], float)
        chans = ("x_base", "x_tip") if st["excitation"] == "base" else ("force", "x")
        # a response recorded as velocity or acceleration (add_noise quantity) goes in as v_tip / a_tip
        chans = tuple(next((p + c[1:] for p in "va" if p + c[1:] in st), c) if c not in st else c for c in chans)
        stages[name] = Stage(name, t - t[0], {c: np.asarray(st[c], float) for c in chans}, st["excitation"],
                             settings={"source_t0": float(t[0]), "sampling_jitter": 0.0})
    src = f"independent:seed={rec.get('system_seed', rec.get('seed'))},{rec['protocol']},{rec['effect']}"
    return Run(stages, attrs={"source": "independent generator"}, source=src)


def model_of(params: dict, excitation: str = "base") -> HystereticModel:
    """A HystereticModel from the generator's per-unit-mass truth dict."""
    return HystereticModel.from_dict({"excitation": excitation, "parameters": params,
                                      "provenance": {"source": "recon.testing.independent"}})


def score(model: HystereticModel, truth: dict) -> dict:
    """Relative errors of every per-unit-mass parameter and fn coefficient of the truth (a missed
    term counts 100 %), spurious and missed terms, admissibility of the estimate."""
    err = {k: abs(getattr(model, k) / truth[k] - 1) for k in KEYS if truth[k] != 0}
    for k, v in truth["fn_m"].items():
        err[k] = abs(model.fn_m.get(k, 0.0) / v - 1)
    spur = sorted(set(model.fn_m) - set(truth["fn_m"]))
    miss = sorted(set(truth["fn_m"]) - set(model.fn_m))
    vals = [model.c_m, model.k_m, model.alpha_m, model.gamma, model.delta, *model.fn_m.values()]
    reasons = []
    # a model without hysteresis (alpha = gamma = delta = 0, the simpler models' equivalent-linear
    # and linear kinds) is admissible: it misses the hysteresis, it is not an impossible law
    no_hysteresis = model.alpha_m == 0.0 and model.gamma == 0.0 and model.delta == 0.0
    if no_hysteresis and truth["alpha_m"] != 0:
        miss.append("hysteresis")
    if not all(math.isfinite(v) for v in vals):
        reasons.append("non-finite parameter")
    if not no_hysteresis and not model.alpha_m > 0:
        reasons.append(f"alpha_m = {model.alpha_m:.4g} <= 0")
    if not no_hysteresis and not model.gamma + model.delta > 0:
        reasons.append(f"gamma + delta = {model.gamma + model.delta:.4g} <= 0 (Bouc-Wen does not saturate)")
    if not model.K_m > 0:
        reasons.append(f"K_m = {model.K_m:.4g} <= 0")
    worst = max(err.values()) if err else float("nan")
    return {"errors": err, "worst": worst, "worst_param": max(err, key=err.get) if err else None,
            "spurious": spur, "missed": miss, "exact": not spur and not miss, "inadmissible": reasons}


def true_model(rec: dict):
    """The recording's own truth as the diagnosis's augmented model: the system with its
    concealed effect (and the further ones of a pair, ``rec["also"]``), mapped from the generator's
    SI effect parameters to the per-unit-mass extras of recon.diagnosis.augmented (the two share no
    code; this is the one place that knows both). Returns (model, number of parameters the effects
    add), or None for an effect the augmented model cannot state."""
    e, m = rec["effect_parameters"], rec["system"]["m"]
    exc = "force" if "inv_m" in rec["truth"] else "base"
    truth = dict(rec["truth"], fn_m=dict(rec["truth"]["fn_m"]))
    extras, k = {}, 0
    for effect in [rec["effect"]] + [a[0] for a in rec.get("also", [])]:
        more = _effect_terms(effect, e, m, truth)
        if more is None:
            return None
        extras.update(more[0])
        k += more[1]
    return AugmentedModel(model_of(truth, exc), extras), k


def _effect_terms(effect: str, e: dict, m: float, truth: dict):
    """(extras, parameter count) of one concealed effect; an fn term goes into ``truth`` in place.
    None for an effect the augmented model cannot state."""
    if effect == "coulomb_friction":
        return {"mu": e["Fc"] / m, "v0": e["v_eps"]}, 1
    if effect == "quadratic_damping":
        return {"c2": e["c2"] / m}, 1
    if effect == "amplitude_damping":
        truth["fn_m"]["y^2*dy"] = truth["fn_m"].get("y^2*dy", 0.0) + e["b2"] / m
        return {}, 1
    if effect == "channel_delay":
        return {"delay": e["tau"]}, 1
    if effect == "higher_mode":
        extras = {"w2": e["w2"], "zeta2": e["zeta2"], "phi2": e["phi2"]}
        if e.get("drive2"):
            extras["drive2"] = e["drive2"]
        return extras, 3
    if effect == "parameter_drift":
        return {"drift": e["drift_rate"]}, 1
    if effect == "sensor_scale":
        return {"tip_scale": e["tip_scale"]}, 1
    if effect == "contact_stiffness":
        return {"kc": e["kc"] / m, "gap": e["gap"], "side": e["side"]}, 2
    if effect == "offset":
        truth["fn_m"]["y^0"] = -e["F0"] / m
        return {}, 1
    if effect in ("cubic_stiffness", "quadratic_stiffness"):
        return {}, 1
    if effect == "hysteresis":
        return {}, 3
    return None

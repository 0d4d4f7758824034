"""The exciter step of reconstruct (``ReconSettings(drive=True)``, ``shakerlab reconstruct --drive``).

When the force channel is the exciter's drive (an amplifier voltage) rather than a measured
force, the finished model is refitted by output error on the fitted stages with the
exciter's two parameters free as well (recon.exciter: the force is HP_hp(u + u2 u^2)),
every other parameter free too. The refit is kept when it is admissible and predicts
the held-out (validation) stages better; either way the figures go to the model's provenance
(``drive_fit``). On the real bolted beam (docs/real-data.md) it finds the exciter's distortion
and roll-off that the records show.
"""
from __future__ import annotations

import math
import time

import numpy as np

from recon.estimator.adequacy import assess
from recon.estimator.fallback import NUMERICAL_ERRORS, admissible, held_out_stages, score
from recon.estimator.finish import validate
from recon.estimator.result import ReconResult, ReconSettings
from recon.model import HystereticModel
from recon.output_error.polish import polish
from recon.output_error.problem import parameter_keys
from shakerlab.run_data import Run

HP_START_HZ = 0.1       # the roll-off's start: far below any structural resonance


def fit_drive(result: ReconResult, run: Run, s: ReconSettings) -> ReconResult:
    """``result`` with the exciter fitted (see the module docstring)."""
    model = result.model       # force excitation: recon.estimator.pipeline.reconstruct refuses --drive otherwise
    t0 = time.perf_counter()
    fitted = tuple(n for n in (s.linear_stage, s.nonlinear_stage) if n in run.stages)
    names, held = held_out_stages(run, fitted)
    start = HystereticModel.from_dict(model.to_dict())
    start.drive_u2, start.drive_hp = 0.0, 2 * math.pi * HP_START_HZ
    info = {"fitted_on": list(fitted), "held_out": names, "held_out_is_validation": held,
            "held_out_nrmse_without": score(model, run, names, s.tuning)}
    try:
        items = [start.fit_item(run.stage(n), tuning=s.tuning) for n in fitted]
        # a model without hysteresis (a simpler kind answered) keeps its Bouc-Wen parameters at 0
        free = ([k for k in parameter_keys(start) if k not in ("alpha_m", "gamma", "delta")]
                if model.alpha_m == 0.0 else None)
        new, pinfo = polish(start, items, max_nfev=s.tuning.drive_nfev, free=free, tuning=s.tuning)
        after = score(new, run, names, s.tuning)
    except NUMERICAL_ERRORS as exc:
        info.update(applied=False, failed=f"{type(exc).__name__}: {exc}", seconds=time.perf_counter() - t0)
        model.provenance["drive_fit"] = info
        return result
    info.update(held_out_nrmse_with=after, drive_u2=new.drive_u2, drive_hp=new.drive_hp,
                drive_hp_hz=abs(new.drive_hp) / (2 * math.pi), fit_nrmse_before=pinfo["nrmse_before"],
                fit_nrmse_after=pinfo["nrmse_after"])
    ok = admissible(new, s.tuning)
    keep = bool(pinfo["applied"] and ok and np.isfinite(after) and after < info["held_out_nrmse_without"])
    info["applied"] = keep
    info["seconds"] = time.perf_counter() - t0
    if not keep:
        info["reason"] = ("the refit with the exciter is not admissible" if not ok else
                          "the refit with the exciter does not predict the held-out stages better")
        model.provenance["drive_fit"] = info
        return result
    new.drive_hp = abs(new.drive_hp)
    new.provenance = dict(model.provenance, drive_fit=info)
    result.model = new
    if result.validation:
        result.validation = validate(new, run, tuning=s.tuning)
    result.adequacy = assess(new, result.validation, run, (result.adequacy or {}).get("fallback"), s.tuning)
    return result

"""Validation: NRMSE of a simulated against a measured response, and the hysteretic force a model implies."""
from __future__ import annotations

import numpy as np


def nrmse(y_sim, y_meas) -> float:
    """rms(y_sim - y_meas) / rms(y_meas - mean(y_meas)); inf if the simulation diverged."""
    y_sim = np.asarray(y_sim, float)
    y_meas = np.asarray(y_meas, float)
    if not np.all(np.isfinite(y_sim)):
        return float("inf")
    den = np.sqrt(np.mean((y_meas - y_meas.mean()) ** 2))
    return float(np.sqrt(np.mean((y_sim - y_meas) ** 2)) / den) if den > 0 else float("inf")


def hysteretic_force_from_data(model, y, dy, ddy, u):
    """z/m implied by measured motion under ``model``: g*u - y'' - c y' - k y - fn(y, y')."""
    return model.input_gain * u - ddy - model.c_m * dy - model.k_m * y - model.fn(y, dy)

"""quadratic_damping: dissipation that grows with the square of the velocity, c2 y'|y'|."""
import numpy as np

from recon.diagnosis.candidates.base import Candidate, start_model


def starts(base, ctx):
    m = start_model(base, {"c2": 0.0}, "quadratic_damping")
    # dissipative by definition: c2 >= 0 (a negative c2 would feed energy in at high speed)
    return [(m, ["x:c2"], {"x:c2": 0.01 * ctx["acc_rms"] / ctx["v_rms"] ** 2}, {"x:c2": (0.0, np.inf)})]


def conceal(truth, baseline, strength):
    return {"c2": 30.0 * strength}


CANDIDATE = Candidate(
    "quadratic_damping",
    "dissipation grows with the square of the velocity (air drag, turbulent losses)",
    "term c2 y'|y'| in the restoring force", "extra force c2 y'|y'|", ("x:c2",), starts,
    signature=("state_cluster", "frequency_harmonic", "correlation_tests"), amplitude_dependent=True,
    conceal=conceal, column=lambda am, t, y, dy: dy * np.abs(dy), hysteresis_absorbs=True, kernel=("c2",))

"""offset: a constant force on the specimen (a preload, gravity, a sensor or amplifier offset)."""
import numpy as np

from recon.diagnosis.candidates.base import Candidate, fn_term_starts


def conceal(truth, baseline, strength):
    # a constant force per unit mass that moves the response off its centre by about a tenth of
    # the nonlinear stage's motion at strength 1
    truth.fn_m["y^0"] = 0.3 * strength
    return {}


CANDIDATE = Candidate(
    "offset",
    "a constant force acts on the specimen (a preload, gravity on a tilted rig, a sensor or amplifier "
    "offset): the response sits off its centre by f0 / k",
    "library term y^0 (a constant f0 per unit mass) in fn", "fn gains f0 y^0 (RK4 of the augmented SDOF)",
    ("fn:y^0",), fn_term_starts("y^0", "offset", lambda c: 0.01 * c["acc_rms"]),
    lambda b, c: "y^0" not in b.fn_m,
    signature=("state_cluster",), amplitude_dependent=True, conceal=conceal,
    column=lambda am, t, y, dy: np.ones_like(y))

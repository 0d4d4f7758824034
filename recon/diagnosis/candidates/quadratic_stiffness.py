"""quadratic_stiffness: the spring is stiffer on one side than on the other (a y^2 term)."""
from recon.diagnosis.candidates.base import Candidate, fn_term_starts


def conceal(truth, baseline, strength):
    truth.fn_m["y^2"] = 2.5e5 * strength
    baseline.fn_m.pop("y^2", None)
    return {}


CANDIDATE = Candidate(
    "quadratic_stiffness",
    "the spring is stiffer on one side than on the other: a quadratic (asymmetric) restoring-force term",
    "library term y^2 in fn", "fn gains a_2 y^2", ("fn:y^2",),
    fn_term_starts("y^2", "quadratic_stiffness", lambda c: 0.01 * c["acc_rms"] / c["y_rms"] ** 2),
    lambda b, c: "y^2" not in b.fn_m,
    signature=("state_beyond_displacement", "frequency_harmonic"), amplitude_dependent=True, conceal=conceal,
    column=lambda am, t, y, dy: y ** 2)

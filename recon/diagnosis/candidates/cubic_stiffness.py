"""cubic_stiffness: the spring stiffens (or softens) with amplitude symmetrically (a y^3 term)."""
from recon.diagnosis.candidates.base import Candidate, fn_term_starts


def conceal(truth, baseline, strength):
    truth.fn_m["y^3"] = 8.0e7 * strength
    baseline.fn_m.pop("y^3", None)
    return {}


CANDIDATE = Candidate(
    "cubic_stiffness",
    "the spring stiffens (or softens) with amplitude symmetrically: a cubic restoring-force term",
    "library term y^3 in fn", "fn gains a_3 y^3 (RK4 of the augmented SDOF)", ("fn:y^3",),
    fn_term_starts("y^3", "cubic_stiffness", lambda c: 0.01 * c["acc_rms"] / c["y_rms"] ** 3),
    lambda b, c: "y^3" not in b.fn_m,
    signature=("state_beyond_displacement", "frequency_harmonic"), amplitude_dependent=True, conceal=conceal,
    column=lambda am, t, y, dy: y ** 3)

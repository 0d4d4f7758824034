"""amplitude_damping: damping that grows with the displacement amplitude (a y^2 y' term)."""
from recon.diagnosis.candidates.base import Candidate, fn_term_starts


def check(m, data) -> list[str]:
    b = m.baseline.fn_m.get("y^2*dy", 0.0)
    return [f"negative amplitude-dependent damping {b:.4g} (feeds energy in)"] if b < 0 else []


def conceal(truth, baseline, strength):
    truth.fn_m["y^2*dy"] = 3.0e6 * strength
    baseline.fn_m.pop("y^2*dy", None)
    return {}


CANDIDATE = Candidate(
    "amplitude_damping",
    "the damping grows with the displacement amplitude (micro-slip in bolted or clamped joints): "
    "a y^2 y' dissipation term",
    "library term y^2*dy in fn", "fn gains b y^2 y' (RK4 of the augmented SDOF)", ("fn:y^2*dy",),
    fn_term_starts("y^2*dy", "amplitude_damping",
                   lambda c: 0.01 * c["acc_rms"] / (c["y_rms"] ** 2 * c["v_rms"])),
    lambda b, c: "y^2*dy" not in b.fn_m,
    check=check, signature=("state_cluster", "frequency_harmonic"), amplitude_dependent=True, conceal=conceal,
    column=lambda am, t, y, dy: y ** 2 * dy, hysteresis_absorbs=True)

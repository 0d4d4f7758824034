"""parameter_drift: the stiffness changes slowly during the session, k (1 + drift t)."""
from recon.diagnosis.candidates.base import Candidate, start_model


def starts(base, ctx):
    m = start_model(base, {"drift": 0.0}, "parameter_drift")
    return [(m, ["x:drift"], {"x:drift": 0.01 / max(ctx["t_end"], 1e-9)}, {})]


def check(m, data) -> list[str]:
    """A drift of more than half the stiffness over the session is not a slow change."""
    t_end = max(float(d.t[-1]) for d in data)
    if abs(m.get("drift")) * t_end > 0.5:
        return [f"stiffness drift of {m.get('drift') * t_end:+.0%} over the session"]
    return []


def conceal(truth, baseline, strength):
    return {"drift": 5e-4 * strength}


CANDIDATE = Candidate(
    "parameter_drift",
    "the stiffness changes slowly during the session (temperature, fatigue, settling)",
    "model change: k(t) = k (1 + drift t), t = recorded stage time",
    "k_m varies linearly with the recorded time", ("x:drift",), starts,
    check=check, signature=("time_trend", "time_segment"), conceal=conceal,
    column=lambda am, t, y, dy: am.baseline.k_m * t * y, kernel=("drift",))

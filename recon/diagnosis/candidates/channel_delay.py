"""channel_delay: the displacement channel lags the input channel by d."""
from recon.diagnosis.candidates.base import Candidate, start_model


def starts(base, ctx):
    # the displacement reading lags the input reading (d >= 0; a lead is not a sensor delay); the
    # fit starts inside the bound, a quarter sample, not on it
    m = start_model(base, {"delay": 0.25 * ctx["dt"]}, "channel_delay")
    return [(m, ["x:delay"], {"x:delay": ctx["dt"]}, {"x:delay": (0.0, 20 * ctx["dt"])})]


def check(m, data) -> list[str]:
    return [f"negative delay {m.get('delay'):.4g} s"] if m.get("delay") < 0 else []


def conceal(truth, baseline, strength):
    return {"delay": 2.5e-4 * strength}


CANDIDATE = Candidate(
    "channel_delay",
    "the two sensors are not sampled at the same instant: the displacement channel lags the input channel",
    "model change: output y_rec(t) = x_tip(t - d) - x_base(t) (force: y(t - d))",
    "simulate, then delay the displacement channel by d (linear interpolation)", ("x:delay",), starts,
    check=check, signature=("channel",), conceal=conceal)

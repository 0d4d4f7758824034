"""contact_stiffness: a one-sided stop beyond a gap, kc max(s y - gap, 0)."""
import numpy as np

from recon.diagnosis.candidates.base import Candidate, start_model


def starts(base, ctx):
    out = []
    for side, ymax in ((1.0, ctx["y_max_pos"]), (-1.0, ctx["y_max_neg"])):
        for frac in (0.35, 0.55, 0.75):
            m = start_model(base, {"kc": 0.0, "gap": frac * ymax, "side": side}, "contact_stiffness")
            out.append((m, ["x:kc", "x:gap"], {"x:kc": 0.1 * abs(base.K_m) + 1.0, "x:gap": 0.1 * ymax},
                        {"x:kc": (0.0, np.inf), "x:gap": (0.0, 0.98 * ymax)}))
    return out


def check(m, data) -> list[str]:
    """The gap inside the recorded range on its side with at least 10 samples beyond it; kc > 0."""
    why = []
    side = 1.0 if m.get("side") >= 0 else -1.0
    reach = float(max(np.max(side * d.displacement) for d in data))
    beyond = int(sum(np.sum(side * d.displacement > m.get("gap")) for d in data))
    if not 0.0 < m.get("gap") < reach or beyond < 10:
        why.append(f"gap {m.get('gap'):.4g} m outside the recorded displacement range (0, {reach:.4g}) on side "
                   f"{side:+.0f} ({beyond} samples beyond it)")
    if m.get("kc") <= 0:
        why.append(f"contact stiffness kc = {m.get('kc'):.4g} <= 0")
    return why


def conceal(truth, baseline, strength):
    return {"kc": 1500.0 * strength, "gap": 0.6e-3}


def column(am, t, y, dy):
    s = 1.0 if am.get("side") >= 0 else -1.0
    return s * np.maximum(s * y - am.get("gap"), 0.0)


CANDIDATE = Candidate(
    "contact_stiffness",
    "one-sided contact: beyond a gap the specimen touches a stop and gets stiffer on that side only",
    "term kc max(s*y - gap, 0) (s = +1 or -1) in the restoring force",
    "extra force kc (y - gap) when y is beyond the gap on side s", ("x:kc", "x:gap", "x:side"), starts,
    check=check, signature=("state_beyond_displacement", "frequency_harmonic"), amplitude_dependent=True,
    conceal=conceal, screen_keys=1, column=column, fit_each="side", even_stiffness_absorbs=True,
    kernel=("kc", "gap", "side"))

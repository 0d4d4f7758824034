"""higher_mode: a second resonance the one-mode model leaves out, seen in the displacement reading."""
import math

from recon.diagnosis.candidates.base import Candidate, start_model

# the range a second mode's damping ratio is fitted in
ZETA2_RANGE = (0.001, 0.3)
# a second mode nearer the fundamental than this share of its frequency is refused (check)
MODE_APART = 0.2


def starts(base, ctx):
    # input-driven starts (a structural mode), then one riding on the measured point (drive2 = 1,
    # driven by its absolute acceleration); which of the two is kept fixed in the fit: started on
    # its bound, a free drive2 in [0, 1] stops the trust-region fit at its first step
    out = []
    points = [(f, phi, 0.0) for f, phi in ctx["mode_starts"][:3]]
    above = ctx.get("mode_start_above_band")
    if above is not None and all(abs(above - f) > 0.1 * f for f, _, _ in points):
        points.append((above, 0.0, 0.0))
    points += [(f, phi, 1.0) for f, phi in ctx.get("mode_starts_point", [])[:1]]
    w1 = math.sqrt(max(base.K_m, 0.0))
    for f, phi, drive in points:
        w = 2 * math.pi * f
        m = start_model(base, {"w2": w, "zeta2": 0.02, "phi2": phi, "drive2": drive}, "higher_mode")
        out.append((m, ["x:phi2", "x:w2", "x:zeta2"], {"x:phi2": 0.01, "x:w2": 0.02 * w, "x:zeta2": 0.01},
                    {"x:w2": mode_range(w, w1), "x:zeta2": ZETA2_RANGE}))
    return out


def mode_range(w: float, w1: float) -> tuple[float, float]:
    """The range a second mode started at ``w`` is fitted in: within a factor 2 of its start, and on
    the start's side of the band MODE_APART around the fundamental ``w1``, where a fitted mode is
    refused (check). A fit that may cross into that band settles beside the fundamental and takes
    up the baseline's error there instead of the mode it started at, and is then refused. A start
    inside the band keeps the plain range."""
    lo, hi = 0.5 * w, 2.0 * w
    if w1 > 0 and w > (1 + MODE_APART) * w1:
        lo = max(lo, (1 + MODE_APART) * w1)
    elif w1 > 0 and w < (1 - MODE_APART) * w1:
        hi = min(hi, (1 - MODE_APART) * w1)
    return lo, hi


def check(m, data) -> list[str]:
    """A mode apart from the fundamental: a separate resonance. Two resonances are separate when
    their half-power bands (the fundamental's c_m wide, the mode's 2 zeta2 w2) do not overlap; a
    broad 'mode' whose band reaches the fundamental's is a change to the fundamental's own
    damping and stiffness, not a second resonance. A damping ratio on an end of its range is not
    refused: one-tone stages drive the mode off its resonance, where the record shows only the
    mode's tail (its static share and phase at the drive frequencies), so it leaves the damping and
    frequency free along a valley and a fit ends where its range does. Whether such a mode explains
    the record is the held-out comparison's question, as for every candidate (the other effects it
    can stand in for, a delay or a tip scale, compete with it there); its entry marks the
    parameters held on their bounds as 'at_bound'."""
    why = []
    w1 = math.sqrt(max(m.baseline.K_m, 0.0))
    w2, zeta2 = m.get("w2"), m.get("zeta2")
    # (a fit held on that band's edge by its bound, mode_range, is refused with it)
    if abs(w2 - w1) < (MODE_APART + 0.01) * w1:
        why.append(f"second mode at {w2 / (2 * math.pi):.4g} Hz is within {MODE_APART:.0%} of the "
                   f"fundamental {w1 / (2 * math.pi):.4g} Hz")
    elif half_power_bands_overlap(w1, max(m.baseline.c_m, 0.0), w2, zeta2):
        lo, hi = w2 * (1 - zeta2), w2 * (1 + zeta2)
        why.append(f"second mode at {w2 / (2 * math.pi):.4g} Hz damped {zeta2:.3g}: its half-power band "
                   f"{lo / (2 * math.pi):.4g}-{hi / (2 * math.pi):.4g} Hz reaches the fundamental's at "
                   f"{w1 / (2 * math.pi):.4g} Hz, so it is not a separate resonance")
    return why


def half_power_bands_overlap(w1: float, c_m: float, w2: float, zeta2: float) -> bool:
    """Whether a mode at ``w2`` damped ``zeta2`` and the fundamental at ``w1`` (damping per unit
    mass ``c_m``, its half-power band c_m wide) share frequencies within their half-power bands,
    so that neither shows as a peak of its own."""
    if w2 >= w1:
        return w2 * (1 - zeta2) <= w1 + 0.5 * c_m
    return w2 * (1 + zeta2) >= w1 - 0.5 * c_m


def conceal(truth, baseline, strength):
    return {"w2": 2 * math.pi * 55.0, "zeta2": 0.02, "phi2": 0.25 * strength}


CANDIDATE = Candidate(
    "higher_mode",
    "a second resonance the one-mode model leaves out shows up in the displacement reading",
    "model change: extra mode q'' + 2 zeta w q' + w^2 q = g u - drive2 a, reading += phi q "
    "(a: the measured point's absolute acceleration beyond the input's)",
    "a second-order oscillator driven by the input (drive2 = 0, a structural mode) or by the measured "
    "point's motion (drive2 = 1, a resonance riding on it), added to the displacement output",
    ("x:phi2", "x:w2", "x:zeta2"), starts,
    check=check, signature=("frequency_resonance", "frequency_band_at_input"), conceal=conceal,
    screen_keys=1, fit_each="drive2", kernel=("w2", "zeta2", "drive2", "gu2"))

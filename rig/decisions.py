"""Decisions the stage plans take from measured responses: has the nonlinear stage reached
nonlinearity, and how far may a level be scaled within the rig's limits (open and closed loop)."""
from __future__ import annotations

from rig import analysis


def nonlinearity_reached(p: dict, first: analysis.Response, r: analysis.Response) -> list[str]:
    """Which stop criteria this response meets (empty list: keep raising)."""
    reasons = []
    if r.thd > p["thd_threshold"]:
        reasons.append(f"THD {r.thd * 100:.1f} % > {p['thd_threshold'] * 100:g} %")
    gain_change = r.gain / first.gain - 1.0
    if abs(gain_change) > p["gain_change_threshold"]:
        reasons.append(f"gain changed by {gain_change * 100:+.1f} % (threshold {p['gain_change_threshold'] * 100:g} %)")
    if first.loss_factor > 0:
        loss_change = r.loss_factor / first.loss_factor - 1.0
        if abs(loss_change) > p["loss_change_threshold"]:
            reasons.append(f"loop loss factor changed by {loss_change * 100:+.1f} % "
                           f"(threshold {p['loss_change_threshold'] * 100:g} %)")
    return reasons


def allowed_scale(limits: dict, r: analysis.Response) -> tuple[float, str]:
    """How much the amplitude may still grow before the response (extrapolated linearly)
    reaches ``soft_limit_fraction`` of a displacement limit; and which limit that is."""
    frac = limits["soft_limit_fraction"]
    best, which = float("inf"), ""
    for key, peak in (("max_base_displacement_m", r.peak_base), ("max_tip_displacement_m", r.peak_tip)):
        if peak > 0 and frac * limits[key] / peak < best:
            best, which = frac * limits[key] / peak, key
    return best, which

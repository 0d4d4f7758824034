"""Decisions the stage plans take from measured responses: where the resonance search measures
and where the resonance is, is a level's response steady, has the
nonlinear stage reached nonlinearity, and how far may a level be scaled within the rig's limits
(open and closed loop)."""
from __future__ import annotations

import numpy as np

from rig import analysis
from rig.messages import Acquire, Log


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


def next_level(level: float, top: float, step_factor: float, limits: dict, r: analysis.Response,
               describe_top: str) -> tuple[float | None, str | None, str | None]:
    """The nonlinear stage's next excitation level (drive Vpp, or base target in m: the rule is the
    same): ``(next level, None, key)`` where ``key`` names the sensor limit that cut the step (or
    None), or ``(None, stop reason, None)`` when the stage stops raising. ``describe_top`` names the
    level's upper bound in the stop reasons ("amplitude limit 6 Vpp")."""
    if level >= top * (1 - 1e-9):
        return None, f"{describe_top} reached without clear nonlinearity", None
    nxt = min(level * step_factor, top)
    if nxt < 1.1 * level:  # the bound is within 10 % of this level: this is the last level
        return None, f"{describe_top} reached (within 10 %) without clear nonlinearity", None
    scale, key = allowed_scale(limits, r)
    if nxt > level * scale:
        # approach the limit: a last, smaller step if it is still worth one
        if scale < 1.1:
            frac = limits["soft_limit_fraction"]
            return None, (f"limit: the next level would exceed {frac:g} x {key} "
                          f"({limits[key] * 1e3:g} mm, extrapolated from this level)"), None
        return level * scale, None, key
    return nxt, None, None


def settled_response(p: dict, f: float, r: analysis.Response, before: analysis.Response | None, label: str):
    """Record further ``analysis_s`` windows at the same drive until two in a row agree
    (``analysis.gain_change`` <= ``settle_tolerance``) or ``settle_max_s`` more has passed; returns
    (the last window's response, its record). A level is then judged on its steady response, not on
    the transient of the step to it: with little damping the transient outlasts a fixed dwell, and
    its free oscillation at the resonance reads as distortion and as a change of gain and loss
    factor (stress seed 41, a 5.8 Hz specimen at 1 % damping: 6.5 % distortion on its first level,
    under 0.1 % once settled)."""
    change = analysis.gain_change(before, r) if before is not None else float("inf")
    waited = 0.0
    while change > p["settle_tolerance"] and waited + p["analysis_s"] <= p["settle_max_s"] * (1 + 1e-9):
        w = yield Acquire(p["analysis_s"])
        waited += p["analysis_s"]
        new = analysis.response(w.x_base, w.x_tip, w.fs, f)
        change, r = analysis.gain_change(r, new), new
    settled = change <= p["settle_tolerance"]
    if not settled:
        yield Log("warning", f"{label}: the response did not settle within {p['settle_max_s']:g} s more "
                             f"(gain change {change:.2%} between the last two windows, tolerance "
                             f"{p['settle_tolerance']:.2%}); judged as it is")
    return r, {"settled": settled, "settle_change": change, "settle_extra_s": waited}


def search_grid(p: dict, table: list, measure):
    """The resonance search's frequencies, as a plan: a geometric grid from start_hz to stop_hz,
    then refine_steps frequencies between the neighbours of the largest transmissibility (none
    measured twice). ``measure(freqs)`` is the plan that measures them, one response appended to
    ``table`` per frequency (open or closed loop)."""
    coarse = np.geomspace(p["start_hz"], p["stop_hz"], p["steps"])
    yield from measure(coarse)
    i = int(np.argmax([r.transmissibility for r in table]))
    if p["refine_steps"] > 0:
        lo = coarse[max(i - 1, 0)]
        hi = coarse[min(i + 1, coarse.size - 1)]
        fine = np.geomspace(lo, hi, p["refine_steps"] + 2)[1:-1]
        done = np.array([r.frequency_hz for r in table])
        fine = [f for f in fine if np.min(np.abs(done / f - 1)) > 1e-6]  # skip frequencies already measured
        yield from measure(fine)


def resonance_found(table: list, held: str = "") -> tuple[float, Log, dict]:
    """The first resonance from the search's table: its frequency, the log line that reports it
    (a warning where it sits at the edge of the searched range) and the stage's summary.
    ``held``: what was held constant, for the log line."""
    freqs = [r.frequency_hz for r in table]
    trans = [r.transmissibility for r in table]
    f_res = analysis.peak_frequency(freqs, trans)
    at_edge = f_res <= min(freqs) * 1.0001 or f_res >= max(freqs) * 0.9999
    peak = max(table, key=lambda r: r.transmissibility)
    msg = (f"resonance search{held}: first resonance at {f_res:.3f} Hz (tip/base amplitude ratio "
           f"{peak.transmissibility:.2f}, phase {peak.phase_deg:.0f} deg)")
    log = Log("warning" if at_edge else "info",
              msg + (" AT THE EDGE OF THE SEARCHED RANGE: widen start_hz/stop_hz" if at_edge else ""))
    summary = {
        "resonance_hz": f_res, "at_edge": at_edge,
        "frequencies_hz": freqs, "transmissibility": trans,
        "phase_deg": [r.phase_deg for r in table],
        "base_amplitude_m": [r.base_amplitude for r in table],
    }
    return f_res, log, summary

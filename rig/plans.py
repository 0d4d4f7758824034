"""The protocol as a plan: a generator of messages (see :mod:`rig.messages`).

:func:`protocol_plan` turns a validated :class:`~rig.protocol.Protocol` into
the stage sequence; each stage is its own small plan so tests can run one
stage alone. The plans decide from measured data (the resonance search finds
the frequency the nonlinear stage uses; the nonlinear stage raises the
amplitude until the response is clearly nonlinear), but they never talk to
an instrument: the runner does, and supervises every block.
"""
from __future__ import annotations

from rig import analysis, control_plans
from rig.decisions import next_level, nonlinearity_reached, resonance_found, search_grid, settled_response
from rig.messages import (PRE_TRIGGER_S, Acquire, BeginStage, Checkpoint, CheckSetpoint, EndStage, Log, Ramp, Rest,
                          SetFrequency)


class PlanContext:
    """What the stages learn and pass on (resonance, final amplitude), plus the limits."""

    def __init__(self, limits: dict):
        self.limits = limits
        self.resonance_hz: float | None = None
        self.nonlinear_vpp: float | None = None
        self.nonlinear_base_m: float | None = None   # final base target of a closed-loop nonlinear stage
        self.results: dict = {}


def linear_stage(p: dict, settle_s: float, pre_trigger_s: float = PRE_TRIGGER_S):
    yield Rest(settle_s)
    yield BeginStage("linear", {"kind": "harmonic", **p}, pre_trigger_s=pre_trigger_s)
    yield SetFrequency(p["frequency_hz"])
    yield Ramp(p["amplitude_vpp"], "linear")
    window = yield Acquire(p["duration_s"])
    r = analysis.response(window.x_base, window.x_tip, window.fs, p["frequency_hz"])
    yield Log("info", f"linear stage: relative amplitude {r.relative_amplitude * 1e3:.3f} mm, "
                      f"THD {r.thd * 100:.2f} % at {p['frequency_hz']:g} Hz")
    yield EndStage({"response": r.to_dict()})
    return r


def resonance_search(p: dict, settle_s: float, ctx: PlanContext, pre_trigger_s: float = PRE_TRIGGER_S):
    """Stepped sine over a geometric grid, then a fine grid between the peak's neighbours."""
    yield Rest(settle_s)
    yield BeginStage("resonance_search", {"kind": "stepped_sine", **p}, pre_trigger_s=pre_trigger_s)
    table = []

    def measure(freqs):
        for f in freqs:
            yield Checkpoint()
            yield SetFrequency(float(f))
            if not table:
                yield Ramp(p["amplitude_vpp"], "search")
            if p["settle_s"] > 0:
                yield Acquire(p["settle_s"])
            w = yield Acquire(p["measure_s"])
            r = analysis.response(w.x_base, w.x_tip, w.fs, float(f))
            table.append(r)

    yield from search_grid(p, table, measure)
    f_res, log, summary = resonance_found(table)
    ctx.resonance_hz = f_res
    yield log
    yield EndStage(summary)
    return f_res


def nonlinear_stage(p: dict, settle_s: float, ctx: PlanContext, pre_trigger_s: float = PRE_TRIGGER_S):
    """Raise the amplitude step by step near the resonance until clear nonlinearity or a limit."""
    f = p["frequency_hz"] if p["frequency_hz"] is not None else p["frequency_factor"] * ctx.resonance_hz
    vmax = p["max_vpp"]
    yield CheckSetpoint(vmax, f, f"[nonlinear] drive frequency {drive_origin(p, ctx)}, levels up to max_vpp")
    yield Rest(settle_s)
    yield BeginStage("nonlinear", {"kind": "stepped_amplitude", **p, "drive_frequency_hz": f,
                                   "resonance_hz": ctx.resonance_hz}, pre_trigger_s=pre_trigger_s)
    yield SetFrequency(f)
    levels, stop_reason, first = [], None, None
    vpp = p["start_vpp"]
    while True:
        yield Checkpoint()
        yield Ramp(vpp, f"level {len(levels) + 1}")
        pre = None
        if p["dwell_s"] > p["analysis_s"]:
            pre = yield Acquire(p["dwell_s"] - p["analysis_s"])
        w = yield Acquire(p["analysis_s"])
        r = analysis.response(w.x_base, w.x_tip, w.fs, f)
        settle = {}
        if p["settle_tolerance"] > 0:
            before = analysis.response(pre.x_base, pre.x_tip, pre.fs, f) if pre is not None else None
            r, settle = yield from settled_response(p, f, r, before, f"level {len(levels) + 1}")
        first = first or r
        reasons = nonlinearity_reached(p, first, r) if len(levels) else []
        levels.append({"amplitude_vpp": vpp, **r.to_dict(), **settle, "criteria": reasons})
        yield Log("info", f"nonlinear level {len(levels)}: {vpp:.3f} Vpp, relative amplitude "
                          f"{r.relative_amplitude * 1e3:.3f} mm, THD {r.thd * 100:.2f} %, gain {r.gain:.3f}, "
                          f"loss factor {r.loss_factor:.4f}")
        if reasons:
            stop_reason = "nonlinearity: " + "; ".join(reasons)
            break
        nxt, stop_reason, key = next_level(vpp, vmax, p["step_factor"], ctx.limits, r,
                                           f"amplitude limit {vmax:g} Vpp")
        if nxt is None:
            break
        if key is not None:
            yield Log("info", f"next level {nxt:.3f} Vpp: limited to {ctx.limits['soft_limit_fraction']:g} x {key}")
        vpp = nxt
    yield Log("info" if stop_reason.startswith("nonlinearity") else "warning",
              f"nonlinear stage stops raising at {vpp:.3f} Vpp: {stop_reason}")
    if p["hold_s"] > 0:
        yield Acquire(p["hold_s"])
    ctx.nonlinear_vpp = vpp
    yield EndStage({"drive_frequency_hz": f, "final_vpp": vpp, "stop_reason": stop_reason,
                    "nonlinear": stop_reason.startswith("nonlinearity"), "levels": levels})
    return vpp


def drive_origin(p: dict, ctx: PlanContext) -> str:
    """How a stage's drive frequency was set (for refusals)."""
    if p["frequency_hz"] is not None:
        return "(frequency_hz)"
    return f"(frequency_factor {p['frequency_factor']:g} x the resonance found, {ctx.resonance_hz:g} Hz)"


def validation_stage(v: dict, settle_s: float, ctx: PlanContext, pre_trigger_s: float = PRE_TRIGGER_S):
    f = v["frequency_hz"] if v["frequency_hz"] is not None else v["frequency_factor"] * ctx.resonance_hz
    if v["amplitude_vpp"] is not None:
        vpp, amplitude_origin = v["amplitude_vpp"], "amplitude_vpp"
    else:
        vpp = v["amplitude_fraction"] * ctx.nonlinear_vpp
        amplitude_origin = f"amplitude_fraction {v['amplitude_fraction']:g} x the nonlinear final level " \
                           f"{ctx.nonlinear_vpp:g} Vpp"
    yield CheckSetpoint(vpp, f, f"[{v['name']}] drive {vpp:g} Vpp ({amplitude_origin}) at {f:g} Hz "
                                f"{drive_origin(v, ctx)}")
    yield Rest(settle_s)
    yield BeginStage(v["name"], {"kind": "harmonic", **v, "drive_frequency_hz": f, "drive_vpp": vpp},
                     pre_trigger_s=pre_trigger_s)
    yield SetFrequency(f)
    yield Ramp(vpp, v["name"])
    w = yield Acquire(v["duration_s"])
    r = analysis.response(w.x_base, w.x_tip, w.fs, f)
    yield EndStage({"response": r.to_dict()})
    return r


def protocol_plan(protocol, limits: dict, ctx: PlanContext | None = None):
    """The whole protocol: linear, resonance search, nonlinear, validation stages."""
    ctx = ctx or PlanContext(limits)
    settle = protocol["run"]["settle_s"]
    pre = protocol["run"]["pre_trigger_s"]   # recorded rest at the start of every stage
    yield Log("info", f"protocol {protocol.source}")
    cp = control_plans  # stages given in base displacement targets run closed loop (rig.sine_control)
    ctx.results["linear"] = yield from (cp.linear_stage if cp.uses_base_targets(protocol["linear"])
                                        else linear_stage)(protocol["linear"], settle, pre)
    yield Checkpoint()
    if protocol["resonance_search"]["enabled"]:
        ctx.results["resonance_hz"] = yield from (
            cp.resonance_search if cp.uses_base_targets(protocol["resonance_search"])
            else resonance_search)(protocol["resonance_search"], settle, ctx, pre)
        yield Checkpoint()
    ctx.results["nonlinear_vpp"] = yield from (cp.nonlinear_stage if cp.uses_base_targets(protocol["nonlinear"])
                                               else nonlinear_stage)(protocol["nonlinear"], settle, ctx, pre)
    for v in protocol.validation:
        yield Checkpoint()
        yield from (cp.validation_stage if cp.validation_uses_base_targets(v, ctx)
                    else validation_stage)(v, settle, ctx, pre)
    yield Rest(0.0)
    return ctx


"""The protocol's stages with amplitudes given as base-displacement targets (closed loop).

Each stage here is the closed-loop twin of the open-loop stage of the same name in
:mod:`rig.plans`: the same steps, decisions and summaries, but every amplitude is a
fundamental peak amplitude of the base motion that the sine controller
(:mod:`rig.sine_control`, through :class:`rig.messages.ControlSine`) holds, instead of a
generator voltage. :func:`rig.plans.protocol_plan` picks, stage by stage, the open-loop plan
(volts) or this one (``base_amplitude_mm``, ``start_base_mm``/``max_base_mm``).

Response limits (notching): every stage may give ``max_tip_mm`` and/or
``max_relative_mm``; the controller then lowers the base target so the tip (or relative)
displacement's fundamental stays at the ceiling, and logs it.
"""
from __future__ import annotations

from rig import analysis
from rig.decisions import next_level, nonlinearity_reached, resonance_found, search_grid, settled_response
from rig.messages import PRE_TRIGGER_S, BeginStage, Checkpoint, ControlSine, EndStage, Log, Rest, SetFrequency
from shakerlab.errors import UserFacingError

MM = 1e-3


def uses_base_targets(p: dict) -> bool:
    return p.get("base_amplitude_mm") is not None or p.get("start_base_mm") is not None


def _ceilings(p: dict) -> dict:
    return {"max_tip_m": p["max_tip_mm"] * MM if p.get("max_tip_mm") is not None else None,
            "max_relative_m": p["max_relative_mm"] * MM if p.get("max_relative_mm") is not None else None}


def _control_summary(res) -> dict:
    return {"control": res.to_dict()}


def linear_stage(p: dict, settle_s: float, pre_trigger_s: float = PRE_TRIGGER_S):
    target = p["base_amplitude_mm"] * MM
    yield Rest(settle_s)
    yield BeginStage("linear", {"kind": "harmonic", "control": "base_displacement", **p}, pre_trigger_s=pre_trigger_s)
    yield SetFrequency(p["frequency_hz"])
    res = yield ControlSine(target, p["duration_s"], label="linear", **_ceilings(p))
    w = res.window
    r = analysis.response(w.x_base, w.x_tip, w.fs, p["frequency_hz"])
    yield Log("info", f"linear stage: base {res.achieved_m * 1e3:.4f} mm (target {target * 1e3:.4g} mm, "
                      f"{res.error_db:+.2f} dB) at {res.vpp:.3f} Vpp, relative amplitude "
                      f"{r.relative_amplitude * 1e3:.3f} mm, THD {r.thd * 100:.2f} % at {p['frequency_hz']:g} Hz")
    yield EndStage({"response": r.to_dict(), **_control_summary(res)})
    return r


def resonance_search(p: dict, settle_s: float, ctx, pre_trigger_s: float = PRE_TRIGGER_S):
    """Stepped sine at a constant base amplitude (closed loop at every frequency)."""
    target = p["base_amplitude_mm"] * MM
    yield Rest(settle_s)
    yield BeginStage("resonance_search", {"kind": "stepped_sine", "control": "base_displacement", **p},
                     pre_trigger_s=pre_trigger_s)
    table, controls = [], []

    def measure(freqs):
        for f in freqs:
            yield Checkpoint()
            yield SetFrequency(float(f))
            res = yield ControlSine(target, p["settle_s"] + p["measure_s"], analysis_s=p["measure_s"],
                                    label=f"search {float(f):.4g} Hz", **_ceilings(p))
            w = res.window
            table.append(analysis.response(w.x_base, w.x_tip, w.fs, float(f)))
            controls.append(res)

    yield from search_grid(p, table, measure)
    f_res, log, summary = resonance_found(table, f" (base held at {target * 1e3:.4g} mm)")
    ctx.resonance_hz = f_res
    yield log
    yield EndStage({
        **summary,
        "drive_vpp": [c.vpp for c in controls],
        "control_error_db": [c.error_db for c in controls],
    })
    return f_res


def nonlinear_stage(p: dict, settle_s: float, ctx, pre_trigger_s: float = PRE_TRIGGER_S):
    """Raise the base target level by level near the resonance (closed loop) until clear
    nonlinearity, a response ceiling, a limit, or a level the generator cannot reach."""

    f = p["frequency_hz"] if p["frequency_hz"] is not None else p["frequency_factor"] * ctx.resonance_hz
    tmax = p["max_base_mm"] * MM
    yield Rest(settle_s)
    yield BeginStage("nonlinear", {"kind": "stepped_amplitude", "control": "base_displacement", **p,
                                   "drive_frequency_hz": f, "resonance_hz": ctx.resonance_hz},
                     pre_trigger_s=pre_trigger_s)
    yield SetFrequency(f)
    levels, stop_reason, first, last_ok = [], None, None, None
    target = p["start_base_mm"] * MM
    final_res = None
    while True:
        yield Checkpoint()
        res = yield ControlSine(target, p["dwell_s"], analysis_s=p["analysis_s"], label=f"level {len(levels) + 1}",
                                on_refusal="return" if levels else "stop", **_ceilings(p))
        if res.refused:
            stop_reason = f"control: level {len(levels) + 1} ({target * 1e3:.4g} mm) refused: {res.refused}"
            target = last_ok
            break
        w = res.window
        r = analysis.response(w.x_base, w.x_tip, w.fs, f)
        settle = {}
        if p["settle_tolerance"] > 0:     # the controller's last window, then more at the drive it holds
            r, settle = yield from settled_response(p, f, r, None, f"level {len(levels) + 1}")
        first = first or r
        reasons = nonlinearity_reached(p, first, r) if len(levels) else []
        levels.append({"base_target_m": target, "effective_target_m": res.effective_target_m,
                       "control_error_db": res.error_db, "amplitude_vpp": res.vpp, "notched": res.notched,
                       **r.to_dict(), **settle, "criteria": reasons})
        final_res, last_ok = res, target
        yield Log("info", f"nonlinear level {len(levels)}: base {r.base_amplitude * 1e3:.4f} mm (target "
                          f"{target * 1e3:.4g} mm, {res.error_db:+.2f} dB) at {res.vpp:.3f} Vpp, relative amplitude "
                          f"{r.relative_amplitude * 1e3:.3f} mm, THD {r.thd * 100:.2f} %, gain {r.gain:.3f}, "
                          f"loss factor {r.loss_factor:.4f}")
        if reasons:
            stop_reason = "nonlinearity: " + "; ".join(reasons)
            break
        if res.notched:
            stop_reason = (f"response limit: the base target was lowered to {res.effective_target_m * 1e3:.4g} mm "
                           f"to keep the response at its ceiling")
            break
        nxt, stop_reason, key = next_level(target, tmax, p["step_factor"], ctx.limits, r,
                                           f"base target limit {tmax * 1e3:g} mm")
        if nxt is None:
            break
        if key is not None:
            yield Log("info", f"next level {nxt * 1e3:.4g} mm: limited to {ctx.limits['soft_limit_fraction']:g} x {key}")
        target = nxt
    yield Log("info" if stop_reason.startswith("nonlinearity") else "warning",
              f"nonlinear stage stops raising at base {target * 1e3:.4g} mm: {stop_reason}")
    if p["hold_s"] > 0:
        final_res = yield ControlSine(target, p["hold_s"], label="hold", **_ceilings(p))
    ctx.nonlinear_vpp = final_res.vpp
    ctx.nonlinear_base_m = target
    yield EndStage({"drive_frequency_hz": f, "final_base_m": target, "final_vpp": final_res.vpp,
                    "stop_reason": stop_reason, "nonlinear": stop_reason.startswith("nonlinearity"),
                    "levels": levels, **_control_summary(final_res)})
    return final_res.vpp


def validation_stage(v: dict, settle_s: float, ctx, pre_trigger_s: float = PRE_TRIGGER_S):
    f = v["frequency_hz"] if v["frequency_hz"] is not None else v["frequency_factor"] * ctx.resonance_hz
    if v["base_amplitude_mm"] is not None:
        target = v["base_amplitude_mm"] * MM
    else:
        target = v["amplitude_fraction"] * ctx.nonlinear_base_m
    yield Rest(settle_s)
    yield BeginStage(v["name"], {"kind": "harmonic", "control": "base_displacement", **v,
                                 "drive_frequency_hz": f, "base_target_m": target}, pre_trigger_s=pre_trigger_s)
    yield SetFrequency(f)
    res = yield ControlSine(target, v["duration_s"], label=v["name"], **_ceilings(v))
    w = res.window
    r = analysis.response(w.x_base, w.x_tip, w.fs, f)
    yield EndStage({"response": r.to_dict(), **_control_summary(res)})
    return r


def validation_uses_base_targets(v: dict, ctx) -> bool:
    """Closed loop when the stage gives a base amplitude, or a fraction of a closed-loop nonlinear stage."""
    return v["base_amplitude_mm"] is not None or (
        v["amplitude_fraction"] is not None and getattr(ctx, "nonlinear_base_m", None) is not None)


# ---- protocol checks (called by rig.protocol) ---------------------------------------------------------

_RESPONSE = ("max_tip_mm", "max_relative_mm")


def check_amplitude_fields(cfg: dict, validation: list[dict], source: str) -> None:
    """Each stage gives its amplitude in volts or as a base target, not both (and not neither);
    response ceilings need a base target (the controller acts on them)."""
    def one_of(table: str, d: dict, volts: str, base: str, default_vpp=None):
        if d[volts] is not None and d[base] is not None:
            raise UserFacingError(f"{source}: [{table}] give {volts} (generator volts) or {base} (base displacement "
                                  f"target), not both")
        if d[volts] is None and d[base] is None:
            if default_vpp is None:
                raise UserFacingError(f"{source}: [{table}] {volts} or {base}: missing (give one)")
            d[volts] = default_vpp

    one_of("linear", cfg["linear"], "amplitude_vpp", "base_amplitude_mm")
    one_of("resonance_search", cfg["resonance_search"], "amplitude_vpp", "base_amplitude_mm", default_vpp=0.1)
    nl = cfg["nonlinear"]
    for volts, base in (("start_vpp", "start_base_mm"), ("max_vpp", "max_base_mm")):
        one_of("nonlinear", nl, volts, base)
    if (nl["start_vpp"] is None) != (nl["max_vpp"] is None):
        raise UserFacingError(f"{source}: [nonlinear] give start_vpp and max_vpp (volts) or start_base_mm and "
                              f"max_base_mm (base targets), not a mix")
    if nl["start_base_mm"] is not None and nl["max_base_mm"] < nl["start_base_mm"]:
        raise UserFacingError(f"{source}: [nonlinear] max_base_mm ({nl['max_base_mm']:g}) is below start_base_mm "
                              f"({nl['start_base_mm']:g})")
    tables = [(t, cfg[t]) for t in ("linear", "resonance_search", "nonlinear")]
    tables += [(f"validation {v.get('name') or i + 1}", v) for i, v in enumerate(validation)]
    for table, d in tables:
        closed = d.get("base_amplitude_mm") is not None or d.get("start_base_mm") is not None
        if table.startswith("validation") and d.get("amplitude_fraction") is not None:
            closed = closed or nl["start_base_mm"] is not None
        for key in _RESPONSE:
            if d.get(key) is not None and not closed:
                raise UserFacingError(f"{source}: [{table}] {key}: a response limit needs a base displacement target "
                                      f"(the sine controller lowers it); this stage gives generator volts")


def base_targets(protocol) -> list[tuple[str, str, float]]:
    """(table, field, metres) of every base target given in the protocol (for the limit checks)."""
    d = protocol.data
    out = [("linear", "base_amplitude_mm", d["linear"]["base_amplitude_mm"]),
           ("resonance_search", "base_amplitude_mm", d["resonance_search"]["base_amplitude_mm"]),
           ("nonlinear", "start_base_mm", d["nonlinear"]["start_base_mm"]),
           ("nonlinear", "max_base_mm", d["nonlinear"]["max_base_mm"])]
    out += [(f"validation {v['name']}", "base_amplitude_mm", v["base_amplitude_mm"]) for v in protocol.validation]
    return [(t, k, v * MM) for t, k, v in out if v is not None]

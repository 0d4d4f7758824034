"""The closed loop: run, diagnose, record the stage that decides, diagnose again (docs/closed-loop.md).

After the protocol, the run just recorded is diagnosed (:func:`recon.diagnose`). The answer
decides the next step (:func:`decide`):

- one or more effects named, none ambiguous, each size determined by the record: stop, *resolved*;
- an effect named whose size the record does not determine (:func:`unsettled_size`: it moved beyond
  its interval when the diagnosis chose the baseline's terms again under it, so the size hangs on
  the baseline's structure, which its interval does not hold): the stage where that kind of effect
  shows (as for an undecided one) is planned as a *fitting* stage (``sizing_frequency_r1``: a name
  that does not begin with ``validation``), so the diagnosis sizes the effect on it; once per
  effect;
- two candidates the held-out data cannot tell apart (``ambiguous``): the stage that separates them
  (:func:`recon.diagnosis.ambiguity.separating_stage`) is planned;
- an effect named only once the loop had added held-out stages (to show an undecided candidate or
  to separate an ambiguous pair) and not named before them: sized the same way, since its size is
  fitted on the fitting stages, which could not show it;
- nothing named, but a candidate the record hints at without showing it (:func:`undecided`: its
  fit takes part of the held-out mismatch without passing the significance rule, i.e. its size on
  this record is near its detection limit): the stage that shows that kind of effect better (a
  second amplitude for an amplitude-dependent one, a frequency step otherwise) is planned;
- nothing named and no candidate undecided (every one below its detection limit): stop, *clean*.

A planned stage is checked before anything moves (:func:`plan_round`): its drive against the rig's
limits (the supervisor's own checks) and against the specimen's ceilings: the first recording's
highest level (``[nonlinear] max_vpp``), its response ceilings (``max_tip_mm``,
``max_relative_mm``) and the displacement limits times ``soft_limit_fraction``, with the response
predicted from what the run recorded at that frequency. A stage beyond a ceiling is refused (never
scaled down) and the plan says which ceiling. The accepted stages are recorded into the same run
file (:func:`rig.session.acquire` with ``append``), and the extended run is diagnosed again. The
loop ends resolved, clean, after ``max_rounds`` added rounds, when every planned stage is refused,
when the operator declines or cancels, or when an added stage does not complete; the rounds'
history is written into the run file (``entry/results/closed_loop_NNN``, docs/recording-format.md).
"""
from __future__ import annotations

import math
import threading
import tomllib
from dataclasses import dataclass, field

import numpy as np

from recon import diagnose
from recon.diagnosis.ambiguity import separating_stage
from rig.messages import Checkpoint, Log, Rest
from rig.plans import PlanContext, validation_stage
from rig.protocol import parse_protocol
from rig.safety import LimitError, Supervisor
from rig.session import acquire
from shakerlab.jsonsafe import clean
from shakerlab.runfile.reader import load_run, read_info
from shakerlab.runfile.results import add_result

# a candidate not named is undecided (the record cannot tell whether it is there) when its fit takes
# this share of the held-out mismatch, or its fitted size this share of its detection limit (an
# estimate, docs/diagnosis.md); a clean record's candidates take well under 1 %
UNDECIDED_EXPLAINED = 0.05
UNDECIDED_SHARE = 0.5
# an added stage's drive may reach this much beyond the recorded levels' predicted response
PREDICTION_MARGIN = 1.2
# two frequencies closer than this (relative) are the same drive frequency for the prediction
SAME_FREQUENCY = 0.02
DEFAULT_MAX_ROUNDS = 2
RESULT_KIND = "closed_loop"

# why the loop stopped (the ``stop`` of the JSON and of the run file's history)
STOPS = {
    "resolved": "the answer is unambiguous and significant",
    "clean": "nothing named, and no candidate near its detection limit on this record (none undecided)",
    "max_rounds": "the configured number of added rounds was reached",
    "refused": "every planned stage is beyond a limit of the rig or a ceiling of the specimen",
    "declined": "the plan was not confirmed",
    "cancelled": "cancelled by the operator",
    "run_failed": "an added stage did not complete",
    "no_stage": "undecided, and no stage is known that would decide",
}


class Cancelled(Exception):
    """The operator cancelled the loop (stages recorded so far are kept)."""


# what an added round is for (the ``purpose`` of a round in the JSON and the run file's history)
PURPOSES = {
    "separate": "held-out stage(s) that tell two candidates apart (validation_*)",
    "show": "held-out stage(s) that show whether an undecided candidate is there (validation_*)",
    "size": "fitting stage(s) where a named effect shows, to size it (sizing_*)",
}


@dataclass
class Decision:
    action: str                  # "stop" or "add"
    stop: str = ""               # a key of STOPS when action == "stop"
    reason: str = ""             # the sentence shown to the operator
    proposal: dict | None = None  # separating_stage(): ids, stages, reason, protocol_toml
    purpose: str = "separate"    # a key of PURPOSES when action == "add"


@dataclass
class PlannedStage:
    name: str
    frequency_hz: float
    amplitude_vpp: float
    duration_s: float
    origin: str                  # how the drive was derived
    predicted: dict = field(default_factory=dict)   # predicted peak displacements, m
    refused: str = ""            # the limit or ceiling it would cross (empty: accepted)

    def to_dict(self) -> dict:
        return {"name": self.name, "frequency_hz": self.frequency_hz, "amplitude_vpp": self.amplitude_vpp,
                "duration_s": self.duration_s, "origin": self.origin, "predicted_peak_m": self.predicted,
                "refused": self.refused or None}


@dataclass
class RoundPlan:
    round: int
    reason: str
    ids: list
    stages: list                 # PlannedStage, accepted and refused
    purpose: str = "separate"    # a key of PURPOSES

    @property
    def accepted(self) -> list:
        return [s for s in self.stages if not s.refused]

    @property
    def refused(self) -> list:
        return [s for s in self.stages if s.refused]

    def to_dict(self) -> dict:
        return {"round": self.round, "reason": self.reason, "ids": list(self.ids), "purpose": self.purpose,
                "stages": [s.to_dict() for s in self.stages]}

    def text(self) -> str:
        lines = [f"round {self.round}: {self.reason}"]
        for s in self.stages:
            what = (f"  {s.name}: {s.amplitude_vpp:.3f} Vpp at {s.frequency_hz:.3f} Hz for {s.duration_s:g} s "
                    f"({s.origin})")
            lines.append(what + (f"\n    REFUSED: {s.refused}" if s.refused else ""))
        return "\n".join(lines)


# ---- the decision ---------------------------------------------------------------------------------

def undecided(d: dict) -> list[dict]:
    """Candidates not named that the record hints at but cannot show: their fit takes at least
    UNDECIDED_EXPLAINED of the held-out mismatch without passing the significance rule (or, when the
    diagnosis reports the fitted size, that size reaches UNDECIDED_SHARE of the detection limit)."""
    out = []
    for c in d.get("candidates_tested", []):
        if c.get("significant") or c.get("failed"):
            continue
        lim = c.get("detection_limit") or {}
        explained = c.get("explained")
        fitted = ((c.get("parameters") or {}).get(lim.get("parameter")) or {}).get("value")
        share = (abs(float(fitted)) / abs(float(lim["value"]))
                 if fitted is not None and lim.get("value") and math.isfinite(float(fitted)) else None)
        if (share is not None and share >= UNDECIDED_SHARE) or (
                explained is not None and math.isfinite(explained) and explained >= UNDECIDED_EXPLAINED):
            out.append({"id": c["id"], "explained": explained, "share_of_limit": share,
                        "limit": {k: lim.get(k) for k in ("parameter", "value")} if lim else None})
    return sorted(out, key=lambda u: -(u["explained"] or 0.0))


def unsettled_size(m: dict) -> dict | None:
    """For a named effect ``m`` (an entry of ``missing_physics``): of its parameters whose value
    before the diagnosis chose the baseline's terms again under it lies outside the revised fit's
    95 % interval, the one that moved most in half-widths of that interval (its name, both values,
    the interval); else None. Such a parameter depends on which terms the baseline holds (they trade
    off against the effect on this record), an uncertainty its interval, computed from the noise
    alone, does not hold: the record does not determine the effect's size."""
    rev = m.get("baseline_terms_revised") or {}
    before, after = rev.get("parameters_before") or {}, m.get("parameters") or {}
    moved = []
    for name, b in before.items():
        a = after.get(name) or {}
        lo_hi = a.get("interval")
        try:
            vb, va = float(b["value"]), float(a["value"])
        except (KeyError, TypeError, ValueError):
            continue
        if lo_hi and all(map(math.isfinite, (vb, va, *lo_hi))) and not lo_hi[0] <= vb <= lo_hi[1]:
            half = max(0.5 * (lo_hi[1] - lo_hi[0]), 1e-300)
            moved.append((abs(vb - va) / half, {"parameter": name, "before": vb, "after": va,
                                                 "interval": list(lo_hi)}))
    # the one that moved most, in half-widths of its interval
    return max(moved, key=lambda x: x[0])[1] if moved else None


def _stage_words(proposal: dict) -> str:
    """What the single-effect stage of ``proposal`` (separating_stage([id, id])) is, in words."""
    return ("a second amplitude at the same frequency" if proposal["stages"] == ["validation_amplitude"]
            else "a frequency step at the same level")


def decide(d: dict, sized=(), shown=()) -> Decision:
    """What the diagnosis ``d`` (``Diagnosis.to_dict()``) asks for next; ``sized``: ids a sizing round
    has already been recorded for (each is sized once); ``shown``: ids named only once the loop had
    added held-out stages (to show an undecided candidate, or to separate an ambiguous pair) and not
    named on the record before them. Such an effect is sized too: its size is fitted on the fitting
    stages, which could not show it."""
    if d.get("ambiguous"):
        a, b = d["ambiguous"][:2]
        proposal = d.get("separating_stage") or separating_stage([a, b])
        return Decision("add", reason=f"ambiguous: {a} and {b} explain the held-out mismatch about equally well; "
                                      f"separating by {proposal['reason']}", proposal=proposal)
    named = [m["id"] for m in d.get("missing_physics", [])]
    for m in d.get("missing_physics", []):
        if m["id"] in sized:
            continue
        u = unsettled_size(m)
        if u is not None:
            why = (f"its {u['parameter']} moved from {u['before']:.4g} to {u['after']:.4g} (outside its interval "
                   f"[{u['interval'][0]:.4g}, {u['interval'][1]:.4g}]) when the baseline's terms were chosen "
                   f"again: this record does not determine its size")
        elif m["id"] in shown:
            why = ("it was named once an added held-out stage showed it, and its size is fitted on the fitting "
                   "stages, which could not show it")
        else:
            continue
        proposal = separating_stage([m["id"], m["id"]])
        how = _stage_words(proposal)
        return Decision("add", purpose="size", proposal={**proposal, "ids": [m["id"]], "reason": how},
                        reason=f"named {m['id']}, but {why}; adding {how} as a fitting stage, where the effect "
                               f"shows, to size it")
    if named:
        still = [m["id"] for m in d.get("missing_physics", []) if unsettled_size(m) is not None]
        note = (f" (after its sizing stage the size of {', '.join(still)} still moves with the baseline's terms "
                f"beyond its interval)" if still else "")
        return Decision("stop", "resolved", f"named {', '.join(named)}: {STOPS['resolved']}{note}")
    open_ = undecided(d)
    if open_:
        u = open_[0]
        proposal = separating_stage([u["id"], u["id"]])
        lim = u["limit"] or {}
        limit = (f" (detection limit on this record: {lim['parameter']} {lim['value']:.3g})"
                 if lim.get("value") is not None else "")
        how = _stage_words(proposal) + (" (the effect changes with amplitude)"
                                        if proposal["stages"] == ["validation_amplitude"] else
                                        " (the effect trades off with the model's terms at one frequency)")
        return Decision("add", purpose="show", reason=f"nothing named, but {u['id']} takes {100 * (u['explained'] or 0):.0f} % of the "
                                      f"held-out mismatch without passing the significance rule{limit}: this record "
                                      f"cannot show whether it is there; adding {how}",
                        proposal={**proposal, "ids": [u["id"]], "reason": how})
    return Decision("stop", "clean", STOPS["clean"])


# ---- the plan -------------------------------------------------------------------------------------

def recorded_context(info: dict) -> dict:
    """What the planned stages are derived from and checked against: the resonance, the nonlinear
    stage's frequency, final level and ceilings, and every recorded response (frequency, Vpp,
    peak base/tip/relative displacement)."""
    stages = info["stages"]
    ctx = {"resonance_hz": None, "nonlinear_vpp": None, "nonlinear_hz": None, "max_vpp": None,
           "max_tip_m": None, "max_relative_m": None, "responses": [], "search": None, "names": list(stages)}
    for name, st in stages.items():
        s, settings = st["summary"], st["settings"]
        if "resonance_hz" in s and ctx["resonance_hz"] is None:
            ctx["resonance_hz"] = float(s["resonance_hz"])
            if s.get("frequencies_hz") and s.get("base_amplitude_m") and settings.get("amplitude_vpp"):
                ctx["search"] = {"hz": s["frequencies_hz"], "base_m": s["base_amplitude_m"],
                                 "transmissibility": s.get("transmissibility"), "vpp": settings["amplitude_vpp"]}
        if name == "nonlinear" and "final_vpp" in s:
            ctx["nonlinear_vpp"] = float(s["final_vpp"])
            ctx["nonlinear_hz"] = float(s["drive_frequency_hz"])
            ctx["max_vpp"] = settings.get("max_vpp")
            for key in ("max_tip", "max_relative"):
                if settings.get(f"{key}_mm") is not None:
                    ctx[f"{key}_m"] = settings[f"{key}_mm"] * 1e-3
            for lv in s.get("levels", []):
                ctx["responses"].append(_response(lv["frequency_hz"], lv["amplitude_vpp"], lv))
        elif "response" in s:
            vpp = settings.get("drive_vpp", settings.get("amplitude_vpp"))
            if vpp:
                ctx["responses"].append(_response(s["response"]["frequency_hz"], vpp, s["response"]))
    return ctx


def _response(hz, vpp, r) -> dict:
    return {"hz": float(hz), "vpp": float(vpp), "base": float(r.get("peak_base", r.get("base_amplitude", 0.0))),
            "tip": float(r.get("peak_tip", r.get("tip_amplitude", 0.0))),
            "relative": float(r.get("peak_relative", r.get("relative_amplitude", 0.0)))}


def predict(ctx: dict, hz: float, vpp: float) -> dict:
    """Peak displacements (m) expected at ``vpp`` and ``hz``: from the recorded response at the same
    frequency nearest in level, scaled in proportion to the drive (the specimen softens with
    amplitude, so a larger level is scaled from the largest recorded, a smaller from the nearest);
    else from the resonance search's table, interpolated and scaled from its level. Times
    PREDICTION_MARGIN. Empty when nothing was recorded near ``hz``."""
    same = [r for r in ctx["responses"] if abs(r["hz"] / hz - 1) <= SAME_FREQUENCY and r["vpp"] > 0]
    if same:
        r = min(same, key=lambda r: abs(math.log(r["vpp"] / vpp)))
        k = PREDICTION_MARGIN * vpp / r["vpp"]
        return {"x_base": k * r["base"], "x_tip": k * r["tip"], "relative": k * r["relative"]}
    s = ctx.get("search")
    if s and min(s["hz"]) <= hz <= max(s["hz"]) and s.get("transmissibility"):
        order = np.argsort(s["hz"])
        f = np.asarray(s["hz"])[order]
        base = float(np.interp(hz, f, np.asarray(s["base_m"])[order])) * vpp / s["vpp"]
        tr = float(np.interp(hz, f, np.asarray(s["transmissibility"])[order]))
        k = PREDICTION_MARGIN * math.sqrt(2.0)      # fundamental amplitudes: a little harmonic content on top
        return {"x_base": k * base, "x_tip": k * base * tr, "relative": k * base * (tr + 1.0)}
    return {}


def stage_tables(proposal: dict) -> list[dict]:
    """The separating validation stages of a proposal (its protocol TOML, parsed and checked)."""
    text = proposal["protocol_toml"]
    protocol = parse_protocol(tomllib.loads(text), text, "separating protocol")
    return [v for v in protocol.validation if v["name"] in proposal["stages"]]


def plan_round(decision: Decision, info: dict, limits: dict, round_no: int) -> RoundPlan:
    """The decision's stages as drives, each checked against the limits and ceilings (refused, never
    scaled). Stage names get the round's suffix (``validation_amplitude_r1``) so every round adds
    new stages."""
    ctx = recorded_context(info)
    sup = Supervisor(limits)
    planned = []
    for v in stage_tables(decision.proposal):
        stem = v["name"] if decision.purpose != "size" else "sizing" + v["name"].removeprefix("validation")
        name = _unique(f"{stem}_r{round_no}", ctx["names"])
        if v["frequency_hz"] is not None:
            hz, f_origin = v["frequency_hz"], "frequency_hz"
        elif ctx["resonance_hz"] is not None:
            hz = v["frequency_factor"] * ctx["resonance_hz"]
            f_origin = f"{v['frequency_factor']:g} x the resonance {ctx['resonance_hz']:.3f} Hz"
        else:
            hz, f_origin = float("nan"), "no resonance recorded"
        if v["amplitude_vpp"] is not None:
            vpp, a_origin = v["amplitude_vpp"], "amplitude_vpp"
        elif ctx["nonlinear_vpp"] is not None and v["amplitude_fraction"] is not None:
            vpp = v["amplitude_fraction"] * ctx["nonlinear_vpp"]
            a_origin = f"{v['amplitude_fraction']:g} x the nonlinear final level {ctx['nonlinear_vpp']:.3f} Vpp"
        else:
            vpp, a_origin = float("nan"), "no open-loop nonlinear level recorded"
        st = PlannedStage(name, float(hz), float(vpp), float(v["duration_s"]), f"{a_origin}; {f_origin}")
        st.refused = _refusal(st, ctx, sup, limits)
        planned.append(st)
    return RoundPlan(round_no, decision.reason, list(decision.proposal.get("ids", [])), planned, decision.purpose)


def _unique(name: str, taken: list) -> str:
    out, i = name, 2
    while out in taken:
        out, i = f"{name}_{i}", i + 1
    return out


def _refusal(st: PlannedStage, ctx: dict, sup: Supervisor, limits: dict) -> str:
    """The first limit or ceiling the stage would cross, as a sentence ("" when none)."""
    if not (math.isfinite(st.frequency_hz) and math.isfinite(st.amplitude_vpp)):
        return f"its drive cannot be derived from this run ({st.origin})"
    try:
        sup.check_amplitude(st.amplitude_vpp)
        sup.check_frequency(st.frequency_hz)
        sup.check_duration(st.duration_s)
    except LimitError as exc:
        return f"rig limit: {exc}"
    if ctx["max_vpp"] is not None and st.amplitude_vpp > ctx["max_vpp"] * (1 + 1e-12):
        return (f"specimen ceiling: {st.amplitude_vpp:g} Vpp exceeds the first recording's highest level "
                f"[nonlinear] max_vpp = {ctx['max_vpp']:g} Vpp")
    st.predicted = predict(ctx, st.frequency_hz, st.amplitude_vpp)
    if not st.predicted:
        return (f"specimen ceiling: no response was recorded near {st.frequency_hz:.3f} Hz, so the displacement "
                f"it would cause cannot be predicted")
    soft = limits.get("soft_limit_fraction", 1.0)
    ceilings = [("x_base", soft * limits["max_base_displacement_m"],
                 f"{soft:g} x limits.max_base_displacement_m"),
                ("x_tip", soft * limits["max_tip_displacement_m"], f"{soft:g} x limits.max_tip_displacement_m")]
    if ctx["max_tip_m"] is not None:
        ceilings.append(("x_tip", ctx["max_tip_m"], "[nonlinear] max_tip_mm"))
    if ctx["max_relative_m"] is not None:
        ceilings.append(("relative", ctx["max_relative_m"], "[nonlinear] max_relative_mm"))
    for key, ceiling, what in ceilings:
        if st.predicted[key] > ceiling:
            return (f"specimen ceiling: predicted peak {key} {st.predicted[key] * 1e3:.3f} mm exceeds {what} = "
                    f"{ceiling * 1e3:.3f} mm")
    return ""


def diagnose_file(path, extra=None) -> dict:
    """The diagnosis of the run file ``path`` (``Diagnosis.to_dict()``), plus ``extra(run)``'s keys."""
    run = load_run(path)
    out = diagnose(run).to_dict()
    if extra is not None:
        out.update(extra(run))
    return out


# ---- recording a round ------------------------------------------------------------------------------

def round_toml(plan: RoundPlan) -> str:
    """The round's accepted stages as ``[[validation]]`` tables with absolute drives (stored in the run
    file as ``closed_loop_round<N>_toml``)."""
    out = [f"# shakerlab closed loop, round {plan.round}: {plan.reason}".replace("\n", " ")]
    # a sizing stage is a fitting stage, not a protocol's validation stage
    table = "[[validation]]" if plan.purpose != "size" else "[[fitting_stage]]"
    for s in plan.accepted:
        out += ["", table, f'name = "{s.name}"', f"frequency_hz = {s.frequency_hz!r}",
                f"amplitude_vpp = {s.amplitude_vpp!r}", f"duration_s = {s.duration_s!r}  # {s.origin}"]
    return "\n".join(out) + "\n"


def round_plan(plan: RoundPlan, limits: dict, settle_s: float):
    """The runner's plan for a round: each accepted stage as a validation stage at its absolute drive
    (the runner's supervisor checks every setpoint again)."""
    ctx = PlanContext(limits)
    yield Log("info", f"closed loop, round {plan.round}: {plan.reason}")
    for s in plan.accepted:
        yield Checkpoint()
        v = {"name": s.name, "frequency_hz": s.frequency_hz, "frequency_factor": None,
             "amplitude_vpp": s.amplitude_vpp, "amplitude_fraction": None, "duration_s": s.duration_s,
             "base_amplitude_mm": None, "max_tip_mm": None, "max_relative_mm": None,
             "closed_loop_round": plan.round, "closed_loop_reason": plan.reason,
             "closed_loop_purpose": plan.purpose}
        yield from validation_stage(v, settle_s, ctx)
    yield Rest(0.0)
    return ctx


def record_round(config, protocol, path, plan: RoundPlan, *, lockstep: bool = False, observers=(),
                 on_runner=None, settle_s: float | None = None):
    """Record the round's accepted stages into the run file ``path`` (appended; the file is replaced by
    the extended one only when that is whole). Returns the :class:`rig.runner.RunOutcome`."""
    settle = protocol["run"]["settle_s"] if settle_s is None else settle_s
    return acquire(config, protocol, path, lockstep=lockstep, observers=observers, on_runner=on_runner,
                   plan=round_plan(plan, config.limits, settle), append=True,
                   texts={f"closed_loop_round{plan.round}_toml": round_toml(plan)})


# ---- the loop -------------------------------------------------------------------------------------

def summary(d: dict) -> dict:
    """The short form of a diagnosis kept in the rounds' history: what was named (fitted size and
    interval), the ambiguity, the held-out NRMSE before and after."""
    named = [{"id": m["id"], "parameters": m.get("parameters", {}), "size_unsettled": unsettled_size(m),
              "held_out_nrmse_before": (m.get("evidence") or {}).get("held_out_nrmse_before"),
              "held_out_nrmse_after": (m.get("evidence") or {}).get("held_out_nrmse_after")}
             for m in d.get("missing_physics", [])]
    return {"result": d.get("result"), "named": named, "ambiguous": list(d.get("ambiguous") or []),
            "held_out_nrmse_before": held_out(d.get("fit_before")),
            "held_out_nrmse_after": (d.get("fit_after") or {}).get("held_out_nrmse"),
            "undecided": [u["id"] for u in undecided(d)]}


def held_out(fit: dict | None):
    """The held-out NRMSE of a ``fit_before``/``fit_after`` block."""
    if not fit:
        return None
    v = fit.get("held_out_nrmse")
    return v if not isinstance(v, dict) else None


@dataclass
class LoopResult:
    diagnosis: dict
    rounds: list
    stop: str
    stop_reason: str
    result_group: str = ""

    def to_dict(self) -> dict:
        return {"stop": self.stop, "stop_reason": self.stop_reason, "rounds": self.rounds}


class ClosedLoop:
    """Runs the loop on one run file.

    ``diagnose(path) -> dict`` diagnoses the run file (``Diagnosis.to_dict()`` keys);
    ``record(plan) -> outcome`` records the plan's accepted stages into the run file (an object with
    ``status`` and ``reason``: :class:`rig.runner.RunOutcome`); ``confirm(plan) -> bool`` asks the
    operator (``None``: accepted, as ``--auto``); ``observer(event, payload)`` is told every step
    (``diagnosing``, ``diagnosis``, ``plan``, ``recording``, ``recorded``, ``done``). :meth:`cancel`
    (thread-safe) stops at the next step; a recording under way is stopped by the caller (its
    runner's abort), and what it recorded is kept.
    """

    def __init__(self, path, limits: dict, *, diagnose, record, confirm=None, observer=None,
                 max_rounds: int = DEFAULT_MAX_ROUNDS):
        if max_rounds < 0:
            raise ValueError("max_rounds must be >= 0")
        self.path = path
        self.limits = limits
        self.diagnose = diagnose
        self.record = record
        self.confirm = confirm
        self.observer = observer
        self.max_rounds = int(max_rounds)
        self.cancelled = threading.Event()

    def cancel(self) -> None:
        self.cancelled.set()

    def _tell(self, event: str, payload=None) -> None:
        if self.observer is not None:
            self.observer(event, payload)

    def _check(self) -> None:
        if self.cancelled.is_set():
            raise Cancelled()

    def _diagnose(self, round_no: int) -> dict:
        self._check()
        self._tell("diagnosing", {"round": round_no})
        d = self.diagnose(self.path)
        self._tell("diagnosis", {"round": round_no, "summary": summary(d), "diagnosis": d})
        return d

    def run(self) -> LoopResult:
        rounds: list[dict] = []
        d: dict = {}
        stop, why = "", ""
        sized: set = set()
        shown: set = set()
        try:
            d = self._diagnose(0)
            round_no = 0
            while True:
                decision = decide(d, sized, shown)
                if decision.action == "stop":
                    stop, why = decision.stop, decision.reason
                    break
                if round_no >= self.max_rounds and decision.purpose == "size":
                    # the answer stands; only its size was to be measured on a stage where it shows
                    named = ", ".join(m["id"] for m in d.get("missing_physics", []))
                    stop, why = "resolved", (f"named {named}: {STOPS['resolved']}; its size was not measured on a "
                                             f"stage where it shows, the configured number of added rounds "
                                             f"({self.max_rounds}) being reached: {decision.reason}")
                    break
                if round_no >= self.max_rounds:
                    stop = "max_rounds"
                    why = f"{STOPS['max_rounds']} ({self.max_rounds}); still: {decision.reason}"
                    break
                round_no += 1
                plan = plan_round(decision, read_info(self.path), self.limits, round_no)
                self._tell("plan", plan)
                entry = {"round": round_no, "why": decision.reason, "purpose": decision.purpose,
                         "plan": plan.to_dict(), "stages_added": [], "before": summary(d), "after": None}
                if decision.purpose == "size":
                    sized.update(plan.ids)
                named_before = {m["id"] for m in d.get("missing_physics", [])}
                if not plan.stages:
                    rounds.append(entry)
                    stop, why = "no_stage", f"{STOPS['no_stage']}: {decision.reason}"
                    break
                if not plan.accepted:
                    rounds.append(entry)
                    stop = "refused"
                    why = f"{STOPS['refused']}: " + "; ".join(f"{s.name}: {s.refused}" for s in plan.refused)
                    break
                self._check()
                if self.confirm is not None and not self.confirm(plan):
                    rounds.append(entry)
                    self._check()
                    stop, why = "declined", f"{STOPS['declined']}; the plan:\n{plan.text()}"
                    break
                self._check()
                self._tell("recording", plan)
                outcome = self.record(plan)
                entry["stages_added"] = added_stages(self.path, plan)
                entry["recording"] = {"status": outcome.status, "reason": outcome.reason}
                self._tell("recorded", {"round": round_no, "outcome": outcome})
                if outcome.status != "complete":
                    rounds.append(entry)
                    stop = "cancelled" if outcome.status == "aborted" or self.cancelled.is_set() else "run_failed"
                    why = f"{STOPS[stop]}: the added recording ended {outcome.status}" + \
                          (f" ({outcome.reason})" if outcome.reason else "")
                    break
                rounds.append(entry)
                d = self._diagnose(round_no)
                entry["after"] = summary(d)
                if decision.purpose in ("show", "separate"):
                    # named now, not before: the added held-out stages showed it (an undecided
                    # candidate, or the runner-up of an ambiguous pair), its size still comes from
                    # the fitting stages
                    shown.update({m["id"] for m in d.get("missing_physics", [])} - named_before)
        except (Cancelled, KeyboardInterrupt):     # the operator's cancel, or Ctrl-C while diagnosing
            stop, why = "cancelled", STOPS["cancelled"]
        result = LoopResult(d, rounds, stop, why)
        result.result_group = write_history(self.path, result)
        self._tell("done", result)
        return result


def added_stages(path, plan: RoundPlan) -> list[str]:
    """The plan's stages that are in the run file now (recorded, wholly or in part)."""
    try:
        names = read_info(path)["stages"]
    except Exception:  # noqa: BLE001 - an unreadable file recorded nothing that can be listed
        return []
    return [s.name for s in plan.accepted if s.name in names]


def write_history(path, result: LoopResult) -> str:
    """The rounds' history into the run file (``entry/results/closed_loop_NNN``); "" when it cannot
    be written (an interrupted file is never opened for writing)."""
    payload = {"stop": result.stop, "stop_reason": result.stop_reason, "rounds": result.rounds,
               "final": summary(result.diagnosis) if result.diagnosis else None}
    try:
        return add_result(path, RESULT_KIND, clean(payload),
                          text=f"closed loop: {result.stop}: {result.stop_reason}",
                          attrs={"stop": result.stop, "n_rounds": len(result.rounds)})
    except Exception as exc:  # noqa: BLE001 - the loop's answer stands; the history is reported missing
        result.stop_reason += f" (the history could not be written into the run file: {exc})"
        return ""

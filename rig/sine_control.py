"""Closed-loop sine control: hold the base motion's fundamental at a target amplitude.

Two parts, kept apart:

- :class:`SineController` is pure logic (no instruments, unit-testable): once
  per analysis window (a whole number of drive periods) it measures the
  fundamental amplitude of the control channel (the base sensor) with the
  least-squares fit of :func:`rig.analysis.harmonics`, compares it with the
  target, and returns the next generator amplitude (Vpp). A correction that
  would need more than ``limits.max_generator_vpp`` is refused, never
  clipped. Optional response limits (notching): when the tip or relative
  displacement's fundamental reaches its ceiling, the base target is lowered
  so that the response sits at the ceiling.
- :class:`SineControlExecutor` runs a :class:`rig.messages.ControlSine`
  message with a :class:`rig.runner.Runner`'s primitives: every block the
  amplitude moves towards the controller's setpoint by at most
  ``ramp_rate_vpp_per_s`` x the block time (the tone stays phase-continuous:
  only the generator's amplitude is changed), every window the controller
  corrects the setpoint, and every window's record (target, achieved, error)
  goes to the observers' ``on_control(record)`` (the HDF5 recorder, the GUI).

Amplitudes here are fundamental *peak* amplitudes in metres (the protocol
gives them in millimetres: ``base_amplitude_mm``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from rig.analysis import harmonics
from rig.instruments import MIN_VPP
from rig.messages import Window
from rig.safety import LimitError


def fundamental(x: np.ndarray, fs: float, f: float) -> float:
    """Peak amplitude of the fundamental at ``f`` over the last whole periods of ``x``
    (least-squares fit of a mean and five harmonics, :func:`rig.analysis.harmonics`)."""
    return float(abs(harmonics(x, fs, f, 5)[0]))


def db(ratio: float) -> float:
    return 20.0 * math.log10(ratio) if ratio > 0 else -math.inf


@dataclass(frozen=True)
class ControlSettings:
    """How the loop behaves (defaults tuned on the simulated rig: bench/sine_control.py)."""

    tolerance_db: float = 0.5        # |control error| within this = on target
    loop_gain: float = 0.7           # fraction of the log correction applied per window (0 < g <= 1)
    window_periods: int = 2          # analysis window: at least this many whole periods ...
    min_window_s: float = 0.1        # ... and at least this long
    lock_windows: int = 3            # consecutive windows on target before the hold counts
    deadband_db: float = 0.1         # once on target, errors within this leave the amplitude alone
    abort_error_db: float = 10.0     # after lock, an error beyond this is refused (control lost)
    min_signal_fraction: float = 0.05  # below this fraction of the target the gain is not trusted
    settle_timeout_s: float = 30.0   # refuse when not on target this long after the start

    def __post_init__(self):
        if not 0 < self.loop_gain <= 1:
            raise ValueError(f"loop_gain must be in (0, 1], got {self.loop_gain}")
        if self.tolerance_db <= 0 or self.window_periods < 1 or self.lock_windows < 1:
            raise ValueError("tolerance_db > 0, window_periods >= 1 and lock_windows >= 1 are required")


@dataclass
class Decision:
    """What the controller decided after one window."""

    setpoint_vpp: float
    record: dict
    refused: str | None = None            # why the correction is refused (the stage ends)
    events: list = field(default_factory=list)   # (level, message) to log


class SineController:
    """One control loop: target ``target_m`` (fundamental peak of the base) at ``frequency_hz``.

    ``ceilings`` maps ``"tip"`` and/or ``"relative"`` to a fundamental peak amplitude [m]
    that the response must not exceed (notching). ``gain_hint`` (m of base amplitude per Vpp)
    gives the first setpoint when known (the same frequency measured before); without it the
    output ramps up from ``vpp_now`` at the ramp rate until the base motion is measurable.
    """

    def __init__(self, target_m: float, frequency_hz: float, *, max_vpp: float, ramp_rate_vpp_per_s: float,
                 settings: ControlSettings = ControlSettings(), ceilings: dict | None = None,
                 gain_hint: float | None = None):
        if not target_m > 0:
            raise ValueError(f"target must be > 0, got {target_m}")
        self.target = float(target_m)
        self.f = float(frequency_hz)
        self.max_vpp = float(max_vpp)
        self.rate = float(ramp_rate_vpp_per_s)
        self.s = settings
        self.ceilings = {k: float(v) for k, v in (ceilings or {}).items() if v is not None}
        bad = set(self.ceilings) - {"tip", "relative"}
        if bad:
            raise ValueError(f"unknown response limit(s) {sorted(bad)}")
        self.gain = gain_hint          # m per Vpp, last trusted estimate
        self.effective = self.target   # the target after notching
        self.n_windows = 0
        self.on_target_run = 0         # consecutive windows within tolerance
        self.locked = False
        self.notched = False
        self.notch_min = self.target

    # -- geometry -------------------------------------------------------------------------------
    def window_n(self, fs: float) -> int:
        periods = max(self.s.window_periods, math.ceil(self.s.min_window_s * self.f))
        return int(round(periods * fs / self.f))

    def initial_setpoint(self, vpp_now: float) -> tuple[float, str | None]:
        """First setpoint before any window: from the gain hint, else keep ``vpp_now``
        (the ramp-up is driven per window). Refused when the hint already says it needs too much."""
        if self.gain:
            need = self.effective / self.gain
            if need > self.max_vpp:
                return vpp_now, self._refusal(need, "measured before at this frequency")
            return need, None
        return vpp_now, None

    def _refusal(self, need_vpp: float, basis: str) -> str:
        return (f"sine control refused: base amplitude {self.effective * 1e3:.4g} mm at {self.f:.4g} Hz "
                f"needs about {need_vpp:.3g} Vpp ({basis}), more than limits.max_generator_vpp = "
                f"{self.max_vpp:g} Vpp")

    # -- the loop ---------------------------------------------------------------------------------
    def update(self, x_base: np.ndarray, x_tip: np.ndarray, fs: float, vpp_mean: float, vpp_now: float,
               window_s: float | None = None) -> Decision:
        """One window (at least :meth:`window_n` samples; the last whole periods are used).

        ``vpp_mean``: the generator amplitude averaged over the window; ``vpp_now``: the
        amplitude at its end. Returns the next setpoint (never above ``max_vpp``) or a refusal.
        """
        s = self.s
        self.n_windows += 1
        a = fundamental(x_base, fs, self.f)
        events: list[tuple[str, str]] = []
        resp = {}
        if self.ceilings:
            ht = harmonics(x_tip, fs, self.f, 5)[0]
            hb = harmonics(x_base, fs, self.f, 5)[0]
            resp = {"tip": abs(ht), "relative": abs(ht - hb)}
        # notching: the base level that puts each limited response at its ceiling (response ~ base)
        eff = self.target
        which = None
        for key, ceiling in self.ceilings.items():
            r = resp[key]
            if r > 0 and a > 0:
                cand = a * ceiling / r
                if cand < eff:
                    eff, which = cand, key
        was = self.notched
        self.notched = which is not None
        if self.notched and not was:
            events.append(("warning", f"notching: {which} response {resp[which] * 1e3:.4g} mm reached its ceiling "
                                      f"{self.ceilings[which] * 1e3:.4g} mm at {self.f:.4g} Hz; base target lowered "
                                      f"from {self.target * 1e3:.4g} to {eff * 1e3:.4g} mm"))
        elif was and not self.notched:
            events.append(("info", f"notching released: base target back to {self.target * 1e3:.4g} mm"))
        self.effective = eff
        if self.notched:
            self.notch_min = min(self.notch_min, eff)
        err = db(a / eff) if a > 0 else -math.inf
        within = abs(err) <= s.tolerance_db
        self.on_target_run = self.on_target_run + 1 if within else 0
        if not self.locked and self.on_target_run >= s.lock_windows:
            self.locked = True
        record = {"frequency_hz": self.f, "target_m": self.target, "effective_target_m": eff,
                  "achieved_m": a, "error_db": err if math.isfinite(err) else -999.0, "vpp": vpp_mean,
                  "tip_m": resp.get("tip", math.nan), "relative_m": resp.get("relative", math.nan),
                  "notched": self.notched, "locked": self.locked}
        if self.locked and abs(err) > s.abort_error_db:
            record["setpoint_vpp"] = vpp_now
            return Decision(vpp_now, record, refused=(
                f"sine control lost: base amplitude {a * 1e3:.4g} mm against the target {eff * 1e3:.4g} mm "
                f"({err:+.1f} dB, abort limit {s.abort_error_db:g} dB) at {self.f:.4g} Hz"), events=events)
        trusted = vpp_mean > 0 and a >= s.min_signal_fraction * eff
        if trusted:
            self.gain = a / vpp_mean
            need = eff / self.gain
            setpoint = vpp_mean * (eff / a) ** s.loop_gain
            if self.locked and abs(err) <= s.deadband_db:
                setpoint = vpp_now   # steady: no dithering of the drive by the measurement noise
            if setpoint > self.max_vpp:
                record["setpoint_vpp"] = vpp_now
                return Decision(vpp_now, record, refused=self._refusal(need, f"measured gain {self.gain * 1e3:.4g} "
                                                                             f"mm/Vpp"), events=events)
        else:
            # base motion not yet measurable: keep ramping up (one window's worth at the ramp rate),
            # or go to the hint's estimate when there is one
            step = self.rate * (window_s if window_s is not None else self.window_n(fs) / fs)
            setpoint = vpp_now + step
            if self.gain:
                setpoint = max(setpoint, min(eff / self.gain, self.max_vpp))
            if setpoint > self.max_vpp:
                record["setpoint_vpp"] = vpp_now
                basis = (f"the base moved only {a * 1e3:.3g} mm at {vpp_mean:.3g} Vpp" if vpp_mean > 0
                         else "no base motion measured")
                need = eff * vpp_mean / a if a > 0 and vpp_mean > 0 else math.inf
                return Decision(vpp_now, record, refused=self._refusal(need, basis), events=events)
        record["setpoint_vpp"] = setpoint
        return Decision(setpoint, record, events=events)


# ---- running a ControlSine message with the runner's primitives ----------------------------------------

@dataclass
class ControlResult:
    """What a :class:`rig.messages.ControlSine` returns to the plan."""

    window: object                  # rig.messages.Window: the last analysis_s of the hold (None if refused early)
    target_m: float
    effective_target_m: float       # after notching (the lowest of the hold)
    achieved_m: float               # fundamental of the base over the returned window
    error_db: float
    vpp: float                      # generator amplitude at the end
    refused: str | None = None
    notched: bool = False
    settle_s: float | None = None   # from the start of the message to the lock
    records: list = field(default_factory=list)
    start_index: int = 0            # sample index when the message started

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("window")
        d.pop("records")
        d.pop("start_index")
        return d


class SineControlExecutor:
    """Executes :class:`rig.messages.ControlSine` for one runner; remembers the gain per frequency
    (so the next level at the same frequency starts from a good first setpoint)."""

    def __init__(self, runner, settings: ControlSettings | None = None):
        self.runner = runner
        self.settings = settings or ControlSettings()
        self.gains: dict[float, float] = {}    # frequency -> m per Vpp

    def _hint(self, f: float):
        for f0, g in self.gains.items():
            if abs(f0 / f - 1) < 1e-6:
                return g
        return None

    def execute(self, msg):
        r = self.runner
        inst, fs = r.inst, r.fs
        lim = r.sup.limits
        f = inst.frequency
        if not f > 0:
            raise LimitError("sine control needs a drive frequency (SetFrequency first)")
        s = self.settings if msg.settle_timeout_s is None else ControlSettings(
            **{**asdict(self.settings), "settle_timeout_s": msg.settle_timeout_s})
        ceilings = {"tip": msg.max_tip_m, "relative": msg.max_relative_m}
        ctrl = SineController(msg.target_m, f, max_vpp=lim["max_generator_vpp"],
                              ramp_rate_vpp_per_s=r.ramp_rate, settings=s, ceilings=ceilings,
                              gain_hint=self._hint(f))
        n_win = ctrl.window_n(fs)
        n_hold = max(1, int(round(msg.duration_s * fs)))
        n_analysis = n_hold if not msg.analysis_s else min(n_hold, max(1, int(round(msg.analysis_s * fs))))
        vpp_now = inst.vpp if inst.output else 0.0
        setpoint, refusal = ctrl.initial_setpoint(vpp_now)
        label = msg.label or "control"
        r._notify("on_setpoint", r.index, setpoint, f, f"control {label}: base to {msg.target_m * 1e3:.4g} mm")
        start_index = r.index
        records: list[dict] = []

        def refuse(reason: str, window=None):
            r.log("error" if msg.on_refusal == "stop" else "warning", reason)
            if msg.on_refusal == "stop":
                raise LimitError(reason)
            return ControlResult(window, msg.target_m, ctrl.effective, math.nan, math.nan,
                                 inst.vpp if inst.output else 0.0, refused=reason, notched=ctrl.notched,
                                 records=records, start_index=start_index)

        if refusal:
            return refuse(refusal)
        # rolling buffers (base, tip, per-sample amplitude) long enough for a window and the analysis
        keep = max(n_win, n_analysis)
        xb = np.empty(0)
        xt = np.empty(0)
        vv = np.empty(0)
        since = 0
        held = 0
        lock_index = None
        serial = r._pause_serial
        block_dt = inst.block_n / fs
        while True:
            cur = inst.vpp if inst.output else 0.0
            step = r.ramp_rate * block_dt
            nxt = setpoint if abs(setpoint - cur) <= step else cur + math.copysign(step, setpoint - cur)
            if nxt != cur:
                r.sup.check_amplitude(nxt)   # never above the limit (the controller refuses before)
                inst.set_amplitude(nxt if nxt > MIN_VPP else 0.0)
            blk = r._block()
            block_dt = max(blk.n, 1) / fs
            if r._pause_serial != serial:      # paused and resumed: the windows start again
                serial = r._pause_serial
                xb, xt, vv = np.empty(0), np.empty(0), np.empty(0)
                since = held = 0
                ctrl.on_target_run = 0
                continue
            xb = np.concatenate([xb, blk.x_base])[-keep:]
            xt = np.concatenate([xt, blk.x_tip])[-keep:]
            vv = np.concatenate([vv, np.full(blk.n, blk.amplitude_vpp)])[-keep:]
            since += blk.n
            if ctrl.locked:
                held += blk.n
            if since >= n_win and xb.size >= n_win:
                since = 0
                d = ctrl.update(xb[-n_win:], xt[-n_win:], fs, float(np.mean(vv[-n_win:])),
                                inst.vpp if inst.output else 0.0, window_s=n_win / fs)
                rec = {"sample_index": int(blk.end_index), "window_n": n_win, **d.record}
                records.append(rec)
                r._notify("on_control", rec)
                for level, text in d.events:
                    r.log(level, text)
                if d.refused:
                    return refuse(d.refused)
                setpoint = d.setpoint_vpp
                if ctrl.locked and lock_index is None:
                    lock_index = blk.end_index
                    self.gains[f] = ctrl.gain
                    r._notify("on_setpoint", r.index, setpoint, f,
                              f"level {label}: base on target {msg.target_m * 1e3:.4g} mm "
                              f"({(lock_index - start_index) / fs:.2f} s)")
            if ctrl.gain:
                self.gains[f] = ctrl.gain
            if lock_index is None and (blk.end_index - start_index) / fs > s.settle_timeout_s:
                return refuse(f"sine control refused: base amplitude {ctrl.effective * 1e3:.4g} mm at {f:.4g} Hz "
                              f"not reached within ±{s.tolerance_db:g} dB in {s.settle_timeout_s:g} s")
            if lock_index is not None and held >= n_hold and xb.size >= n_analysis:
                break
        win = Window(blk.end_index - n_analysis, fs, xb[-n_analysis:].copy(), xt[-n_analysis:].copy(),
                     float(np.mean(vv[-n_analysis:])), f)
        achieved = fundamental(win.x_base, fs, f)
        if ctrl.notched or ctrl.notch_min < ctrl.target:
            r.log("info", f"notching held the base target at {ctrl.notch_min * 1e3:.4g} mm (asked "
                          f"{ctrl.target * 1e3:.4g} mm) at {f:.4g} Hz")
        return ControlResult(win, msg.target_m, ctrl.notch_min, achieved, db(achieved / ctrl.effective),
                             inst.vpp if inst.output else 0.0, notched=ctrl.notch_min < ctrl.target,
                             settle_s=(lock_index - start_index) / fs, records=records, start_index=start_index)

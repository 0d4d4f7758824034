"""``shakerlab check-rig``: connect every instrument, drive a calibration tone, compare the sensors.

The documented set-up (docs/real-rig.md): both sensors aimed at the shaker's
base (armature), so they see the same motion.  The check

1. connects to the generator, the amplifier and both sensors and reads their
   identities (an unreachable instrument is named);
2. checks the amplifier settings the device bounds (as ``acquire`` does);
3. drives a small tone (``[check] tone_hz``, ``tone_vpp``) through the same
   supervised runner as a run (ramped up, limits and interlocks active,
   ramped down and made safe at the end or on any failure), lets it settle for
   ``settle_s`` and measures ``duration_s``;
4. reports each sensor's amplitude at the tone (least-squares fit, after its
   ``sensitivity``) and their agreement, tip / base;

and fails, naming the reason, when an instrument cannot be reached, the run
trips or errs, the base moves less than ``min_amplitude_m``, or the two
amplitudes differ by more than ``agreement_tolerance``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rig.analysis import harmonics
from rig.config import RigConfig
from rig.instruments import RigInstruments
from rig.messages import Acquire, Log, Ramp, Rest, SetFrequency
from rig.runner import Runner
from rig.safety import Supervisor
from rig.session import check_device_settings
from shakerlab.errors import UserFacingError


@dataclass
class CheckReport:
    source: str
    passed: bool = False
    reasons: list = field(default_factory=list)
    addresses: dict = field(default_factory=dict)
    identities: dict = field(default_factory=dict)
    tone: dict = field(default_factory=dict)
    sensors: dict = field(default_factory=dict)
    agreement: dict = field(default_factory=dict)
    amplifier: str = ""
    run: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"config": self.source, "passed": self.passed, "reasons": list(self.reasons),
                "addresses": self.addresses, "identities": self.identities, "amplifier_kind": self.amplifier,
                "tone": self.tone, "sensors": self.sensors, "agreement": self.agreement, "run": self.run}

    def text(self) -> str:
        lines = [f"check-rig: {self.source}"]
        for name, address in self.addresses.items():
            lines.append(f"  {name:<12} {self.identities.get(name, '(not reached)')}  [{address}]")
        if self.tone:
            t = self.tone
            lines.append(f"calibration tone {t['frequency_hz']:g} Hz, {t['amplitude_vpp']:g} Vpp, "
                         f"{t['duration_s']:g} s after {t['settle_s']:g} s settling (both sensors on the base):")
        for point, s in self.sensors.items():
            amp = s.get("amplitude_m")
            lines.append(f"  {point:<5} " + ("amplitude not measured" if amp is None else
                                             f"amplitude {amp * 1e3:.5f} mm") +
                         f"  ({s['quantity']}, sensitivity {s['sensitivity']:g}"
                         + (f", serial {s['serial_number']}" if s["serial_number"] else "") + ")")
        if self.agreement:
            a = self.agreement
            lines.append(f"  agreement: tip / base = {a['ratio']:.4f} ({a['deviation'] * 100:.2f} % apart, "
                         f"phase {a['phase_deg']:+.2f} deg; tolerance {a['tolerance'] * 100:g} %)")
        if self.passed:
            lines.append("PASS")
        else:
            lines += [f"FAIL: {r}" for r in self.reasons]
        return "\n".join(lines)


def _plan(chk: dict):
    yield Log("info", f"check-rig: calibration tone {chk['tone_hz']:g} Hz, {chk['tone_vpp']:g} Vpp")
    yield SetFrequency(chk["tone_hz"])
    yield Ramp(chk["tone_vpp"], "calibration tone")
    yield Acquire(chk["settle_s"])
    window = yield Acquire(chk["duration_s"])
    yield Rest(0.0)
    return window


def check_rig(config: RigConfig, *, lockstep: bool = False) -> CheckReport:
    """Run the check on the rig at ``config``'s addresses (see the module docstring)."""
    chk = config.data["check"]
    report = CheckReport(config.source, addresses=config.addresses(), amplifier=config.amplifier_kind)
    for point in ("base", "tip"):
        s = config.data["sensors"][point]
        report.sensors[point] = {"quantity": s["quantity"], "sensitivity": s["sensitivity"],
                                 "serial_number": s["serial_number"], "calibration_date": s["calibration_date"],
                                 "range_m": s["range_m"], "amplitude_m": None}
    inst = RigInstruments(config, lockstep=lockstep)
    try:
        try:
            report.identities = inst.connect()
        except Exception as exc:  # noqa: BLE001 - an unreachable instrument is the finding
            report.reasons.append(f"cannot reach the instruments ({type(exc).__name__}: {exc}); check the "
                                  f"addresses, the cables and that the instruments are on")
            return report
        try:
            check_device_settings(config, inst)
        except UserFacingError as exc:
            report.reasons.append(str(exc))
            return report
        report.tone = {"frequency_hz": chk["tone_hz"], "amplitude_vpp": chk["tone_vpp"],
                       "duration_s": chk["duration_s"], "settle_s": chk["settle_s"]}
        runner = Runner(inst, Supervisor(config.limits))
        outcome = runner.run(_plan(chk), {})
    finally:
        inst.close()
    report.run = {"status": outcome.status, "reason": outcome.reason}
    if outcome.status != "complete" or outcome.plan_result is None:
        report.reasons.append(f"the calibration tone did not complete ({outcome.status}: {outcome.reason})")
        return report
    window = outcome.plan_result
    fit = {"base": harmonics(window.x_base, window.fs, chk["tone_hz"], 1)[0],
           "tip": harmonics(window.x_tip, window.fs, chk["tone_hz"], 1)[0]}
    for point, c in fit.items():
        report.sensors[point]["amplitude_m"] = float(abs(c))
    base, tip = fit["base"], fit["tip"]
    if abs(base) < chk["min_amplitude_m"]:
        report.reasons.append(f"the base sensor measured {abs(base) * 1e3:.5f} mm at {chk['tone_hz']:g} Hz, below "
                              f"[check] min_amplitude_m {chk['min_amplitude_m'] * 1e3:g} mm: is the amplifier on "
                              f"and its gain up, is the base sensor aimed at the armature?")
        return report
    ratio = abs(tip) / abs(base)
    deviation = abs(ratio - 1.0)
    phase = math.degrees(float(np.angle(tip / base)))
    report.agreement = {"ratio": ratio, "deviation": deviation, "phase_deg": phase,
                        "tolerance": chk["agreement_tolerance"]}
    if deviation > chk["agreement_tolerance"]:
        report.reasons.append(
            f"the sensors disagree: tip / base amplitude = {ratio:.4f}, {deviation * 100:.2f} % apart, beyond "
            f"[check] agreement_tolerance {chk['agreement_tolerance'] * 100:g} % (with both on the base: a "
            f"sensitivity is wrong, a sensor is not on the base, or a range is set wrong)")
        return report
    report.passed = True
    return report

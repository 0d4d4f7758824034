"""Safety supervision, kept apart from the science (the plans know nothing of it).

The :class:`Supervisor` checks

- every setpoint before it is sent (generator amplitude, drive frequency,
  amplifier gain, step duration): a setpoint beyond a limit is refused
  (:class:`LimitError`), never clipped; the protocol check
  (:meth:`rig.protocol.Protocol.check_against_limits`) uses the same checks
  before anything moves;
- every acquired block while the output runs (interlocks): base and tip
  displacement about their rest readings (always metres: a velocity sensor's
  readings arrive integrated, :class:`rig.instruments.VelocityIntegrator`), sensor flags (out of range, signal
  loss), the amplifier's measured output current and its fault bits.

A crossed interlock returns a :class:`Trip` naming the limit, the measured
value and the sample; the runner then ramps the output to zero, mutes the
amplifier and records why. Independently, the amplifier's own over-current
trip and its comms watchdog (fed by the heartbeat in :mod:`rig.instruments`)
mute the output in hardware when the controller cannot.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.signal_generator import FREQ_RANGE as GENERATOR_FREQUENCY_RANGE


class LimitError(Exception):
    """A setpoint that the configured limits do not allow."""


@dataclass(frozen=True)
class Trip:
    """Why an interlock tripped."""

    limit: str      # the config field (or "sensor_flags", "amplifier_fault")
    message: str
    index: int      # sample index (since the common trigger) where it was seen

    def __str__(self) -> str:
        return self.message


FLAG_NAMES = {1: "out of range", 2: "signal loss"}


def _flag_text(bits: int) -> str:
    names = [name for bit, name in FLAG_NAMES.items() if bits & bit]
    return " and ".join(names) or f"flag 0x{bits:02x}"


class Supervisor:
    """Checks setpoints and acquired blocks against ``limits`` (the rig config's ``[limits]``)."""

    def __init__(self, limits: dict):
        self.limits = dict(limits)
        self.rest = {"x_base": 0.0, "x_tip": 0.0}
        self.peak = {"x_base": 0.0, "x_tip": 0.0, "current": 0.0}

    def set_rest(self, x_base: float, x_tip: float) -> None:
        """Readings at rest (output off): displacement limits apply about these."""
        self.rest = {"x_base": float(x_base), "x_tip": float(x_tip)}

    def check_amplitude(self, vpp: float) -> None:
        vmax = self.limits["max_generator_vpp"]
        if vpp > vmax * (1 + 1e-12):
            raise LimitError(f"generator amplitude {vpp:g} Vpp exceeds limits.max_generator_vpp = {vmax:g} Vpp")

    def check_frequency(self, hz: float) -> None:
        low, high = GENERATOR_FREQUENCY_RANGE
        if not low <= hz <= high:
            raise LimitError(f"drive frequency {hz:g} Hz is outside the generator's range {low:g}..{high:g} Hz")
        fmax = self.limits["max_drive_frequency_hz"]
        if hz > fmax * (1 + 1e-12):
            raise LimitError(f"drive frequency {hz:g} Hz exceeds limits.max_drive_frequency_hz = {fmax:g} Hz "
                             f"(at most the sensors' sample rate / 20)")

    def check_duration(self, seconds: float) -> None:
        tmax = self.limits["max_step_duration_s"]
        if seconds > tmax:
            raise LimitError(f"step duration {seconds:g} s exceeds limits.max_step_duration_s = {tmax:g} s")

    def check_gain(self, gain: float) -> None:
        gmax = self.limits["max_amplifier_gain"]
        if gain > gmax * (1 + 1e-12):
            raise LimitError(f"amplifier gain {gain:g} exceeds limits.max_amplifier_gain = {gmax:g}")

    def check_block(self, block) -> Trip | None:
        """Interlocks on one acquired block (see :class:`rig.instruments.Block`)."""
        for ch, flags in (("x_base", block.flags_base), ("x_tip", block.flags_tip)):
            if flags.size and flags.any():
                i = int(np.flatnonzero(flags)[0])
                sensor = "sensor_base" if ch == "x_base" else "sensor_tip"
                return Trip("sensor_flags", f"{sensor}: {_flag_text(int(flags[i]))} at sample {block.index0 + i}",
                            block.index0 + i)
        for ch, values, key in (("x_base", block.x_base, "max_base_displacement_m"),
                                ("x_tip", block.x_tip, "max_tip_displacement_m")):
            if not values.size:
                continue
            dev = np.abs(values - self.rest[ch])
            i = int(np.argmax(dev))
            self.peak[ch] = max(self.peak[ch], float(dev[i]))
            if dev[i] > self.limits[key]:
                point = ch.split("_")[1]
                how = (f" (displacement integrated from sensor_{point}'s velocity)"
                       if f"v_{point}" in getattr(block, "measured", {}) else "")
                return Trip(key, f"|{ch}| = {dev[i] * 1e3:.3f} mm exceeds limits.{key} = "
                                 f"{self.limits[key] * 1e3:g} mm at sample {block.index0 + i}{how}", block.index0 + i)
        end = block.index0 + block.x_base.size
        if block.current_a is not None:
            self.peak["current"] = max(self.peak["current"], abs(block.current_a))
            if abs(block.current_a) > self.limits["max_amplifier_current_a"]:
                return Trip("max_amplifier_current_a",
                            f"amplifier output current {abs(block.current_a):.3f} A exceeds "
                            f"limits.max_amplifier_current_a = {self.limits['max_amplifier_current_a']:g} A", end)
        if block.amplifier_faults:
            return Trip("amplifier_fault", f"amplifier fault: {', '.join(block.amplifier_faults)}", end)
        return None

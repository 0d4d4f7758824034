"""Driver for the shaker power amplifier with the shakerlab register map, over Modbus TCP.

Register map: see docs/protocols.md (the simulated amplifier implements it).
Errors, timeouts and the reconnect policy are those of the transport,
:class:`drivers.modbus_link.ModbusTcpInstrument`.  An amplifier with another
register map: :mod:`drivers.modbus_amplifier`.
"""
from __future__ import annotations

from dataclasses import dataclass

from drivers.base import MalformedReply, Register, SettingRangeError, in_range
from drivers.modbus_link import MODBUS_EXCEPTIONS, ModbusTcpInstrument

STATUS_ACTIVE, STATUS_OVER_CURRENT, STATUS_OVER_TEMPERATURE, STATUS_CLIP, STATUS_WATCHDOG = 1, 2, 4, 8, 16
MAX_WATCHDOG_S = 60.0
REG_IDENT, N_IDENT = 32, 16


@dataclass(frozen=True)
class AmplifierFaults:
    over_current: bool
    over_temperature: bool
    clip: bool
    watchdog: bool

    @property
    def any(self) -> bool:
        return self.over_current or self.over_temperature or self.clip or self.watchdog

    def names(self) -> list[str]:
        return [n for n in ("over_current", "over_temperature", "clip", "watchdog") if getattr(self, n)]


class PowerAmplifier(ModbusTcpInstrument):
    """The register map (docs/protocols.md), one property per register."""

    name = "power amplifier"

    enabled = Register(0, "ENABLE", "Output stage enabled (muted when False).", kind=bool)
    gain = Register(1, "GAIN", "Gain, 0..max_gain, resolution 0.001.", scale=1000,
                    bounds=lambda amp: (0.0, amp.max_gain))
    current_limit = Register(2, "CURRENT_LIMIT", "Over-current trip level [A], resolution 1 mA.", scale=1000,
                             bounds=lambda amp: (0.001, amp.max_current_limit), unit=" A")
    watchdog_timeout = Register(3, "WATCHDOG_TIMEOUT", "Comms watchdog [s]; 0 = off.  The output mutes when "
                                "the master is silent for longer (while enabled).", scale=1000,
                                validator=in_range(0.0, MAX_WATCHDOG_S, " s"))
    fault_reset = Register(4, "FAULT_RESET", "Write 1: clear latched faults (reads 0).", kind=int)
    heartbeat_count = Register(5, "HEARTBEAT", "Any value; a cheap request for the watchdog.", kind=int)
    status = Register(16, "STATUS", "Bits: output active, over-current, over-temperature, clip, watchdog.",
                      kind=int, writable=False)
    output_current = Register(17, "OUTPUT_CURRENT", "Measured output current [A].", scale=1000, signed=True,
                              writable=False)
    output_voltage = Register(18, "OUTPUT_VOLTAGE", "Measured output voltage [V].", scale=100, signed=True,
                              writable=False)
    temperature = Register(19, "TEMPERATURE", "Output-stage temperature [degC].", scale=10, signed=True,
                           writable=False)
    max_gain = Register(20, "MAX_GAIN", "Highest gain the device accepts.", scale=1000, writable=False,
                        cached=True)
    max_current_limit = Register(21, "MAX_CURRENT_LIMIT", "Highest current limit the device accepts [A].",
                                 scale=1000, writable=False, cached=True)

    @property
    def faults(self) -> AmplifierFaults:
        s = self.status
        return AmplifierFaults(bool(s & STATUS_OVER_CURRENT), bool(s & STATUS_OVER_TEMPERATURE),
                               bool(s & STATUS_CLIP), bool(s & STATUS_WATCHDOG))

    @property
    def output_active(self) -> bool:
        """True when the output stage is enabled and not muted by a fault."""
        return bool(self.status & STATUS_ACTIVE)

    # ---- methods --------------------------------------------------------------------------------
    def identify(self) -> str:
        regs = self._read(REG_IDENT, N_IDENT, "IDENT")
        raw = b"".join(bytes([(r >> 8) & 0xFF, r & 0xFF]) for r in regs)
        try:
            return raw.decode("ascii").rstrip(" \x00")
        except UnicodeDecodeError:
            raise MalformedReply(self.name, "read IDENT", f"non-ASCII identification {raw!r}") from None

    def reset_faults(self) -> None:
        """Clear latched faults (over-temperature stays until the stage has cooled)."""
        self.fault_reset = 1

    def heartbeat(self) -> None:
        """Tell the watchdog the master is alive (any request does; this is the cheapest)."""
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        self.heartbeat_count = self._heartbeat

    def check_errors(self) -> list[str]:
        """Names of the active (latched) faults; [] when healthy."""
        return self.faults.names()

    def safe_state(self) -> None:
        """Disable the output and set the gain to 0 (one request)."""
        self._write_regs(PowerAmplifier.enabled.address, [0, 0])



__all__ = ["PowerAmplifier", "AmplifierFaults", "SettingRangeError", "MODBUS_EXCEPTIONS"]

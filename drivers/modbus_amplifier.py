"""Driver for a power amplifier with a vendor Modbus TCP register map, declared as data.

Many amplifiers with remote control speak Modbus but each with its own map.
:class:`RegisterMap` declares it (addresses of the holding registers, their
scaling, the enable/mute values, the watchdog if the amplifier has one);
:func:`modbus_amplifier` builds a driver whose properties are
:class:`~drivers.base.Register` declarations at those addresses, so the
properties validate before sending exactly like the built-in map's
(:mod:`drivers.power_amplifier`).  Only the enable register is required; a
property whose register is not declared raises ``AttributeError`` naming it.
"""
from __future__ import annotations

from dataclasses import dataclass

from drivers.base import MalformedReply, Register, in_range, int_range
from drivers.modbus_link import ModbusTcpInstrument

MAX_WATCHDOG_S = 60.0


@dataclass(frozen=True)
class RegisterMap:
    """Holding-register addresses (0..65535) and scaling; ``None``: the amplifier has no such register.

    ``enable``: written ``enable_on`` to let the output through, ``enable_off`` to mute it.
    ``gain``: raw = gain x ``gain_scale``, 0..``gain_max``. ``watchdog``: the comms-watchdog
    timeout, raw = seconds x ``watchdog_scale``. ``heartbeat``: any write counts as master
    activity. ``current``: measured output current, A = raw / ``current_scale`` (int16 when
    ``current_signed``). ``status``: the bits in ``fault_bits`` mean a fault. ``fault_reset``:
    written 1 to clear latched faults. ``ident``: ``ident_registers`` registers of ASCII, two
    characters each (high byte first).
    """

    enable: int
    enable_on: int = 1
    enable_off: int = 0
    gain: int | None = None
    gain_scale: float = 1.0
    gain_max: float | None = None
    watchdog: int | None = None
    watchdog_scale: float = 1000.0
    heartbeat: int | None = None
    current: int | None = None
    current_scale: float = 1000.0
    current_signed: bool = True
    status: int | None = None
    fault_bits: int = 0xFFFF
    fault_reset: int | None = None
    ident: int | None = None
    ident_registers: int = 16

    def __post_init__(self):
        for name in ("enable", "gain", "watchdog", "heartbeat", "current", "status", "fault_reset", "ident"):
            value = getattr(self, name)
            if value is not None:
                int_range(0, 0xFFFF)("register map", name, value)
        for name in ("enable_on", "enable_off", "fault_bits"):
            int_range(0, 0xFFFF)("register map", name, getattr(self, name))
        if self.enable_on == self.enable_off:
            raise ValueError("register map: enable_on and enable_off must differ")
        for name in ("gain_scale", "watchdog_scale", "current_scale"):
            in_range(1e-9, 1e9)("register map", name, getattr(self, name))
        if self.gain is not None and self.gain_max is None:
            raise ValueError("register map: a gain register needs gain_max (the highest gain it accepts)")
        if self.gain_max is not None and not 0 < self.gain_max <= 0xFFFF / self.gain_scale:
            raise ValueError(f"register map: gain_max {self.gain_max:g} does not fit the register "
                             f"(0 < gain_max <= {0xFFFF / self.gain_scale:g} at gain_scale {self.gain_scale:g})")
        int_range(1, 64)("register map", "ident_registers", self.ident_registers)


class ModbusAmplifier(ModbusTcpInstrument):
    """An amplifier with a declared register map; build one with :func:`modbus_amplifier`."""

    name = "power amplifier"
    register_map: RegisterMap

    def __init__(self, address: str, device_id: int = 1, timeout: float = 1.0, **options):
        super().__init__(address, device_id=device_id, timeout=timeout, **options)

    @property
    def enabled(self) -> bool:
        """Output let through (True) or muted (False): the enable register's on/off value."""
        m = self.register_map
        raw = self._read(m.enable, 1, "ENABLE")[0]
        if raw not in (m.enable_on, m.enable_off):
            raise MalformedReply(self.name, "read ENABLE", f"register {m.enable} holds {raw}, neither enable_on "
                                                          f"{m.enable_on} nor enable_off {m.enable_off}")
        return raw == m.enable_on

    @enabled.setter
    def enabled(self, value: bool) -> None:
        if not isinstance(value, bool):
            raise TypeError(f"{self.name}: enabled expects True or False, got {value!r}")
        m = self.register_map
        self._write_register(m.enable, m.enable_on if value else m.enable_off, "ENABLE")

    @property
    def max_gain(self) -> float | None:
        return self.register_map.gain_max

    @property
    def has_watchdog(self) -> bool:
        return self.register_map.watchdog is not None

    def identify(self) -> str:
        m = self.register_map
        if m.ident is None:
            return f"Modbus amplifier at {self.address} (device {self.device_id}; no identity register declared)"
        regs = self._read(m.ident, m.ident_registers, "IDENT")
        raw = b"".join(bytes([(r >> 8) & 0xFF, r & 0xFF]) for r in regs)
        try:
            return raw.decode("ascii").rstrip(" \x00")
        except UnicodeDecodeError:
            raise MalformedReply(self.name, "read IDENT", f"non-ASCII identification {raw!r}") from None

    def heartbeat(self) -> None:
        """Tell the watchdog the master is alive (the heartbeat register, or a read of ENABLE)."""
        if self.register_map.heartbeat is None:
            _ = self.enabled
            return
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        self.heartbeat_count = self._heartbeat

    def reset_faults(self) -> None:
        if self.register_map.fault_reset is not None:
            self.fault_reset = 1

    @property
    def output_current(self) -> float | None:
        """Measured output current [A]; None when the map has no current register."""
        if self.register_map.current is None:
            return None
        return self.current_register

    def check_errors(self) -> list[str]:
        """The fault bits set in the status register (``fault_bits``); [] when healthy or undeclared."""
        if self.register_map.status is None:
            return []
        bits = self.status & self.register_map.fault_bits
        return [f"status bit {b}" for b in range(16) if bits >> b & 1]

    def safe_state(self) -> None:
        """Mute (enable register off), then the gain to 0 when the map has a gain register."""
        self.enabled = False
        if self.register_map.gain is not None:
            self.gain = 0.0


def _absent(name: str, what: str):
    def get(self):
        raise AttributeError(f"{self.name}: the register map declares no {what} register ({name})")
    return property(get, lambda self, value: get(self))


def modbus_amplifier(address: str, register_map: RegisterMap, device_id: int = 1, timeout: float = 1.0,
                     **options) -> ModbusAmplifier:
    """A connected :class:`ModbusAmplifier` whose properties are the declared registers."""
    m = register_map
    attrs = {"register_map": m}
    if m.gain is not None:
        attrs["gain"] = Register(m.gain, "GAIN", "Gain, 0..gain_max.", scale=m.gain_scale,
                                 validator=in_range(0.0, m.gain_max))
    else:
        attrs["gain"] = _absent("gain", "gain")
    if m.watchdog is not None:
        attrs["watchdog_timeout"] = Register(m.watchdog, "WATCHDOG_TIMEOUT", "Comms watchdog [s]; 0 = off.",
                                             scale=m.watchdog_scale,
                                             validator=in_range(0.0, min(MAX_WATCHDOG_S, 0xFFFF / m.watchdog_scale),
                                                                " s"))
    else:
        attrs["watchdog_timeout"] = _absent("watchdog", "watchdog")
    if m.heartbeat is not None:
        attrs["heartbeat_count"] = Register(m.heartbeat, "HEARTBEAT", "Any value: master activity.", kind=int)
    if m.current is not None:
        attrs["current_register"] = Register(m.current, "OUTPUT_CURRENT", "Measured output current [A].",
                                             scale=m.current_scale, signed=m.current_signed, writable=False)
    if m.status is not None:
        attrs["status"] = Register(m.status, "STATUS", "Fault bits (fault_bits).", kind=int, writable=False)
    if m.fault_reset is not None:
        attrs["fault_reset"] = Register(m.fault_reset, "FAULT_RESET", "Write 1: clear latched faults.", kind=int)
    cls = type("DeclaredModbusAmplifier", (ModbusAmplifier,), attrs)
    return cls(address, device_id=device_id, timeout=timeout, **options)


__all__ = ["RegisterMap", "ModbusAmplifier", "modbus_amplifier"]

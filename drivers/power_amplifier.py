"""Driver for the shaker power amplifier over Modbus TCP (pymodbus client).

Register map: see docs/protocols.md (the simulated amplifier implements it).
Every request has a timeout; a Modbus exception reply raises
:class:`InstrumentFault`, a lost or refused connection
:class:`InstrumentConnectionError`, no reply :class:`InstrumentTimeout` -- each
naming the register.  Reconnect policy: a lost connection is reopened on the
next call (``reconnect_attempts`` tries); a failed request is not re-sent.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from drivers.base import (Instrument, InstrumentConnectionError, InstrumentFault, InstrumentTimeout,
                          MalformedReply, Register, SettingRangeError, in_range)

STATUS_ACTIVE, STATUS_OVER_CURRENT, STATUS_OVER_TEMPERATURE, STATUS_CLIP, STATUS_WATCHDOG = 1, 2, 4, 8, 16
MAX_WATCHDOG_S = 60.0
REG_IDENT, N_IDENT = 32, 16
MODBUS_EXCEPTIONS = {1: "illegal function", 2: "illegal data address", 3: "illegal data value (out of range)",
                     4: "device failure", 6: "device busy"}


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


class PowerAmplifier(Instrument):
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

    def __init__(self, address: str, device_id: int = 1, timeout: float = 1.0,
                 reconnect_attempts: int = 3, reconnect_delay: float = 0.1):
        host, sep, port = address.rpartition(":")
        if not sep or not host or not port.isdigit():
            raise ValueError(f"{self.name}: address must be 'host:port', got {address!r}")
        if not isinstance(timeout, (int, float)) or not timeout > 0:
            raise ValueError(f"{self.name}: timeout must be > 0 s, got {timeout!r}")
        self.address = address
        self.device_id = device_id
        self.timeout = float(timeout)
        self.reconnect_attempts = reconnect_attempts
        self.reconnect_delay = reconnect_delay
        self._client = ModbusTcpClient(host, port=int(port), timeout=self.timeout, retries=0)
        self._lock = threading.Lock()
        self._heartbeat = 0
        self._connect("connect")

    # ---- transport ---------------------------------------------------------------------------
    def _connect(self, what: str) -> None:
        for attempt in range(max(1, self.reconnect_attempts)):
            if self._client.connect():
                return
            if attempt + 1 < self.reconnect_attempts:
                time.sleep(self.reconnect_delay)
        raise InstrumentConnectionError(self.name, what, f"cannot connect to Modbus TCP {self.address}")

    def _call(self, what: str, func, *args, **kwargs):
        with self._lock:
            if not self._client.connected:
                self._connect(what)
            try:
                rr = func(*args, device_id=self.device_id, **kwargs)
            except ConnectionException as exc:
                self._client.close()
                raise InstrumentConnectionError(self.name, what, f"connection lost: {exc}") from None
            except ModbusIOException as exc:
                self._client.close()
                raise InstrumentTimeout(self.name, what, f"no valid reply within {self.timeout:g} s ({exc})") from None
            except ModbusException as exc:
                self._client.close()
                raise MalformedReply(self.name, what, f"Modbus error: {exc}") from None
            except OSError as exc:
                self._client.close()
                raise InstrumentConnectionError(self.name, what, f"connection lost: {exc}") from None
        if rr.isError():
            code = getattr(rr, "exception_code", None)
            meaning = MODBUS_EXCEPTIONS.get(code, "error")
            raise InstrumentFault(self.name, what, f"Modbus exception {code}: {meaning}")
        return rr

    def _read(self, reg: int, count: int, label: str) -> list[int]:
        what = f"read {label} (register {reg}, count {count})"
        rr = self._call(what, self._client.read_holding_registers, reg, count=count)
        regs = list(getattr(rr, "registers", []) or [])
        if len(regs) != count:
            raise MalformedReply(self.name, what, f"expected {count} register(s), got {len(regs)}")
        return regs

    def _write_register(self, reg: int, value: int, label: str) -> None:
        what = f"write {label} (register {reg}) = {value}"
        self._call(what, self._client.write_register, reg, value)

    def _write_regs(self, reg: int, values: list[int]) -> None:
        what = f"write registers {reg}..{reg + len(values) - 1} = {values}"
        self._call(what, self._client.write_registers, reg, values)

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

    def close(self) -> None:
        with self._lock:
            self._client.close()


__all__ = ["PowerAmplifier", "AmplifierFaults", "SettingRangeError"]

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

from drivers.base import (InstrumentConnectionError, InstrumentFault, InstrumentTimeout,
                          MalformedReply, Setting, SettingRangeError, boolean, in_range)

REG_ENABLE, REG_GAIN, REG_LIMIT, REG_WATCHDOG, REG_RESET, REG_HEARTBEAT = range(6)
REG_STATUS, REG_CURRENT, REG_VOLTAGE, REG_TEMPERATURE, REG_MAX_GAIN, REG_MAX_LIMIT = range(16, 22)
REG_IDENT, N_IDENT = 32, 16
STATUS_ACTIVE, STATUS_OVER_CURRENT, STATUS_OVER_TEMPERATURE, STATUS_CLIP, STATUS_WATCHDOG = 1, 2, 4, 8, 16
MAX_WATCHDOG_S = 60.0
REG_NAMES = {REG_ENABLE: "ENABLE", REG_GAIN: "GAIN", REG_LIMIT: "CURRENT_LIMIT",
             REG_WATCHDOG: "WATCHDOG_TIMEOUT", REG_RESET: "FAULT_RESET", REG_HEARTBEAT: "HEARTBEAT",
             REG_STATUS: "STATUS", REG_CURRENT: "OUTPUT_CURRENT", REG_VOLTAGE: "OUTPUT_VOLTAGE",
             REG_TEMPERATURE: "TEMPERATURE", REG_MAX_GAIN: "MAX_GAIN", REG_MAX_LIMIT: "MAX_CURRENT_LIMIT",
             REG_IDENT: "IDENT"}
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


def _signed(v: int) -> int:
    return v - 0x10000 if v >= 0x8000 else v


class PowerAmplifier:
    name = "power amplifier"

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
        self._limits: tuple[float, float] | None = None
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

    def _read(self, reg: int, count: int = 1) -> list[int]:
        what = f"read {REG_NAMES.get(reg, reg)} (register {reg}, count {count})"
        rr = self._call(what, self._client.read_holding_registers, reg, count=count)
        regs = list(getattr(rr, "registers", []) or [])
        if len(regs) != count:
            raise MalformedReply(self.name, what, f"expected {count} register(s), got {len(regs)}")
        return regs

    def _write_reg(self, reg: int, value: int) -> None:
        what = f"write {REG_NAMES.get(reg, reg)} (register {reg}) = {value}"
        self._call(what, self._client.write_register, reg, value)

    def _write_regs(self, reg: int, values: list[int]) -> None:
        what = f"write registers {reg}..{reg + len(values) - 1} = {values}"
        self._call(what, self._client.write_registers, reg, values)

    # ---- device limits (read once from the device) ----------------------------------------------
    def _device_limits(self) -> tuple[float, float]:
        if self._limits is None:
            g, i = self._read(REG_MAX_GAIN, 2)
            self._limits = (g / 1000.0, i / 1000.0)
        return self._limits

    def _set_gain(self, value: float) -> None:
        max_gain = self._device_limits()[0]
        in_range(0.0, max_gain)(self.name, "gain", value)
        self._write_reg(REG_GAIN, int(round(value * 1000)))

    def _set_limit(self, value: float) -> None:
        max_limit = self._device_limits()[1]
        in_range(0.001, max_limit, " A")(self.name, "current_limit", value)
        self._write_reg(REG_LIMIT, int(round(value * 1000)))

    # ---- settings ----------------------------------------------------------------------------
    enabled = Setting(lambda s: bool(s._read(REG_ENABLE)[0]),
                      lambda s, v: s._write_reg(REG_ENABLE, int(v)), boolean,
                      doc="Output stage enabled (muted when False).")
    gain = Setting(lambda s: s._read(REG_GAIN)[0] / 1000.0, lambda s, v: s._set_gain(v),
                   doc="Gain, 0..max_gain, resolution 0.001.")
    current_limit = Setting(lambda s: s._read(REG_LIMIT)[0] / 1000.0, lambda s, v: s._set_limit(v),
                            doc="Over-current trip level [A], resolution 1 mA.")
    watchdog_timeout = Setting(lambda s: s._read(REG_WATCHDOG)[0] / 1000.0,
                               lambda s, v: s._write_reg(REG_WATCHDOG, int(round(v * 1000))),
                               in_range(0.0, MAX_WATCHDOG_S, " s"),
                               doc="Comms watchdog [s]; 0 = off.  The output mutes when the "
                                   "master is silent for longer (while enabled).")
    output_current = Setting(lambda s: _signed(s._read(REG_CURRENT)[0]) / 1000.0,
                             doc="Measured output current [A] (read only).")
    output_voltage = Setting(lambda s: _signed(s._read(REG_VOLTAGE)[0]) / 100.0,
                             doc="Measured output voltage [V] (read only).")
    temperature = Setting(lambda s: _signed(s._read(REG_TEMPERATURE)[0]) / 10.0,
                          doc="Output-stage temperature [degC] (read only).")

    @property
    def max_gain(self) -> float:
        return self._device_limits()[0]

    @property
    def max_current_limit(self) -> float:
        return self._device_limits()[1]

    @property
    def faults(self) -> AmplifierFaults:
        s = self._read(REG_STATUS)[0]
        return AmplifierFaults(bool(s & STATUS_OVER_CURRENT), bool(s & STATUS_OVER_TEMPERATURE),
                               bool(s & STATUS_CLIP), bool(s & STATUS_WATCHDOG))

    @property
    def output_active(self) -> bool:
        """True when the output stage is enabled and not muted by a fault."""
        return bool(self._read(REG_STATUS)[0] & STATUS_ACTIVE)

    # ---- methods --------------------------------------------------------------------------------
    def identify(self) -> str:
        regs = self._read(REG_IDENT, N_IDENT)
        raw = b"".join(bytes([(r >> 8) & 0xFF, r & 0xFF]) for r in regs)
        try:
            return raw.decode("ascii").rstrip(" \x00")
        except UnicodeDecodeError:
            raise MalformedReply(self.name, "read IDENT", f"non-ASCII identification {raw!r}") from None

    def reset_faults(self) -> None:
        """Clear latched faults (over-temperature stays until the stage has cooled)."""
        self._write_reg(REG_RESET, 1)

    def heartbeat(self) -> None:
        """Tell the watchdog the master is alive (any request does; this is the cheapest)."""
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        self._write_reg(REG_HEARTBEAT, self._heartbeat)

    def check_errors(self) -> list[str]:
        """Names of the active (latched) faults; [] when healthy."""
        return self.faults.names()

    def safe_state(self) -> None:
        """Disable the output and set the gain to 0 (one request)."""
        self._write_regs(REG_ENABLE, [0, 0])

    def close(self) -> None:
        with self._lock:
            self._client.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


__all__ = ["PowerAmplifier", "AmplifierFaults", "SettingRangeError"]

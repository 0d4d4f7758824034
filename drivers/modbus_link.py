"""Modbus TCP transport of the register-based drivers (pymodbus client).

:class:`ModbusTcpInstrument` gives a driver the ``_read`` / ``_write_register``
primitives its :class:`~drivers.base.Register` properties use.  Every request
has a timeout; a Modbus exception reply raises :class:`InstrumentFault`, a
lost or refused connection :class:`InstrumentConnectionError`, no reply
:class:`InstrumentTimeout` -- each naming the register.  Reconnect policy: a
lost connection is reopened on the next call (``reconnect_attempts`` tries); a
failed request is not re-sent.
"""
from __future__ import annotations

import threading
import time

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from drivers.base import Instrument, InstrumentConnectionError, InstrumentFault, InstrumentTimeout, MalformedReply

MODBUS_EXCEPTIONS = {1: "illegal function", 2: "illegal data address", 3: "illegal data value (out of range)",
                     4: "device failure", 6: "device busy"}


class ModbusTcpInstrument(Instrument):
    """A Modbus TCP device at ``host:port`` (``device_id``: the unit id)."""

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

    def close(self) -> None:
        with self._lock:
            self._client.close()

"""Simulated power amplifier: a Modbus TCP device served by a real pymodbus server.

Register map (holding registers, device id 1 by default; the read-only block is
also readable with function 4).  See docs/protocols.md.

====  =================  =====  ==========================================
addr  name               access meaning
====  =================  =====  ==========================================
0     ENABLE             rw     0 = output off, 1 = on
1     GAIN               rw     gain x 1000 (0 .. max_gain x 1000)
2     CURRENT_LIMIT      rw     over-current trip level [mA] (1 .. max)
3     WATCHDOG_TIMEOUT   rw     comms watchdog [ms], 0 = off (max 60000)
4     FAULT_RESET        w      write 1: clear latched faults (reads 0)
5     HEARTBEAT          rw     any write counts as master activity
16    STATUS             r      bit0 output active, bit1 over-current,
                                bit2 over-temperature, bit3 clip, bit4 watchdog
17    OUTPUT_CURRENT     r      int16 [mA]
18    OUTPUT_VOLTAGE     r      int16 [10 mV]
19    TEMPERATURE        r      [0.1 degC]
20    MAX_GAIN           r      x 1000
21    MAX_CURRENT_LIMIT  r      [mA]
32-47 IDENT              r      ASCII, two characters per register (high byte first)
====  =================  =====  ==========================================

Every request counts as master activity for the watchdog.  The watchdog runs in
wall-clock time and only while the output is enabled: when the master is silent
for longer than WATCHDOG_TIMEOUT the output is muted and the watchdog fault
latches until FAULT_RESET.
"""
from __future__ import annotations

import asyncio
import threading
import time

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from sim_backend import physics as ph

IDENT = "shakerlab SIM-PA100 amplifier"
REG_ENABLE, REG_GAIN, REG_LIMIT, REG_WATCHDOG, REG_RESET, REG_HEARTBEAT = range(6)
REG_STATUS, REG_CURRENT, REG_VOLTAGE, REG_TEMPERATURE, REG_MAX_GAIN, REG_MAX_LIMIT = range(16, 22)
REG_IDENT, N_IDENT = 32, 16
MAX_WATCHDOG_MS = 60000


def _int16(v: float) -> int:
    n = int(round(v))
    n = max(-32768, min(32767, n))
    return n & 0xFFFF


class SimPowerAmplifier:
    def __init__(self, world, device_id: int = 1, host: str = "127.0.0.1", port: int = 0):
        self.world = world
        self.device_id = device_id
        self.host = host
        self.port = port
        amp = world.config["amplifier"]
        self.max_gain = float(amp["max_gain"])
        self.max_limit = float(amp["max_current_limit"])
        self.watchdog_timeout = float(amp["watchdog_timeout"])
        self.last_activity = time.monotonic()
        self.alive = False
        self.requests = 0
        self.response_delay = 0.0  # test hook: seconds each request takes (timeouts, kill mid-request)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: ModbusTcpServer | None = None
        self._thread: threading.Thread | None = None
        self._wd_thread: threading.Thread | None = None
        ident = IDENT.ljust(2 * N_IDENT)[: 2 * N_IDENT].encode("ascii")
        ident_regs = [(ident[2 * k] << 8) | ident[2 * k + 1] for k in range(N_IDENT)]
        self.device = SimDevice(
            device_id,
            simdata=[
                SimData(REG_ENABLE, values=[0, 0, int(round(amp["current_limit"] * 1000)),
                                            int(round(self.watchdog_timeout * 1000)), 0, 0],
                        datatype=DataType.REGISTERS),
                SimData(REG_STATUS, count=6, values=0, datatype=DataType.REGISTERS, readonly=True),
                SimData(REG_IDENT, values=ident_regs, datatype=DataType.REGISTERS, readonly=True),
            ],
            action=self._action,
        )

    # ---- lifecycle --------------------------------------------------------------------
    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def start(self) -> "SimPowerAmplifier":
        ready = threading.Event()
        error: list[BaseException] = []

        def run():
            async def main():
                try:
                    self._server = ModbusTcpServer(self.device, address=(self.host, self.port))
                    await self._server.serve_forever(background=True)
                    self.port = self._server.transport.sockets[0].getsockname()[1]
                except BaseException as exc:  # noqa: BLE001 - reported to the starting thread
                    error.append(exc)
                    ready.set()
                    return
                self._loop = asyncio.get_running_loop()
                self.alive = True
                ready.set()
                await self._server.serving
            asyncio.run(main())

        self._thread = threading.Thread(target=run, name="sim-amplifier", daemon=True)
        self._thread.start()
        if not ready.wait(10.0):
            raise RuntimeError("simulated amplifier: Modbus server did not start")
        if error:
            raise OSError(f"amplifier: cannot listen on {self.host}:{self.port}: Modbus server failed ({error[0]})")
        self.last_activity = time.monotonic()
        self._wd_thread = threading.Thread(target=self._watchdog_loop, name="sim-amp-watchdog",
                                           daemon=True)
        self._wd_thread.start()
        return self

    def kill(self) -> None:
        """Abrupt power-off: the server goes away and the output is muted."""
        if not self.alive:
            return
        self.alive = False

        def mute():
            self.world.amplifier_alive = False
            self.world.A[ph.A_ENABLE] = 0.0
        self.world.apply(mute)
        if self._loop is not None and self._server is not None:
            fut = asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop)
            try:
                fut.result(timeout=5.0)
            except Exception:  # noqa: BLE001 - shutting down anyway
                pass
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    stop = kill

    # ---- watchdog (wall clock) -----------------------------------------------------------
    def _watchdog_loop(self) -> None:
        while self.alive:
            time.sleep(0.01)
            timeout = self.watchdog_timeout
            if timeout <= 0:
                continue
            if time.monotonic() - self.last_activity > timeout:
                def trip():
                    A = self.world.A
                    if A[ph.A_ENABLE] != 0.0 and A[ph.A_WD] == 0.0:
                        A[ph.A_WD] = 1.0
                self.world.apply(trip)

    # ---- Modbus ----------------------------------------------------------------------------
    async def _action(self, function_code, start_address, address, count, registers, set_values):
        self.last_activity = time.monotonic()
        self.requests += 1
        if self.response_delay > 0:
            await asyncio.sleep(self.response_delay)
        if set_values is not None:
            return self._write(address, set_values, registers, start_address)
        if address + count > REG_STATUS and address < REG_IDENT:
            self._refresh(registers, start_address)
        return None

    def _refresh(self, registers, start) -> None:
        def read():
            A, X = self.world.A, self.world.X
            status = 0
            active = (A[ph.A_ENABLE] != 0 and A[ph.A_OC] == 0 and A[ph.A_OT] == 0 and A[ph.A_WD] == 0)
            status |= 1 if active else 0
            status |= 2 if A[ph.A_OC] else 0
            status |= 4 if A[ph.A_OT] else 0
            status |= 8 if A[ph.A_CLIP] else 0
            status |= 16 if A[ph.A_WD] else 0
            return status, A[ph.A_I], A[ph.A_V], X[ph.X_T]
        status, current, voltage, temp = self.world.apply(read)
        registers[REG_STATUS - start] = status
        registers[REG_CURRENT - start] = _int16(current * 1000)
        registers[REG_VOLTAGE - start] = _int16(voltage * 100)
        registers[REG_TEMPERATURE - start] = _int16(temp * 10)
        registers[REG_MAX_GAIN - start] = int(round(self.max_gain * 1000))
        registers[REG_MAX_LIMIT - start] = int(round(self.max_limit * 1000))

    def _write(self, address, values, registers, start):
        # validate everything first: a rejected request changes nothing
        for k, v in enumerate(values):
            reg = address + k
            if reg == REG_ENABLE and v not in (0, 1):
                return ExcCodes.ILLEGAL_VALUE
            if reg == REG_GAIN and v > self.max_gain * 1000:
                return ExcCodes.ILLEGAL_VALUE
            if reg == REG_LIMIT and not 1 <= v <= self.max_limit * 1000:
                return ExcCodes.ILLEGAL_VALUE
            if reg == REG_WATCHDOG and v > MAX_WATCHDOG_MS:
                return ExcCodes.ILLEGAL_VALUE
            if reg == REG_RESET and v not in (0, 1):
                return ExcCodes.ILLEGAL_VALUE
        for k, v in enumerate(values):
            reg = address + k
            if reg == REG_ENABLE:
                self.world.apply(lambda v=v: self.world.A.__setitem__(ph.A_ENABLE, float(v)))
            elif reg == REG_GAIN:
                self.world.apply(lambda v=v: self.world.A.__setitem__(ph.A_GAIN, v / 1000.0))
            elif reg == REG_LIMIT:
                self.world.apply(lambda v=v: self.world.A.__setitem__(ph.A_LIMIT, v / 1000.0))
            elif reg == REG_WATCHDOG:
                self.watchdog_timeout = v / 1000.0
            elif reg == REG_RESET and v == 1:
                self.world.apply(self._reset_faults)
                values[k] = 0
        return None

    def front_panel(self, gain: float, enabled: bool = True) -> None:
        """The operator's hands on the front panel: gain knob and output switch (a manual amplifier)."""
        if not 0.0 <= gain <= self.max_gain:
            raise ValueError(f"simulated amplifier: front-panel gain {gain:g} is outside 0..{self.max_gain:g}")

        def set_panel():
            self.world.A[ph.A_GAIN] = float(gain)
            self.world.A[ph.A_ENABLE] = 1.0 if enabled else 0.0
        self.world.apply(set_panel)

    def _reset_faults(self) -> None:
        A, X = self.world.A, self.world.X
        A[ph.A_OC] = 0.0
        A[ph.A_CLIP] = 0.0
        A[ph.A_WD] = 0.0
        # over-temperature only clears once the stage has cooled below the trip level by
        # 5 K (or half the way to ambient when that is less)
        P = self.world.P
        hysteresis = min(5.0, 0.5 * (P[ph.P_TMAX] - P[ph.P_TAMB]))
        if X[ph.X_T] < P[ph.P_TMAX] - hysteresis:
            A[ph.A_OT] = 0.0

"""Each driver pinned to its manual (docs/protocols.md), independently of the simulator.

Line instruments: a scripted peer on a real loopback socket (or a real pty) records the exact
bytes the driver sends and answers with scripted bytes (PyMeasure's ``expected_protocol`` idea).
Modbus: a real pymodbus server over a plain register datastore records every request.
"""
import asyncio
import math
import os
import socket
import threading
import tty

import pytest
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.base import InstrumentFault, SettingRangeError
from drivers.laser_sensor import FLAG_OUT_OF_RANGE, FLAG_SIGNAL_LOSS, LaserSensor
from drivers.power_amplifier import PowerAmplifier
from drivers.signal_generator import SignalGenerator

NO_ERROR = b'+0,"No error"\n'


class ScriptedPeer:
    """Answers each expected request (bytes up to and including ``terminator``) with its scripted
    reply; records everything received. Over TCP (``url``) or a pty (``pty_path``)."""

    def __init__(self, script: list[tuple[bytes, bytes]], terminator: bytes, use_pty: bool = False):
        self.script = list(script)
        self.terminator = terminator
        self.received = bytearray()
        self.mismatch: str | None = None
        if use_pty:
            master, slave = os.openpty()
            tty.setraw(slave)
            self._fd, self._slave = master, slave
            self.url = os.ttyname(slave)
            self._recv, self._send = (lambda: os.read(master, 4096)), (lambda b: os.write(master, b))
            self._listener = None
        else:
            self._listener = socket.create_server(("127.0.0.1", 0))
            self.url = f"socket://127.0.0.1:{self._listener.getsockname()[1]}"
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self):
        if self._listener is not None:
            self._listener.settimeout(5)
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return
            conn.settimeout(5)
            self._recv, self._send = (lambda: conn.recv(4096)), conn.sendall
        buf = b""
        for request, reply in self.script:
            while self.terminator not in buf:
                try:
                    data = self._recv()
                except OSError:
                    return
                if not data:
                    return
                buf += data
                self.received += data
            got, _, buf = buf.partition(self.terminator)
            if got + self.terminator != request:
                self.mismatch = f"expected {request!r}, got {got + self.terminator!r}"
                return
            self._send(reply)
        while True:  # anything after the script is recorded (and fails the test)
            try:
                data = self._recv()
            except OSError:
                return
            if not data:
                return
            self.received += data

    def sent_by_driver(self) -> bytes:
        return bytes(self.received)

    def release_pty(self):
        """After the driver has closed the pty: close this end's copy of the slave too, so the peer
        reads what the driver sent and then gets EIO (the end) instead of blocking until close."""
        if self._listener is None and self._slave is not None:
            os.close(self._slave)
            self._slave = None

    def close(self):
        if self._listener is not None:
            self._listener.close()
        else:
            self.release_pty()
            os.close(self._fd)


def expect(driver_cls, script, terminator, use_pty=False, **options):
    peer = ScriptedPeer(script, terminator, use_pty)
    return peer, driver_cls(peer.url, timeout=1.0, reconnect_attempts=1, **options)


def finish(peer, driver, script):
    driver.close()
    peer.release_pty()
    peer._thread.join(2)
    peer.close()
    assert peer.mismatch is None, peer.mismatch
    assert peer.sent_by_driver() == b"".join(request for request, _ in script)


# ---- signal generator (SCPI, LF) ------------------------------------------------------------------

GENERATOR_EXCHANGES = [
    (lambda g: setattr(g, "frequency", 14.2), [(b"FREQ 14.2;:SYST:ERR?\n", NO_ERROR)], None),
    (lambda g: g.frequency, [(b"FREQ?\n", b"+1.42000000000000E+01\n")], 14.2),
    (lambda g: setattr(g, "amplitude", 0.25), [(b"VOLT 0.25;:SYST:ERR?\n", NO_ERROR)], None),
    (lambda g: setattr(g, "offset", 0.0), [(b"VOLT:OFFS 0;:SYST:ERR?\n", NO_ERROR)], None),
    (lambda g: setattr(g, "output", True), [(b"OUTP ON;:SYST:ERR?\n", NO_ERROR)], None),
    (lambda g: g.output, [(b"OUTP?\n", b"0\n")], False),
    (lambda g: g.identify(), [(b"*IDN?\n", b"maker,model,serial,fw\n")], "maker,model,serial,fw"),
    (lambda g: g.reset(), [(b"*RST;*CLS;*OPC?\n", b"1\n")], None),
    (lambda g: g.trigger(), [(b"*TRG;*OPC?\n", b"1\n")], None),
    (lambda g: g.set_voltage_limits(-3.0, 3.0),
     [(b"VOLT:LIM:STAT OFF;:VOLT:LIM:HIGH 5;:VOLT:LIM:LOW -3;:VOLT:LIM:HIGH 3;:VOLT:LIM:STAT ON;:SYST:ERR?\n",
       NO_ERROR)], None),
    (lambda g: g.safe_state(), [(b"OUTP OFF;:SYST:ERR?\n", NO_ERROR), (b"OUTP?\n", b"0\n")], None),
    (lambda g: g.check_errors(), [(b"SYST:ERR?\n", b'-222,"Data out of range"\n'), (b"SYST:ERR?\n", NO_ERROR)],
     ['-222,"Data out of range"']),
]


@pytest.mark.parametrize("action,script,expected", GENERATOR_EXCHANGES)
def test_signal_generator_sends_exactly_the_manuals_bytes(action, script, expected):
    peer, gen = expect(SignalGenerator, script, b"\n")
    assert action(gen) == expected
    finish(peer, gen, script)


def test_signal_generator_refused_write_drains_the_queue_into_the_fault():
    script = [(b"FREQ 20;:SYST:ERR?\n", b'-221,"Settings conflict"\n'),
              (b"SYST:ERR?\n", b'-350,"Queue overflow"\n'), (b"SYST:ERR?\n", NO_ERROR)]
    peer, gen = expect(SignalGenerator, script, b"\n")
    with pytest.raises(InstrumentFault, match=r'FREQ 20: rejected by the instrument: -221,"Settings conflict" '
                                              r'\(and -350,"Queue overflow"\)'):
        gen.frequency = 20
    finish(peer, gen, script)


@pytest.mark.parametrize("attr,value", [("amplitude", 10.5), ("frequency", 0.0), ("frequency", 31e6),
                                        ("offset", 6.0), ("output", 1), ("amplitude", math.nan)])
def test_signal_generator_out_of_range_setting_sends_nothing(attr, value):
    peer, gen = expect(SignalGenerator, [], b"\n")
    with pytest.raises(SettingRangeError):
        setattr(gen, attr, value)
    finish(peer, gen, [])


def test_signal_generator_over_a_pty():
    script = [(b"*IDN?\n", b"a,b,c,d\n"), (b"OUTP OFF;:SYST:ERR?\n", NO_ERROR), (b"OUTP?\n", b"0\n")]
    peer, gen = expect(SignalGenerator, script, b"\n", use_pty=True)
    assert gen.identify() == "a,b,c,d"
    gen.safe_state()
    finish(peer, gen, script)


# ---- laser sensor (CR) ----------------------------------------------------------------------------

SENSOR_EXCHANGES = [
    (lambda s: s.identify(), [(b"ID\r", b"ID,maker SIM,base\r")], "maker SIM,base"),
    (lambda s: s.measuring_range, [(b"RG\r", b"RG,10.000\r")], 0.01),
    (lambda s: s.sampling_rate, [(b"SS\r", b"SS,10000\r")], 10000.0),
    (lambda s: setattr(s, "sampling_rate", 5000), [(b"SS,5000\r", b"SS\r")], None),
    (lambda s: s.read(), [(b"M0\r", b"M0,-01.25000\r")], -1.25e-3),
    (lambda s: s.arm(None), [(b"AS,0\r", b"AS\r")], None),
    (lambda s: s.arm(500), [(b"AS,500\r", b"AS\r")], None),
    (lambda s: s.stop(), [(b"AQ\r", b"AQ\r")], None),
    (lambda s: s.status(), [(b"ST\r", b"ST,RUNNING,120,100\r")], ("RUNNING", 120, 100)),
    (lambda s: s.check_errors(), [(b"EQ\r", b"EQ,3\r")], ["buffer overflow", "signal loss"]),
]


@pytest.mark.parametrize("action,script,expected", SENSOR_EXCHANGES)
def test_laser_sensor_sends_exactly_the_manuals_bytes(action, script, expected):
    peer, sensor = expect(LaserSensor, script, b"\r")
    got = action(sensor)
    assert got == (pytest.approx(expected) if isinstance(expected, float) else expected)
    finish(peer, sensor, script)


def test_laser_sensor_fetch_decodes_values_and_flags():
    script = [(b"AO,3\r", b"AO,7,3,+00.10000,+FFFFFFF,XXXXXXXX\r")]
    peer, sensor = expect(LaserSensor, script, b"\r")
    block = sensor.fetch(3)
    assert block.index0 == 7
    assert block.values[0] == pytest.approx(1e-4) and math.isnan(block.values[1]) and math.isnan(block.values[2])
    assert list(block.flags) == [0, FLAG_OUT_OF_RANGE, FLAG_SIGNAL_LOSS]
    finish(peer, sensor, script)


def test_laser_sensor_error_reply_names_the_code_and_the_sensor():
    script = [(b"SS,2000\r", b"ER,SS,30\r")]
    peer, sensor = expect(LaserSensor, script, b"\r", name="tip")
    with pytest.raises(InstrumentFault, match=r"laser sensor tip: SS,2000: error 30: not allowed in the current"):
        sensor.sampling_rate = 2000
    finish(peer, sensor, script)


def test_laser_sensor_unsupported_rate_sends_nothing():
    peer, sensor = expect(LaserSensor, [], b"\r")
    with pytest.raises(SettingRangeError):
        sensor.sampling_rate = 3000
    finish(peer, sensor, [])


def test_laser_sensor_over_a_pty():
    script = [(b"ID\r", b"ID,m,tip\r"), (b"AS,0\r", b"AS\r")]
    peer, sensor = expect(LaserSensor, script, b"\r", use_pty=True)
    assert sensor.identify() == "m,tip"
    sensor.arm(None)
    finish(peer, sensor, script)


# ---- power amplifier (Modbus TCP, a plain register datastore) -----------------------------------------

class RecordingModbusServer:
    """A real pymodbus server over plain holding registers 0..47 that records each request as
    (function code, address, count, written values or None)."""

    def __init__(self, registers: dict[int, int]):
        values = [registers.get(a, 0) for a in range(48)]
        self.requests: list[tuple[int, int, int, list | None]] = []
        self.device = SimDevice(1, simdata=[SimData(0, values=values, datatype=DataType.REGISTERS)],
                                action=self._record)
        self._ready = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)
        self._thread.start()
        assert self._ready.wait(10)

    async def _record(self, function_code, start_address, address, count, registers, set_values):
        if function_code in (6, 16) and set_values is None:
            return None  # pymodbus reading back a written register for the echo, not a request
        self.requests.append((function_code, address, count, None if set_values is None else list(set_values)))
        return None

    async def _main(self):
        self.server = ModbusTcpServer(self.device, address=("127.0.0.1", 0))
        await self.server.serve_forever(background=True)
        self.port = self.server.transport.sockets[0].getsockname()[1]
        self.loop = asyncio.get_running_loop()
        self._ready.set()
        await self.server.serving

    def writes(self):
        return [(fc, addr, vals) for fc, addr, _, vals in self.requests if vals is not None]

    def stop(self):
        asyncio.run_coroutine_threadsafe(self.server.shutdown(), self.loop).result(5)
        self._thread.join(5)


@pytest.fixture
def modbus():
    server = RecordingModbusServer({20: 10_000, 21: 20_000, 17: 0x10000 - 500, 19: 253})
    amp = PowerAmplifier(f"127.0.0.1:{server.port}", timeout=1.0)
    yield server, amp
    amp.close()
    server.stop()


def test_power_amplifier_writes_the_register_map(modbus):
    server, amp = modbus
    amp.enabled = True
    amp.gain = 1.5                 # reads MAX_GAIN (register 20) once, then writes GAIN x 1000
    amp.gain = 2.0
    amp.current_limit = 4.0        # reads MAX_CURRENT_LIMIT (21) once, then mA
    amp.watchdog_timeout = 2.0     # ms
    amp.heartbeat()
    amp.heartbeat()
    amp.reset_faults()
    amp.safe_state()               # one write of ENABLE and GAIN
    assert server.writes() == [(6, 0, [1]), (6, 1, [1500]), (6, 1, [2000]), (6, 2, [4000]), (6, 3, [2000]),
                               (6, 5, [1]), (6, 5, [2]), (6, 4, [1]), (16, 0, [0, 0])]
    reads = [(addr, count) for fc, addr, count, _ in server.requests if fc in (3, 4)]
    assert reads == [(20, 1), (21, 1)]  # the device limits, once each


def test_power_amplifier_decodes_scaled_and_signed_registers(modbus):
    _, amp = modbus
    assert amp.output_current == -0.5
    assert amp.temperature == 25.3
    assert amp.max_gain == 10.0 and amp.max_current_limit == 20.0


@pytest.mark.parametrize("attr,value", [("gain", 10.001), ("gain", -1.0), ("current_limit", 0.0),
                                        ("current_limit", 20.5), ("watchdog_timeout", 60.5), ("enabled", 1)])
def test_power_amplifier_out_of_range_setting_writes_nothing(modbus, attr, value):
    server, amp = modbus
    with pytest.raises(SettingRangeError):
        setattr(amp, attr, value)
    assert server.writes() == []


def test_power_amplifier_read_only_register_refuses_a_write_locally(modbus):
    server, amp = modbus
    with pytest.raises(AttributeError, match="read-only"):
        amp.output_current = 1.0
    assert server.requests == []

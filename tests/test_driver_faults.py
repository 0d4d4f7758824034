"""Transport faults: killed servers, garbage, split replies, silence, dropped links, process death.

Every fault must give a clear InstrumentError naming the instrument and the
command (never a hang), and must leave the simulated shaker undriven once the
survivors are put in their safe state.
"""
import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from drivers.base import (InstrumentConnectionError, InstrumentError, InstrumentTimeout,
                          MalformedReply)
from drivers.laser_sensor import LaserSensor
from drivers.power_amplifier import PowerAmplifier
from drivers.signal_generator import SignalGenerator
from sim_backend.rig import SimulatedRig


@pytest.fixture
def rig():
    with SimulatedRig(speed=None, seed=2) as r:
        yield r


@pytest.fixture
def drivers(rig):
    a = rig.addresses
    gen = SignalGenerator(a["generator"], timeout=0.5)
    amp = PowerAmplifier(a["amplifier"], timeout=0.5)
    tip = LaserSensor(a["sensor_tip"], timeout=0.5, name="tip")
    gen.frequency, gen.amplitude, gen.output = 14.0, 0.5, True
    amp.gain, amp.enabled = 1.0, True
    assert rig.world.is_driven()
    yield gen, amp, tip
    for d in (gen, amp, tip):
        d.close()


def test_generator_killed_mid_command(rig, drivers):
    gen, amp, _ = drivers
    rig.servers["generator"].inject("kill")
    t0 = time.monotonic()
    with pytest.raises(InstrumentConnectionError) as info:
        gen.frequency = 10.0
    assert time.monotonic() - t0 < 1.0
    msg = str(info.value)
    assert "signal generator" in msg and "FREQ 10" in msg
    assert not rig.world.is_driven(), "a dead generator outputs nothing"
    with pytest.raises(InstrumentConnectionError):  # reconnect attempts fail clearly too
        gen.identify()
    amp.safe_state()
    assert not rig.world.is_driven()


def test_sensor_killed_mid_fetch_then_safe_state(rig, drivers):
    gen, amp, tip = drivers
    tip.arm(None)
    gen.trigger()
    tip.fetch(100)
    rig.servers["sensor_tip"].inject("kill")
    with pytest.raises(InstrumentConnectionError) as info:
        tip.fetch(100)
    assert "laser sensor tip" in str(info.value) and "AO,100" in str(info.value)
    gen.safe_state()
    amp.safe_state()
    assert not rig.world.is_driven()


def test_amplifier_killed_mid_request(rig, drivers):
    gen, amp, _ = drivers
    rig.amplifier.response_delay = 0.3
    killer = threading.Timer(0.1, rig.kill, args=("amplifier",))
    killer.start()
    t0 = time.monotonic()
    with pytest.raises(InstrumentError) as info:
        amp.gain = 2.0
    killer.join()
    assert time.monotonic() - t0 < 2.0
    assert "power amplifier" in str(info.value) and "GAIN" in str(info.value)
    assert not rig.world.is_driven(), "a dead amplifier drives nothing"
    with pytest.raises(InstrumentConnectionError):
        amp.output_current
    gen.safe_state()


def test_amplifier_timeout(rig, drivers):
    gen, amp, _ = drivers
    rig.amplifier.response_delay = 1.0
    t0 = time.monotonic()
    with pytest.raises(InstrumentTimeout) as info:
        amp.output_current
    assert time.monotonic() - t0 < 2.0
    assert "OUTPUT_CURRENT" in str(info.value)
    rig.amplifier.response_delay = 0.0
    amp.safe_state()  # reconnects by itself
    assert not rig.world.is_driven()


@pytest.mark.parametrize("name", ["generator", "sensor_tip"])
def test_garbage_reply_is_a_malformed_reply_and_the_link_recovers(rig, drivers, name):
    gen, amp, tip = drivers
    rig.servers[name].inject("garbage")
    drv, call = (gen, lambda: gen.frequency) if name == "generator" else (tip, tip.identify)
    with pytest.raises(MalformedReply) as info:
        call()
    assert drv.name in str(info.value)
    assert call()  # reopened, in sync again
    gen.safe_state()
    amp.safe_state()
    assert not rig.world.is_driven()


def test_replies_split_into_single_bytes_are_reassembled(rig, drivers):
    gen, _, _ = drivers
    rig.servers["generator"].inject("split")
    assert gen.frequency == 14.0
    # a block reply sent byte by byte with 2 ms pauses takes about 0.5 s: this sensor waits longer
    # (the test is about reassembly, not speed: under load the pauses stretch)
    tip = LaserSensor(rig.addresses["sensor_tip"], timeout=5.0, name="tip")
    try:
        tip.arm(None)
        gen.trigger()
        rig.servers["sensor_tip"].inject("split")
        blk = tip.fetch(20)
        assert len(blk) == 20 and blk.index0 == 0
    finally:
        tip.close()


@pytest.mark.parametrize("name", ["generator", "sensor_tip"])
def test_silence_is_a_timeout_naming_the_command(rig, drivers, name):
    gen, amp, tip = drivers
    rig.servers[name].inject("silent")
    drv, call, cmd = ((gen, lambda: gen.output, "OUTP?") if name == "generator"
                      else (tip, lambda: tip.measuring_range, "RG"))
    t0 = time.monotonic()
    with pytest.raises(InstrumentTimeout) as info:
        call()
    assert 0.4 < time.monotonic() - t0 < 1.5
    assert drv.name in str(info.value) and cmd in str(info.value)
    call()  # the next one works
    amp.safe_state()
    assert not rig.world.is_driven()


def test_dropped_connection_is_reported_then_reconnected(rig, drivers):
    gen, amp, _ = drivers
    rig.servers["generator"].drop_connections()
    time.sleep(0.05)
    with pytest.raises(InstrumentConnectionError):
        gen.frequency
    assert gen.frequency == 14.0  # policy: reconnect on the next call, never re-send the failed one


def test_connection_refused_is_clear():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    with pytest.raises(InstrumentConnectionError) as info:
        SignalGenerator(f"socket://127.0.0.1:{port}", timeout=0.3)
    assert "signal generator" in str(info.value)
    with pytest.raises(InstrumentConnectionError) as info:
        PowerAmplifier(f"127.0.0.1:{port}", timeout=0.3)
    assert "power amplifier" in str(info.value)


class _GarbageModbus:
    """A TCP server that answers every request with non-Modbus bytes (or in 1-byte pieces of a
    real reply, when proxying)."""

    def __init__(self, upstream=None):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.port = self.sock.getsockname()[1]
        self.upstream = upstream
        threading.Thread(target=self.run, daemon=True).start()

    def run(self):
        try:
            conn, _ = self.sock.accept()
        except OSError:
            return
        up = socket.create_connection(self.upstream) if self.upstream else None
        while True:
            try:
                data = conn.recv(4096)
            except OSError:
                return
            if not data:
                return
            if up is None:
                conn.sendall(b"\x13\x37garbage, not modbus\xff")
                continue
            up.sendall(data)
            reply = up.recv(4096)
            for k in range(len(reply)):
                conn.sendall(reply[k:k + 1])
                time.sleep(0.002)

    def close(self):
        self.sock.close()


def test_modbus_garbage_reply_is_an_error_not_a_hang():
    srv = _GarbageModbus()
    amp = PowerAmplifier(f"127.0.0.1:{srv.port}", timeout=0.5, reconnect_attempts=1)
    t0 = time.monotonic()
    with pytest.raises(InstrumentError) as info:
        amp.enabled
    assert time.monotonic() - t0 < 2.0
    assert "power amplifier" in str(info.value) and "ENABLE" in str(info.value)
    amp.close()
    srv.close()


def test_modbus_reply_split_into_single_bytes(rig):
    host, port = rig.addresses["amplifier"].split(":")
    proxy = _GarbageModbus(upstream=(host, int(port)))
    amp = PowerAmplifier(f"127.0.0.1:{proxy.port}", timeout=1.0)
    assert amp.identify() == "shakerlab SIM-PA100 amplifier"
    amp.close()
    proxy.close()


def test_master_process_death_mutes_the_amplifier_within_the_watchdog(rig):
    """A rig process that dies (SIGKILL) stops feeding the watchdog: the output mutes."""
    a = rig.addresses
    script = textwrap.dedent(f"""
        import time
        from drivers.power_amplifier import PowerAmplifier
        from drivers.signal_generator import SignalGenerator
        gen = SignalGenerator({a['generator']!r})
        amp = PowerAmplifier({a['amplifier']!r})
        amp.watchdog_timeout = 0.3
        gen.frequency, gen.amplitude, gen.output = 14.0, 0.5, True
        amp.gain, amp.enabled = 1.0, True
        print("driving", flush=True)
        while True:
            amp.heartbeat()
            time.sleep(0.05)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        assert proc.stdout.readline().strip() == "driving"
        time.sleep(0.5)
        assert rig.world.is_driven(), "heartbeats keep it alive"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)
        t_dead = time.monotonic()
        while rig.world.is_driven() and time.monotonic() - t_dead < 3.0:
            time.sleep(0.01)
        muted_after = time.monotonic() - t_dead
        assert not rig.world.is_driven()
        assert muted_after < 0.3 + 0.2
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_control_character_in_a_reply_is_malformed_and_a_tab_is_not():
    """A reply is printable ASCII and tabs: a bell (a garbled line) is refused naming the command,
    a tab-separated reply is returned as sent (a real socket, one reply per request)."""
    from drivers.line_link import LineLink
    replies = iter([b"a\tb\n", b"1.0\x07\n"])
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)

    def serve():
        conn, _ = srv.accept()
        with conn:
            for reply in replies:
                if not conn.recv(64):
                    return
                conn.sendall(reply)

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    link = LineLink("bench meter", f"socket://127.0.0.1:{srv.getsockname()[1]}", timeout=2.0)
    try:
        assert link.query("FORM?") == "a\tb"
        with pytest.raises(MalformedReply) as info:
            link.query("MEAS?")
        assert "control characters" in str(info.value) and "MEAS?" in str(info.value)
    finally:
        link.close()
    th.join(timeout=5)
    srv.close()

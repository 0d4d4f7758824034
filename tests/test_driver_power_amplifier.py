"""PowerAmplifier driver against the simulated Modbus TCP amplifier; pymodbus's own client as a cross-check."""
import time

import pytest
from pymodbus.client import ModbusTcpClient

from drivers.base import InstrumentFault, SettingRangeError
from drivers.power_amplifier import PowerAmplifier
from drivers.signal_generator import SignalGenerator
from sim_backend import physics as ph
from sim_backend.rig import SimulatedRig


def make(config=None):
    rig = SimulatedRig(config, speed=None, seed=0).start()
    gen = SignalGenerator(rig.addresses["generator"])
    amp = PowerAmplifier(rig.addresses["amplifier"], timeout=1.0)
    return rig, gen, amp


@pytest.fixture
def setup():
    rig, gen, amp = make()
    yield rig, gen, amp
    gen.close()
    amp.close()
    rig.stop()


def drive(gen, amp, vpp=0.5, f=14.0, gain=1.0):
    gen.frequency, gen.amplitude, gen.output = f, vpp, True
    amp.gain = gain
    amp.enabled = True


def test_identify_settings_and_measurements(setup):
    rig, gen, amp = setup
    assert amp.identify() == "shakerlab SIM-PA100 amplifier"
    assert amp.enabled is False and amp.gain == 0.0
    assert amp.current_limit == 5.0
    assert amp.max_gain == 10.0 and amp.max_current_limit == 20.0
    drive(gen, amp, vpp=1.0, gain=2.0)
    assert amp.enabled is True and amp.gain == 2.0
    rig.world.advance(2345)
    # 1 Vpp sine x gain 2 x 1 A/V: |i| <= 1 A, and the reading is the simulated current
    i = amp.output_current
    assert abs(i) <= 1.0
    assert i == pytest.approx(rig.world.A[ph.A_I], abs=1e-3)
    assert amp.output_voltage == pytest.approx(rig.world.A[ph.A_V], abs=0.01)
    assert amp.temperature == pytest.approx(25.0, abs=0.5)
    assert amp.faults.any is False and amp.check_errors() == []
    assert rig.world.is_driven()
    amp.safe_state()
    assert amp.enabled is False and amp.gain == 0.0
    assert not rig.world.is_driven()


@pytest.mark.parametrize("attr,value", [("gain", -0.1), ("gain", 10.5), ("current_limit", 0.0),
                                        ("current_limit", 25.0), ("watchdog_timeout", -1.0),
                                        ("watchdog_timeout", 61.0), ("enabled", 1)])
def test_out_of_range_setpoints_raise(setup, attr, value):
    _, _, amp = setup
    before = getattr(amp, attr)
    with pytest.raises(SettingRangeError) as info:
        setattr(amp, attr, value)
    assert "power amplifier" in str(info.value)
    assert getattr(amp, attr) == before


def test_device_rejects_out_of_range_register_writes_from_any_master(setup):
    rig, _, amp = setup
    host, port = rig.addresses["amplifier"].split(":")
    client = ModbusTcpClient(host, port=int(port), timeout=1)
    assert client.connect()
    try:
        rr = client.write_register(1, 50_000, device_id=1)  # gain 50 > max 10
        assert rr.isError() and rr.exception_code == 3
        rr = client.write_register(17, 1, device_id=1)  # OUTPUT_CURRENT is read-only
        assert rr.isError()
        rr = client.write_registers(0, [1, 1500], device_id=1)
        assert not rr.isError()
        rr = client.read_holding_registers(32, count=16, device_id=1)
        ident = b"".join(r.to_bytes(2, "big") for r in rr.registers).decode().strip()
        assert ident == "shakerlab SIM-PA100 amplifier"
    finally:
        client.close()
    assert amp.enabled is True and amp.gain == 1.5  # the driver reads what the other master wrote


def test_over_current_latches_and_mutes_until_reset(setup):
    rig, gen, amp = setup
    amp.current_limit = 0.1
    drive(gen, amp, vpp=0.5)  # 0.25 A peak > 0.1 A
    rig.world.advance(1000)
    f = amp.faults
    assert f.over_current and not f.watchdog
    assert amp.check_errors() == ["over_current"]
    assert not rig.world.is_driven()
    assert amp.output_current == 0.0
    amp.current_limit = 1.0
    rig.world.advance(1000)
    assert amp.faults.over_current, "the fault latches until reset"
    amp.reset_faults()
    assert amp.check_errors() == []
    assert rig.world.is_driven()


def test_clip_and_over_temperature():
    cfg = {"amplifier": {"rail_voltage": 0.3, "thermal_resistance": 200.0, "thermal_time_constant": 0.2,
                         "max_temperature": 30.0}}
    rig, gen, amp = make(cfg)
    try:
        drive(gen, amp, vpp=1.0, gain=1.0)  # 0.5 A needs 0.5 V > 0.3 V rail: clips
        rig.world.advance(200)
        assert amp.faults.clip
        assert rig.world.is_driven(), "clipping distorts but does not mute"
        for _ in range(100):  # ~0.1 W x 200 K/W heats the stage past 30 degC within a second
            rig.world.advance(200)
            if amp.faults.over_temperature:
                break
        assert amp.faults.over_temperature
        assert amp.temperature > 29.0
        assert not rig.world.is_driven()
        amp.reset_faults()
        assert amp.faults.over_temperature, "stays until the stage has cooled"
        amp.safe_state()
        rig.world.advance(20000)
        amp.reset_faults()
        assert amp.check_errors() == []
    finally:
        gen.close()
        amp.close()
        rig.stop()


def test_watchdog_mutes_a_silent_master_and_heartbeat_prevents_it(setup):
    rig, gen, amp = setup
    amp.watchdog_timeout = 0.2
    drive(gen, amp)
    for _ in range(10):  # 0.5 s of heartbeats: no trip
        time.sleep(0.05)
        amp.heartbeat()
    assert amp.check_errors() == []
    assert rig.world.is_driven()
    time.sleep(0.5)  # silence
    assert not rig.world.is_driven()
    assert amp.faults.watchdog
    assert gen.output is True, "only the amplifier mutes; the generator is untouched"
    amp.reset_faults()
    assert rig.world.is_driven()


def test_modbus_exception_reply_is_an_instrument_fault_naming_the_register(setup):
    _, _, amp = setup
    with pytest.raises(InstrumentFault) as info:
        # read-only register (the driver refuses this write itself): the device answers exception 2
        amp._write_register(PowerAmplifier.output_current.address, 1, PowerAmplifier.output_current.label)
    msg = str(info.value)
    assert "power amplifier" in msg and "OUTPUT_CURRENT" in msg and "illegal data address" in msg

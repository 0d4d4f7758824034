"""SignalGenerator driver against the simulated 33500B over TCP and a pty; PyVISA as an independent client."""
import pytest

from drivers.base import InstrumentFault, SettingRangeError
from drivers.signal_generator import SignalGenerator
from sim_backend import physics as ph
from sim_backend.rig import SimulatedRig


@pytest.fixture(scope="module")
def rig():
    with SimulatedRig(speed=None, seed=0, pty=True) as r:
        yield r


@pytest.fixture
def gen(rig):
    g = SignalGenerator(rig.addresses["generator"], timeout=1.0)
    g.reset()
    yield g
    g.close()


def test_identify_reset_and_settings_round_trip(rig, gen):
    assert gen.identify().split(",")[1] == "SIM33521B"
    assert gen.output is False
    gen.frequency = 14.25
    gen.amplitude = 0.75
    gen.offset = -0.1
    gen.output = True
    assert gen.frequency == 14.25
    assert gen.amplitude == 0.75
    assert gen.offset == -0.1
    assert gen.output is True
    # the settings reached the physics at once
    G = rig.world.G
    assert G[ph.G_FREQ] == 14.25 and G[ph.G_VPP] == 0.75 and G[ph.G_OUT] == 1.0
    assert gen.check_errors() == []
    gen.reset()
    assert gen.output is False and gen.frequency == 1000.0


@pytest.mark.parametrize("attr,value", [("frequency", 0.0), ("frequency", 31e6), ("amplitude", 0.0),
                                        ("amplitude", 10.5), ("offset", 5.5), ("output", 1),
                                        ("frequency", float("nan")), ("amplitude", "1")])
def test_out_of_range_setpoints_raise_before_sending(gen, attr, value):
    before = getattr(gen, attr)
    with pytest.raises(SettingRangeError) as info:
        setattr(gen, attr, value)
    assert "signal generator" in str(info.value) and attr in str(info.value)
    assert getattr(gen, attr) == before
    assert gen.check_errors() == []


def test_voltage_limits_make_the_instrument_refuse_larger_settings(gen):
    gen.amplitude = 1.0
    gen.set_voltage_limits(-1.0, 1.0)
    assert gen.voltage_limits == (-1.0, 1.0)
    assert gen.voltage_limits_enabled
    with pytest.raises(InstrumentFault) as info:
        gen.amplitude = 3.0  # within the driver's range but beyond the limits: instrument says no
    assert "-221" in str(info.value) and "VOLT 3" in str(info.value)
    assert gen.amplitude == 1.0
    assert gen.check_errors() == []  # the driver drained the queue when it raised
    with pytest.raises(SettingRangeError):
        gen.set_voltage_limits(1.0, -1.0)


def test_sweep_and_burst(rig, gen):
    gen.configure_sweep(5.0, 25.0, 10.0)
    gen.sweep_enabled = True
    assert gen.sweep_enabled
    G = rig.world.G
    assert (G[ph.G_F0], G[ph.G_F1], G[ph.G_TSWEEP], G[ph.G_SWEEP]) == (5.0, 25.0, 10.0, 1.0)
    with pytest.raises(InstrumentFault):
        gen.configure_burst(3)  # burst while sweeping: settings conflict
    gen.sweep_enabled = False
    gen.frequency = 100.0
    gen.configure_burst(3)
    gen.output = True
    assert gen.burst_enabled
    t0 = rig.world.step
    gen.trigger()
    assert rig.world.trigger_steps[-1] == t0
    assert G[ph.G_BURST_ACTIVE] == 1.0
    rig.world.advance(int(0.031 * rig.world.sample_rate))  # 3 cycles of 100 Hz last 30 ms
    assert G[ph.G_BURST_ACTIVE] == 0.0
    with pytest.raises(SettingRangeError):
        gen.configure_burst(0)
    with pytest.raises(SettingRangeError):
        gen.configure_sweep(5.0, 25.0, 0.0)


def test_safe_state_turns_the_output_off(rig, gen):
    gen.amplitude = 0.5
    gen.output = True
    gen.safe_state()
    assert gen.output is False
    assert rig.world.G[ph.G_OUT] == 0.0


def test_over_a_pty(rig):
    path = rig.pty_paths["generator"]
    with SignalGenerator(path, timeout=1.0) as g:
        assert "SIM33521B" in g.identify()
        g.frequency = 12.5
        assert g.frequency == 12.5


def test_pyvisa_socket_resource_as_independent_client(rig, gen):
    pyvisa = pytest.importorskip("pyvisa")
    host, port = rig.addresses["generator"].removeprefix("socket://").split(":")
    rm = pyvisa.ResourceManager("@py")
    inst = rm.open_resource(f"TCPIP::{host}::{port}::SOCKET", read_termination="\n",
                            write_termination="\n", timeout=2000)
    try:
        assert inst.query("*IDN?").startswith("shakerlab,SIM33521B")
        inst.write("SOUR:FREQ 17.5;:SOURce:VOLTage:LEVel:IMMediate:AMPLitude 250 MVPP")
        assert float(inst.query("FREQ?")) == 17.5
        assert float(inst.query("VOLT?")) == pytest.approx(0.25)
        inst.write("FREQ 99 GHZ")  # bad unit: lands in the error queue
        inst.write("BOGUS:CMD 1")
        assert inst.query("SYST:ERR?").startswith("-104")
        assert inst.query("SYST:ERR?").startswith("-113")
        assert inst.query("SYST:ERR?") == '+0,"No error"'
    finally:
        inst.close()
        rm.close()
    assert gen.frequency == 17.5  # the driver sees what the other client set

"""LaserSensor driver against the simulated LK-G style controllers (TCP and pty)."""
import time

import numpy as np
import pytest

from drivers.base import InstrumentFault, SettingRangeError
from drivers.laser_sensor import FLAG_OUT_OF_RANGE, FLAG_SIGNAL_LOSS, LaserSensor, OutOfRange, SignalLoss
from drivers.power_amplifier import PowerAmplifier
from drivers.signal_generator import SignalGenerator
from sim_backend.rig import SimulatedRig


class Bench:
    def __init__(self, config=None, speed=None, pty=False):
        self.rig = SimulatedRig(config, speed=speed, seed=5, pty=pty).start()
        a = self.rig.addresses
        self.gen = SignalGenerator(a["generator"])
        self.amp = PowerAmplifier(a["amplifier"])
        self.base = LaserSensor(a["sensor_base"], name="base")
        self.tip = LaserSensor(a["sensor_tip"], name="tip")

    def drive(self, vpp=0.5, f=14.0):
        self.gen.frequency, self.gen.amplitude, self.gen.output = f, vpp, True
        self.amp.gain, self.amp.enabled = 1.0, True

    def close(self):
        for d in (self.gen, self.amp, self.base, self.tip):
            d.close()
        self.rig.stop()


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def test_identify_range_and_sampling_rate(bench):
    assert bench.tip.identify() == "shakerlab SIM-LKG5001,tip"
    assert bench.base.measuring_range == pytest.approx(0.010)
    assert bench.tip.sampling_rate == 10000.0
    bench.tip.sampling_rate = 5000
    assert bench.tip.sampling_rate == 5000.0
    with pytest.raises(SettingRangeError):
        bench.tip.sampling_rate = 3000  # not a rate the controller has
    with pytest.raises(InstrumentFault) as info:
        bench.tip.sampling_rate = 20000  # a controller rate, but above the simulated one
    assert "laser sensor tip" in str(info.value) and "SS,20000" in str(info.value)
    assert bench.tip.sampling_rate == 5000.0


def test_single_reading_follows_the_physics(bench):
    bench.drive()
    bench.rig.world.advance(30000)
    x_tip = bench.tip.read()
    st = bench.rig.world.state()
    # the reading is the sample at the start of the last step: within one step of motion + noise
    v_tip = st["v_base"] + st["dy"]
    step_motion = abs(v_tip) * bench.rig.world.dt
    assert x_tip == pytest.approx(st["x_base"] + st["y"], abs=1.2 * step_motion + 2e-6)
    assert abs(x_tip) > 1e-4


def test_shared_time_base_after_a_common_trigger(bench):
    bench.drive()
    bench.rig.world.advance(1234)
    bench.base.arm(None)
    bench.tip.arm(None)
    b0 = bench.base.fetch()
    assert len(b0) == 0 and b0.index0 == 0  # armed, no trigger yet
    bench.gen.trigger()
    t_step = bench.rig.world.trigger_steps[-1]
    b1 = bench.base.fetch(700)
    t1 = bench.tip.fetch(1500)
    b2 = bench.base.fetch(800)
    assert (b1.index0, len(b1), t1.index0, len(t1), b2.index0, len(b2)) == (0, 700, 0, 1500, 700, 800)
    base = np.concatenate([b1.values, b2.values])
    # both channels are the world's readings at the same steps since the trigger
    steps = t_step + np.arange(1500)
    assert np.allclose(base, bench.rig.world.readings(0, steps), atol=1e-8)
    assert np.allclose(t1.values, bench.rig.world.readings(1, steps), atol=1e-8)


def test_decimated_rate_and_finite_acquisition(bench):
    bench.drive()
    for s in (bench.base, bench.tip):
        s.sampling_rate = 2000
        s.arm(1000)
    bench.gen.trigger()
    t_step = bench.rig.world.trigger_steps[-1]
    b = bench.base.fetch(5000)  # asks for more than armed: gets the 1000
    assert len(b) == 1000
    assert np.allclose(b.values, bench.rig.world.readings(0, t_step + 5 * np.arange(1000)), atol=1e-8)
    assert bench.base.status() == ("DONE", 1000, 1000)
    assert len(bench.base.fetch()) == 0
    assert len(bench.tip.fetch()) == 1000


def test_out_of_range_and_signal_loss():
    b = Bench({"sensors": {"range": 0.0005}})
    try:
        b.drive(vpp=0.6)
        b.tip.arm(None)
        b.gen.trigger()
        blk = b.tip.fetch(40000)
        oor = blk.flags == FLAG_OUT_OF_RANGE
        assert oor.any() and (~oor).any()
        assert np.isnan(blk.values[oor]).all() and np.isfinite(blk.values[~oor]).all()
        assert np.nanmax(np.abs(blk.values)) <= 0.0005
        with pytest.raises(OutOfRange):
            for _ in range(200):
                b.tip.read()
                b.rig.world.advance(7)
        b.rig.sensors["sensor_tip"].signal_loss = True
        with pytest.raises(SignalLoss) as info:
            b.tip.read()
        assert "laser sensor tip" in str(info.value)
        blk = b.tip.fetch(100)
        assert (blk.flags == FLAG_SIGNAL_LOSS).all() and np.isnan(blk.values).all()
        b.rig.sensors["sensor_tip"].signal_loss = False
        assert b.tip.check_errors() == ["signal loss"]
        assert b.tip.check_errors() == []
    finally:
        b.close()


def test_ring_overflow_is_reported_not_hidden():
    b = Bench({"clock": {"ring_seconds": 0.5}})
    try:
        b.base.arm(None)
        b.gen.trigger()
        b.rig.world.advance(10000)  # 1 s with nobody fetching: half of it is gone
        blk = b.base.fetch()
        assert blk.index0 > 0
        assert b.base.check_errors() == ["buffer overflow"]
        nxt = b.base.fetch(100)
        assert nxt.index0 == blk.index0 + len(blk)
    finally:
        b.close()


def test_fetch_in_real_time_mode_returns_what_has_been_measured():
    b = Bench(speed=1.0)
    try:
        b.base.arm(None)
        b.tip.arm(None)
        b.gen.trigger()
        time.sleep(0.3)
        blk = b.base.fetch()
        assert 1500 < len(blk) < 8000  # 0.3 s at 10 kHz, generous for a loaded machine
        t = b.tip.fetch(len(blk))
        assert t.index0 == 0 and len(t) == len(blk)
    finally:
        b.close()


def test_over_a_pty():
    b = Bench(pty=True)
    try:
        with LaserSensor(b.rig.pty_paths["sensor_base"], name="base") as s:
            assert s.identify().endswith(",base")
            s.arm(500)
            b.gen.trigger()
            assert len(s.fetch(500)) == 500
    finally:
        b.close()


def test_bad_arguments_raise(bench):
    with pytest.raises(SettingRangeError):
        bench.base.arm(0)
    with pytest.raises(SettingRangeError):
        bench.base.fetch(0)
    with pytest.raises(InstrumentFault) as info:
        bench.base.fetch()  # never armed
    assert "AO" in str(info.value) and "not allowed" in str(info.value)

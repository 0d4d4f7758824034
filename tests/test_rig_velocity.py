"""Velocity sensors on the rig (issue 14): the laser-sensor driver's measuring mode, the simulated
controller's velocity readings, the real-time integration the supervisor and the plans work on, the
run file, and `shakerlab acquire` -> `shakerlab reconstruct` from velocity against the same run from
displacement (the real simulated rig over its real transports, lockstep)."""
from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from drivers.base import InstrumentFault, SettingRangeError
from drivers.laser_sensor import LaserSensor
from drivers.power_amplifier import PowerAmplifier
from drivers.signal_generator import SignalGenerator
from rig.config import DEFAULT_RIG_PATH, load_config
from rig.instruments import VelocityIntegrator
from sim_backend import physics as ph
from sim_backend.rig import SimulatedRig
from sim_backend.world import World
from shakerlab.cli import main
from shakerlab.errors import UserFacingError
from shakerlab.runfile.reader import load_run


def velocity_rig_toml(tmp_path, points=("base", "tip"), limits: dict | None = None, sample_rate_hz=None):
    text = DEFAULT_RIG_PATH.read_text()
    if sample_rate_hz is not None:   # else the shipped 10 kHz
        rate = f"sample_rate_hz = {float(sample_rate_hz)}"
        text = text.replace("sample_rate_hz = 10000.0", rate)
        assert rate in text, "the shipped rig config no longer names its 10 kHz rate"
    for p in points:
        head = f"[sensors.{p}]"
        i = text.index(head)
        j = text.index("timeout_s = 1.0\n", i) + len("timeout_s = 1.0\n")
        text = text[:j] + 'quantity = "velocity"\n' + text[j:]
    for key, value in (limits or {}).items():
        text = "\n".join(f"{key} = {value}" if line.startswith(f"{key} =") else line for line in text.splitlines())
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return path


# ---- the simulator's kernel: displacement unchanged, velocity the derivative ----------------------

def test_the_velocity_kernel_leaves_the_displacement_readings_bit_identical():
    w = World(speed=None, seed=3)
    P, n = w.P, 20000
    G = w.G.copy()
    G[ph.G_OUT], G[ph.G_VPP], G[ph.G_FREQ] = 1.0, 1.0, 13.0
    A = w.A.copy()
    A[ph.A_ENABLE], A[ph.A_GAIN] = 1.0, 1.0
    out = {}
    for with_v in (False, True):
        X, g, a = w.X.copy(), G.copy(), A.copy()
        # zeros, not np.empty: the plain kernel leaves the velocity rows as they were, and
        # uninitialised memory there (NaN at times) made the check below fail by chance
        xb, xt, vb, vt = (np.zeros(n) for _ in range(4))
        if with_v:
            ph.advance_with_velocity(P, X, g, a, 0, n, xb, xt, vb, vt)
        else:
            ph.advance(P, X, g, a, 0, n, xb, xt)
        out[with_v] = (xb, xt, vb, vt)
    np.testing.assert_array_equal(out[False][0], out[True][0])
    np.testing.assert_array_equal(out[False][1], out[True][1])
    assert not np.any(out[False][3]) and np.std(out[True][3]) > 0     # only the velocity kernel writes them
    # without noise the velocity reading is the displacement reading's derivative
    P0 = P.copy()
    P0[ph.P_NOISE] = P0[ph.P_VNOISE] = 0.0
    xb, xt, vb, vt = (np.empty(n) for _ in range(4))
    ph.advance_with_velocity(P0, w.X.copy(), G.copy(), A.copy(), 0, n, xb, xt, vb, vt)
    dt = 1.0 / w.sample_rate
    for x, v in ((xb, vb), (xt, vt)):
        dx = np.gradient(x, dt)[n // 2:-2]
        assert np.std(dx - v[n // 2:-2]) < 1e-3 * np.std(v[n // 2:])
    # with noise: its own stream, about velocity_noise_std
    _, _, vb_noisy, _ = out[True]
    assert np.std(vb_noisy - vb) == pytest.approx(2e-5, rel=0.05)


# ---- driver and simulated controller, over TCP ----------------------------------------------------

@pytest.fixture
def bench():
    rig = SimulatedRig(speed=None, seed=5).start()
    a = rig.addresses
    gen, amp = SignalGenerator(a["generator"]), PowerAmplifier(a["amplifier"])
    base, tip = LaserSensor(a["sensor_base"], name="base"), LaserSensor(a["sensor_tip"], name="tip")
    yield rig, gen, amp, base, tip
    for d in (gen, amp, base, tip):
        d.close()
    rig.stop()


def test_the_measuring_mode_is_a_validated_setting(bench):
    rig, gen, amp, base, tip = bench
    assert tip.quantity == "displacement"
    assert tip.velocity_range == pytest.approx(2.0)
    tip.quantity = "velocity"
    assert tip.quantity == "velocity" and base.quantity == "displacement"
    for bad in ("acceleration", "Velocity", 1, True, None):
        with pytest.raises(SettingRangeError):
            tip.quantity = bad
    assert tip.quantity == "velocity"          # nothing was sent
    tip.arm(None)
    with pytest.raises(InstrumentFault, match="MD,0: error 30"):
        tip.quantity = "displacement"          # not while acquiring
    tip.stop()
    assert rig.sensors["sensor_tip"].handle("MD,7") == "ER,MD,22"
    assert rig.sensors["sensor_tip"].handle("MD,x") == "ER,MD,20"


def test_velocity_readings_are_the_motion_in_m_per_s(bench):
    rig, gen, amp, base, tip = bench
    tip.quantity = "velocity"
    gen.frequency, gen.amplitude, gen.output = 14.0, 0.5, True
    amp.gain, amp.enabled = 1.0, True
    base.arm(None)
    tip.arm(None)
    gen.trigger()
    xb, vt = base.fetch(20000), tip.fetch(20000)
    gen.output = False
    assert xb.index0 == vt.index0 == 0
    xt_true = rig.world.ring[1, :20000]             # the tip displacement readings of the same steps
    v_from_x = np.gradient(xt_true, 1e-4)
    half = slice(10000, 19990)
    assert np.std(vt.values[half] - v_from_x[half]) < 0.05 * np.std(vt.values[half])
    assert 0.02 < np.max(np.abs(vt.values[half])) < 2.0   # m/s, not mm/s


# ---- the real-time integrator ---------------------------------------------------------------------

def test_the_integrator_gives_displacement_in_blocks_with_its_documented_error():
    fs, f = 10000.0, 5.0
    t = np.arange(int(20 * fs)) / fs
    x = 1e-3 * np.sin(2 * np.pi * f * t)
    v = 1e-3 * 2 * np.pi * f * np.cos(2 * np.pi * f * t)
    integ = VelocityIntegrator(fs)
    got = np.concatenate([integ(b) for b in np.array_split(v, 397)])      # blocks of any length
    x_rel = x - x[0]
    # the leak lets the start offset (here 1 mm, the cosine's integration constant) decay with
    # tau = 10 s; after 3 tau the motion itself matches
    late = t > 15
    ref = x_rel[late] - np.mean(x_rel[late])
    err = got[late] - np.mean(got[late]) - ref
    assert np.max(np.abs(err)) < 0.005 * 1e-3
    whole = VelocityIntegrator(fs)(v)
    np.testing.assert_allclose(got, whole, rtol=0, atol=1e-15)


# ---- config ---------------------------------------------------------------------------------------

def test_the_rig_config_refuses_an_unknown_quantity(tmp_path):
    path = velocity_rig_toml(tmp_path, ("tip",))
    assert load_config(path).quantities == {"base": "displacement", "tip": "velocity"}
    path.write_text(path.read_text().replace('quantity = "velocity"', 'quantity = "acceleration"'))
    with pytest.raises(UserFacingError, match=r"\[sensors\.tip\] quantity|sensors.tip.quantity"):
        load_config(path)
    assert load_config(None).quantities == {"base": "displacement", "tip": "displacement"}


# ---- limits and decisions in metres when the sensors give velocity -----------------------------------

def _run_sim(tmp_path, limits, name):
    from rig.protocol import load_protocol
    from rig.session import acquire, simulated_rig

    # sampled at 1 kHz (as tests/test_closed_loop.py's rig_toml_1khz): a tenth of the samples to simulate,
    # stream and write through the default protocol; the limits are in metres and the blocks in seconds
    cfg = velocity_rig_toml(tmp_path, limits=limits, sample_rate_hz=1000.0)
    with simulated_rig(speed=None, seed=2, rig_config=cfg) as (sim, config):
        out = acquire(config, load_protocol(), tmp_path / name, lockstep=True)
        world = sim.world
        true_tip = world.ring[1, world.trigger_steps[0]:world.step].copy()   # the simulator's displacement
        trigger = world.trigger_steps[0]
        ring = world.ring[1].copy()
        # the sensors' sample n is the world's step trigger + n * steps_per_sample (sim_backend.laser_sensor:
        # the world steps at its own 10 kHz, the sensors read every tenth step at 1 kHz)
        steps_per_sample = int(round(world.sample_rate / config.acquisition["sample_rate_hz"]))
    return out, true_tip, trigger, ring, steps_per_sample


def test_the_tip_displacement_limit_trips_on_the_integrated_velocity(tmp_path):
    """A 0.3 mm tip limit with velocity sensors trips at the tip displacement the simulator itself had
    at that sample, named as integrated from the velocity: never a velocity compared with metres."""
    out, _, trigger, ring, steps_per_sample = _run_sim(tmp_path, {"max_tip_displacement_m": 0.0003}, "trip.h5")
    assert out.status == "tripped", out.reason
    assert "max_tip_displacement_m" in out.reason and "integrated from sensor_tip's velocity" in out.reason
    value_mm = float(out.reason.split("|x_tip| = ")[1].split(" mm")[0])
    sample = int(out.reason.split("at sample ")[1].split()[0])
    truth_mm = abs(ring[trigger + sample * steps_per_sample]) * 1e3
    # the reason prints the reading to 1 um: a trip just over the limit reads 0.300
    assert value_mm >= 0.3 and value_mm == pytest.approx(truth_mm, abs=0.005)


def test_the_nonlinear_stage_stops_before_a_tip_limit_measured_as_velocity(tmp_path):
    """The plans' limit decision extrapolates the integrated displacement: with a 1 mm tip limit the
    stage stops raising on that limit, and the simulator's own tip displacement stayed below it."""
    out, true_tip, _, _, _ = _run_sim(tmp_path, {"max_tip_displacement_m": 0.001}, "soft.h5")
    assert out.status == "complete", out.reason
    nl = load_run(out.path).stage("nonlinear").settings["summary"]
    assert "max_tip_displacement_m" in json.dumps(nl)
    assert 0.5e-3 < np.max(np.abs(true_tip)) < 1e-3


# ---- acquire -> reconstruct: velocity against displacement -----------------------------------------

KEYS = ("c_m", "k_m", "alpha_m", "gamma", "delta")


@pytest.mark.slow
# two acquisitions and two full reconstructs: each reconstruct takes ~140 s on a loaded 2-core machine
# (the two-stage fit's restarts on the rig's records), past the suite's 300 s per test
@pytest.mark.slow
@pytest.mark.timeout(900)
def test_acquire_with_velocity_sensors_then_reconstruct_matches_displacement(tmp_path, capsys):
    runs = {}
    for kind in ("displacement", "velocity"):
        out = tmp_path / f"{kind}.h5"
        args = ["acquire", "--sim-speed", "0", "--seed", "1", "-o", str(out), "--quiet"]
        if kind == "velocity":
            args[1:1] = ["--config", str(velocity_rig_toml(tmp_path)), "--simulated"]
        assert main(args) == 0, capsys.readouterr().out
        capsys.readouterr()
        assert main(["reconstruct", str(out), "--json"]) == 0
        runs[kind] = (out, json.loads(capsys.readouterr().out))
    # the run file holds the velocity as measured, per channel, with its start value
    with h5py.File(runs["velocity"][0]) as f:
        g = f["entry/stages/nonlinear"]
        assert {"v_base", "v_tip"} <= set(g) and "x_tip" not in g
        assert g["v_tip"].attrs["quantity"] == "velocity" and g["v_tip"].attrs["units"] == "m/s"
        assert "start_m" in g["v_tip"].attrs
        assert json.loads(f["entry/instrument/sensor_tip"].attrs["settings_json"])["quantity"] == "velocity"
    with h5py.File(runs["displacement"][0]) as f:
        g = f["entry/stages/nonlinear"]
        assert "x_tip" in g and "quantity" not in g["x_tip"].attrs
        assert "quantity" not in json.loads(f["entry/instrument/sensor_tip"].attrs["settings_json"])
    vel = load_run(runs["velocity"][0]).stage("nonlinear")
    assert vel.quantities == {"x_base": "velocity", "x_tip": "velocity"}
    d, v = runs["displacement"][1]["parameters"], runs["velocity"][1]["parameters"]
    assert sorted(v["fn_m"]) == sorted(d["fn_m"])
    diff = {k: v[k] / d[k] - 1 for k in KEYS}
    diff.update({k: v["fn_m"][k] / d["fn_m"][k] - 1 for k in d["fn_m"]})
    # measured (seed 1, against the displacement run): c -0.02 %, K +0.16 %, alpha -0.51 %, gamma +0.63 %,
    # delta -0.44 %, y^2 -0.87 %, y^3 -0.30 %; the weak nonlinear damping y^2*dy +6.0 %. Asserted: 2 % and 12 %
    bad = {k: round(e * 100, 2) for k, e in diff.items() if abs(e) > (0.12 if k == "y^2*dy" else 0.02)}
    assert not bad, f"velocity vs displacement (percent): {bad}"
    # both validate: measured NRMSE 0.0061 (displacement) and 0.0087 (velocity)
    for kind, (_, res) in runs.items():
        assert res["validation"]["nrmse"] < 0.015, (kind, res["validation"])

"""The runner on the real simulated rig (lockstep, as fast as possible): protocol, recording,
ramps, pause, abort, trips and dead instruments. No mocks: real sockets, a real pymodbus server,
real HDF5 files."""
import threading
import time

import h5py
import numpy as np
import pytest

from rig.config import DEFAULT_RIG_PATH, load_config
from rig.protocol import parse_protocol
from rig.session import acquire, simulated_rig
from shakerlab.runfile.reader import read_events, read_info
from shakerlab.runfile.reader import load_run

SMALL_PROTOCOL = """
[run]
settle_s = 0.3
[linear]
frequency_hz = 8.0
amplitude_vpp = 0.4
duration_s = 1.0
[resonance_search]
start_hz = 8.0
stop_hz = 25.0
steps = 7
refine_steps = 3
amplitude_vpp = 0.05
settle_s = 0.6
measure_s = 0.3
[nonlinear]
start_vpp = 0.1
step_factor = 1.5
max_vpp = 1.0
dwell_s = 0.8
analysis_s = 0.4
hold_s = 0.5
[[validation]]
frequency_factor = 0.8
amplitude_fraction = 0.8
duration_s = 1.0
"""


def small_protocol(**changes):
    import tomllib

    data = tomllib.loads(SMALL_PROTOCOL)
    for key, value in changes.items():
        table, field = key.split("__")
        data[table][field] = value
    return parse_protocol(data, SMALL_PROTOCOL, "small-protocol")


# the rate these tests sample at: a tenth of the shipped 10 kHz, as tests/test_closed_loop.py's
# rig_toml_1khz (a tenth of the samples to simulate, stream and write). Blocks, ramps, limits and
# timeouts are in seconds, so what the tests check does not hang on the rate; the drive frequencies
# (8-25 Hz) stay far below the rate's ceiling (sample_rate_hz / 20 = 50 Hz)
FS = 1000.0


def rig_config(tmp_path, sim, sample_rate_hz=FS, **limits):
    # the shipped watchdog timeout (2 s): shorter ones tripped spuriously on the heavily loaded
    # test machine (the simulated amplifier shares this process and its GIL)
    text = DEFAULT_RIG_PATH.read_text()
    rate = f"sample_rate_hz = {float(sample_rate_hz)}"
    text = text.replace("sample_rate_hz = 10000.0", rate)
    assert rate in text, "the shipped rig config no longer names its 10 kHz rate"
    for key, value in limits.items():
        import re

        text = re.sub(rf"^{key} = .*$", f"{key} = {value}", text, flags=re.M)
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return load_config(path).with_addresses(sim.addresses)


class Tape:
    """Observer keeping what the runner did, and firing an action at a chosen block."""

    def __init__(self, when=None, action=None):
        self.blocks = []
        self.events = []
        self.states = []
        self.when, self.action = when, action
        self.fired = None

    def on_block(self, block):
        self.blocks.append((block.index0, block.n, block.amplitude_vpp, block.stage, block.output))
        if self.action and self.fired is None and self.when(block):
            self.fired = len(self.blocks)
            self.action()

    def on_event(self, level, message, t):
        self.events.append((level, message))

    def on_state(self, state):
        self.states.append(state)

    def amplitudes(self):
        return np.array([b[2] for b in self.blocks])


@pytest.fixture
def sim():
    with simulated_rig(speed=None, seed=3) as (rig, _):
        yield rig


def _ramped(tape, rate, fs=FS, tol=1e-9):
    """Largest amplitude change between consecutive blocks, relative to rate * block time."""
    a = tape.amplitudes()
    n = np.array([b[1] for b in tape.blocks])
    allowed = rate * n[1:] / fs + tol
    return np.max(np.abs(np.diff(a)) / allowed)


def test_protocol_records_every_stage(tmp_path, sim):
    cfg = rig_config(tmp_path, sim)
    tape = Tape()
    out = acquire(cfg, small_protocol(), tmp_path / "run.h5", lockstep=True, observers=[tape])
    assert out.status == "complete", out.reason
    assert out.samples_lost == 0
    # the resonance of the simulated specimen (small amplitude): sqrt(k_m + alpha_m) / 2 pi
    truth = sim.world.truth()
    fn = np.sqrt(truth["k_m"] + truth["alpha_m"]) / (2 * np.pi)
    assert out.context.resonance_hz == pytest.approx(fn, rel=0.02)
    info = read_info(out.path)
    assert info["clean_close"] and info["status"] == "complete"
    assert list(info["stages"]) == ["linear", "resonance_search", "nonlinear", "validation"]
    assert set(info["instruments"]) == {"generator", "amplifier", "sensor_base", "sensor_tip"}
    assert "SIM" in info["instruments"]["sensor_tip"]["identity"].upper()
    assert info["instruments"]["amplifier"]["settings"]["watchdog_timeout_s"] == 2.0
    assert "frequency_factor" in info["config"]["protocol_toml"]
    assert sim.addresses["generator"] in info["config"]["rig_toml"] or "[limits]" in info["config"]["rig_toml"]
    nl = info["stages"]["nonlinear"]["summary"]
    assert len(nl["levels"]) >= 2 and nl["stop_reason"]
    assert info["stages"]["nonlinear"]["settings"]["drive_frequency_hz"] == pytest.approx(out.context.resonance_hz)
    with h5py.File(out.path, "r") as f:
        for name in info["stages"]:
            idx = f[f"entry/stages/{name}/sample_index"][:]
            assert np.all(np.diff(idx) == 1), name  # contiguous: nothing lost inside a stage
            assert idx[0] == f[f"entry/stages/{name}"].attrs["start_index"]
        assert f["entry/stages/nonlinear/steps"].shape[0] >= 2
    run = load_run(out.path)
    lin, non = run.stage("linear"), run.stage("nonlinear")
    assert np.ptp(non.y) > 3 * np.ptp(lin.y)  # the large stage is large
    assert lin.t[0] == 0.0 and lin.fs == pytest.approx(FS)
    # amplitude changes are ramped, never stepped, and the rig ends undriven
    assert _ramped(tape, cfg.limits["ramp_rate_vpp_per_s"]) <= 1.0
    assert not sim.world.is_driven()
    levels = [e["level"] for e in read_events(out.path)]
    assert "error" not in levels


def test_pause_and_resume_inside_a_step(tmp_path, sim):
    cfg = rig_config(tmp_path, sim)
    holder = {}

    def pause():
        holder["runner"].pause()
        threading.Timer(0.3, holder["runner"].resume).start()

    tape = Tape(when=lambda b: b.stage == "nonlinear" and b.amplitude_vpp > 0.12, action=pause)
    out = acquire(cfg, small_protocol(), tmp_path / "run.h5", lockstep=True, observers=[tape],
                  on_runner=lambda r: holder.setdefault("runner", r))
    assert out.status == "complete", out.reason
    assert "paused" in tape.states and tape.states[-1] == "done"
    a = tape.amplitudes()[tape.fired:]
    assert a.min() == 0.0  # ramped to zero while paused...
    assert _ramped(tape, cfg.limits["ramp_rate_vpp_per_s"]) <= 1.0  # ...never stepped
    msgs = [e["message"] for e in read_events(out.path)]
    assert any(m.startswith("paused at") for m in msgs) and any(m.startswith("resumed") for m in msgs)


def test_abort_ramps_down_and_second_abort_cuts(tmp_path, sim):
    cfg = rig_config(tmp_path, sim)
    holder = {}
    tape = Tape(when=lambda b: b.stage == "nonlinear" and b.amplitude_vpp > 0.12,
                action=lambda: holder["runner"].abort("operator pressed stop"))
    out = acquire(cfg, small_protocol(), tmp_path / "run.h5", lockstep=True, observers=[tape],
                  on_runner=lambda r: holder.setdefault("runner", r))
    assert out.status == "aborted" and out.reason == "operator pressed stop"
    after = tape.amplitudes()[tape.fired - 1:]
    assert after[0] > 0.12 and after[-1] == 0.0
    ramp_blocks = int(np.argmax(after == 0.0))
    assert ramp_blocks >= 5  # ramped over abort_ramp_s (0.5 s = 10 blocks), not cut
    assert not sim.world.is_driven()
    info = read_info(out.path)
    assert info["status"] == "aborted" and info["clean_close"]
    assert info["stages"]["nonlinear"]["status"] == "aborted"
    assert "validation" not in info["stages"]
    assert any("operator pressed stop" in e["message"] for e in read_events(out.path))

    # a second abort during the ramp cuts at once
    holder.clear()

    def twice():
        holder["runner"].abort("first")
        holder["runner"].abort("second")

    tape2 = Tape(when=lambda b: b.stage == "nonlinear" and b.amplitude_vpp > 0.12, action=twice)
    with simulated_rig(speed=None, seed=4) as (sim2, _):
        cfg2 = rig_config(tmp_path, sim2)
        out2 = acquire(cfg2, small_protocol(), tmp_path / "run2.h5", lockstep=True, observers=[tape2],
                       on_runner=lambda r: holder.setdefault("runner", r))
        assert not sim2.world.is_driven()
    assert out2.status == "aborted"
    assert len(tape2.blocks) - tape2.fired <= 2  # cut within a block, no ramp
    assert any("cut at once" in e["message"] for e in read_events(out2.path))


def test_limit_crossed_ramps_down_and_records_why(tmp_path, sim):
    # a tip limit that the linear stage crosses while its amplitude ramps up (it gives ~0.17 mm)
    cfg = rig_config(tmp_path, sim, max_tip_displacement_m=0.0001)
    tape = Tape()
    out = acquire(cfg, small_protocol(), tmp_path / "run.h5", lockstep=True, observers=[tape])
    assert out.status == "tripped"
    assert "max_tip_displacement_m" in out.reason and "exceeds" in out.reason
    a = tape.amplitudes()
    i = int(np.argmax(a))
    assert a[-1] == 0.0 and np.count_nonzero(a[i:] > 0) >= 5  # ramped down over several blocks
    assert np.max(np.abs(np.diff(a[i:]))) <= a[i] / cfg.limits["abort_ramp_s"] * 0.05 + 1e-9
    assert not sim.world.is_driven()
    ev = read_events(out.path)
    assert any(e["level"] == "error" and "max_tip_displacement_m" in e["message"] for e in ev)
    info = read_info(out.path)
    assert info["status"] == "tripped" and info["stages"]["linear"]["status"] == "tripped"
    assert "max_tip_displacement_m" in info["stages"]["linear"]["summary"]["stop_reason"]
    assert list(info["stages"]) == ["linear"]


def test_nonlinear_stage_stops_before_a_limit(tmp_path, sim):
    # the soft limit: the next level's predicted tip motion would cross 0.8 x 0.5 mm, so the raising stops
    cfg = rig_config(tmp_path, sim, max_tip_displacement_m=0.0005)
    out = acquire(cfg, small_protocol(nonlinear__step_factor=3.0), tmp_path / "run.h5", lockstep=True)
    assert out.status == "complete", out.reason
    nl = read_info(out.path)["stages"]["nonlinear"]["summary"]
    assert nl["stop_reason"].startswith("limit: the next level would exceed")
    assert "max_tip_displacement_m" in nl["stop_reason"]


@pytest.mark.parametrize("name", ["generator", "amplifier", "sensor_base", "sensor_tip"])
def test_instrument_killed_mid_stage(tmp_path, sim, name):
    cfg = rig_config(tmp_path, sim)
    tape = Tape(when=lambda b: b.stage == "linear" and b.amplitude_vpp >= 0.4, action=lambda: sim.kill(name))
    t0 = time.monotonic()
    out = acquire(cfg, small_protocol(), tmp_path / "run.h5", lockstep=True, observers=[tape])
    assert time.monotonic() - t0 < 20
    assert out.status == "error"
    label = {"generator": "signal generator", "amplifier": "amplifier", "sensor_base": "laser sensor base",
             "sensor_tip": "laser sensor tip"}[name]
    assert label in out.reason.lower()
    # the last event says what was confirmed by reading the instruments back, nothing more
    last = read_events(out.path)[-1]["message"]
    generator_off, amplifier_muted = "generator output off (read back)", "amplifier muted (read back"
    assert (generator_off in last) == (name != "generator"), last
    assert (amplifier_muted in last) == (name != "amplifier"), last
    if name == "amplifier":
        assert "amplifier NOT confirmed muted" in last and "comms watchdog" in last
    deadline = time.monotonic() + 3.0  # the amplifier watchdog (2 s) covers a dead amplifier link
    while sim.world.is_driven() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not sim.world.is_driven()
    info = read_info(out.path)
    assert info["status"] == "error" and info["clean_close"]
    assert info["stages"]["linear"]["status"] == "error"
    run = load_run(out.path)
    ramp_s = 0.4 / cfg.limits["ramp_rate_vpp_per_s"]  # killed once the linear stage reached 0.4 Vpp
    assert run.stage("linear").t.size >= ramp_s * FS  # the data up to the failure is kept


def test_abort_during_a_trip_ramp_cuts_at_once(tmp_path, sim):
    cfg = rig_config(tmp_path, sim, max_tip_displacement_m=0.0001)
    holder = {}

    class AbortWhenStopping(Tape):
        def on_state(self, state):
            super().on_state(state)
            if state == "stopping":
                self.fired = len(self.blocks)
                holder["runner"].abort("operator")

    tape = AbortWhenStopping()
    out = acquire(cfg, small_protocol(), tmp_path / "run.h5", lockstep=True, observers=[tape],
                  on_runner=lambda r: holder.setdefault("runner", r))
    assert out.status == "tripped"
    assert len(tape.blocks) - tape.fired <= 1
    assert not sim.world.is_driven()
    assert any("cut at once" in e["message"] for e in read_events(out.path))


QUICK_PROTOCOL = """
[run]
settle_s = 0.3
[linear]
frequency_hz = 8.0
amplitude_vpp = 0.4
duration_s = 0.5
[resonance_search]
enabled = false
[nonlinear]
frequency_hz = 12.0
start_vpp = 0.1
step_factor = 1.5
max_vpp = 0.15
dwell_s = 0.3
analysis_s = 0.2
hold_s = 0.0
"""


def test_every_stage_records_its_pre_trigger_at_rest_before_the_drive(tmp_path, sim):
    """The stage's record opens with ``run.pre_trigger_s`` (0.1 s by default) acquired with the
    output off: the drive goes on inside the record, never before its first sample. Without it the
    record began with the drive's first block: over its first 0.1 s the base read up to 28 um and
    the tip 48 um here (noise 0.2 um)."""
    import tomllib

    cfg = rig_config(tmp_path, sim)
    protocol = parse_protocol(tomllib.loads(QUICK_PROTOCOL), QUICK_PROTOCOL, "quick-protocol")
    assert protocol["run"]["pre_trigger_s"] == 0.1          # the default
    tape = Tape()
    out = acquire(cfg, protocol, tmp_path / "run.h5", lockstep=True, observers=[tape])
    assert out.status == "complete", out.reason
    fs = cfg.acquisition["sample_rate_hz"]
    n_pre = int(round(0.1 * fs))
    info = read_info(out.path)
    for name in ("linear", "nonlinear"):
        assert info["stages"][name]["settings"]["pre_trigger_s"] == 0.1
        blocks = [b for b in tape.blocks if b[3] == name]
        pre = [b for b in blocks if b[0] < blocks[0][0] + n_pre]
        assert sum(b[1] for b in pre) >= n_pre and not any(b[4] for b in pre), name   # output off
        with h5py.File(out.path, "r") as f:
            g = f[f"entry/stages/{name}"]
            first_drive = int(g["steps"]["sample_index"][0])
            assert first_drive >= g.attrs["start_index"] + n_pre, name
    # the first stage (nothing rings before it): base and tip at rest, within the sensor noise
    noise = sim.world.config["sensors"]["noise_std"]
    lin = load_run(out.path).stage("linear")
    for channel in ("x_base", "x_tip"):
        x = lin.channels[channel][:n_pre]
        assert np.max(np.abs(x)) < 6 * noise, channel                      # 0.81 um against 0.2 um noise
        assert abs(np.polyfit(lin.t[:n_pre], x, 1)[0]) < 1e-5, channel     # no motion: |slope| < 0.01 mm/s


def test_a_runner_that_falls_behind_keeps_its_ramp_steps(tmp_path):
    """A slow observer stalls the runner (real time, not lockstep) once on the ramp up and once on
    the abort's ramp down: the next block is long, and a step sized on it would be a jump of the
    drive. Every amplitude change between blocks stays within the ramp's rate times the nominal
    block, and the operator is told once that ramps take longer."""
    stalls = {"up": False, "down": False}
    holder = {}

    class Stall(Tape):
        def on_block(self, block):
            super().on_block(block)
            if block.stage == "linear" and 0.1 < block.amplitude_vpp < 0.3 and not stalls["up"]:
                stalls["up"] = True
                time.sleep(0.4)
            elif block.stage == "linear" and block.amplitude_vpp >= 0.4 and "runner" in holder \
                    and not holder.get("aborted"):
                holder["aborted"] = True
                holder["runner"].abort("operator pressed stop")
            elif holder.get("aborted") and 0.0 < block.amplitude_vpp < 0.3 and not stalls["down"]:
                stalls["down"] = True
                time.sleep(0.4)

    with simulated_rig(speed=1.0, seed=5) as (rig, _):
        cfg = rig_config(tmp_path, rig)
        tape = Stall()
        out = acquire(cfg, small_protocol(), tmp_path / "run.h5", observers=[tape],
                      on_runner=lambda r: holder.setdefault("runner", r))
        assert not rig.world.is_driven()
    assert out.status == "aborted", out.reason
    assert stalls["up"] and stalls["down"]
    n = np.array([b[1] for b in tape.blocks])
    assert n.max() >= 0.3 * FS       # the stalls did make long blocks
    block_s = cfg.acquisition["block_s"]
    lim = cfg.data["limits"]
    fastest = max(lim["ramp_rate_vpp_per_s"], 0.4 / lim["abort_ramp_s"])
    steps = np.abs(np.diff(tape.amplitudes()))
    assert steps.max() <= fastest * block_s + 1e-9, (steps.max(), fastest * block_s)
    assert tape.amplitudes()[-1] == 0.0
    assert sum("during a ramp" in m and "take longer" in m for _, m in tape.events) == 1   # said once

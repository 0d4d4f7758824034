"""The GUI's live quantities (no Qt): linear step and nonlinear loop against ground truth."""
import math
import tomllib

import numpy as np
import pytest

from rig.gui.live_state import LinearStep, LiveData, linear_step, nonlinear_loop


def _linear_response(K, c, f, fs=10000.0, seconds=2.0, amp=1e-3, noise=0.0, seed=0):
    """Steady state of y'' + c y' + K y = -x_base'' for x_base = amp sin(w t) (exact)."""
    w = 2 * math.pi * f
    t = np.arange(int(seconds * fs)) / fs
    xb = amp * np.sin(w * t)
    H = w * w / (K - w * w + 1j * w * c)          # Y / X_base
    y = np.imag(amp * H * np.exp(1j * w * t))
    rng = np.random.default_rng(seed)
    return xb + noise * rng.standard_normal(t.size), xb + y + noise * rng.standard_normal(t.size)


def test_linear_step_recovers_stiffness_and_damping():
    xb, xt = _linear_response(K=8000.0, c=3.5, f=8.0)
    s = linear_step(xb, xt, 10000.0, 8.0)
    assert s.K_m == pytest.approx(8000.0, rel=1e-9)
    assert s.c_m == pytest.approx(3.5, rel=1e-7)
    # with sensor noise (0.1 um on 0.05 mm of relative motion) still close
    xb, xt = _linear_response(K=8000.0, c=3.5, f=8.0, amp=1e-4, noise=1e-7)
    s = linear_step(xb, xt, 10000.0, 8.0)
    assert s.K_m == pytest.approx(8000.0, rel=0.005)
    assert s.c_m == pytest.approx(3.5, rel=0.1)


def test_linear_step_refuses_less_than_a_period():
    with pytest.raises(ValueError, match="less than one period"):
        linear_step(np.zeros(100), np.zeros(100), 10000.0, 8.0)


def test_nonlinear_loop_of_a_linear_specimen_is_zero_and_of_a_cubic_spring_is_its_force():
    step = LinearStep(K_m=8000.0, c_m=3.5, frequency_hz=12.0, relative_amplitude=0.0, n_samples=0)
    xb, xt = _linear_response(K=8000.0, c=3.5, f=12.0)
    y, fn = nonlinear_loop(xb, xt, 10000.0, 12.0, step)
    assert np.ptp(y) == pytest.approx(2 * np.max(np.abs(xt - xb)), rel=1e-3)
    assert np.max(np.abs(fn)) < 1e-6 * 8000.0 * np.max(np.abs(y))
    # a cubic spring, integrated to steady state: Fn(y) = k3 y^3 (no loop area)
    from scipy.integrate import solve_ivp

    K, c, k3, f, amp = 8000.0, 3.5, 4e8, 12.0, 5e-4
    w = 2 * math.pi * f

    def rhs(t, s):
        return [s[1], amp * w * w * math.sin(w * t) - c * s[1] - K * s[0] - k3 * s[0] ** 3]

    fs = 10000.0
    t = np.arange(int(6.0 * fs)) / fs
    sol = solve_ivp(rhs, (0, t[-1]), [0.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-13, method="DOP853")
    y_true = sol.y[0]
    xb = amp * np.sin(w * t)
    keep = t >= 4.0                                # after the transient (decay time 2/c = 0.6 s)
    y, fn = nonlinear_loop(xb[keep], xb[keep] + y_true[keep], fs, f, step, n_harmonics=7)
    cubic = k3 * y ** 3
    assert np.max(np.abs(fn - cubic)) < 0.02 * np.max(np.abs(cubic))


def test_live_data_on_the_simulated_rig_knows_the_linear_step():
    """Fed by the real runner (lockstep): the linear step matches the simulator's specimen."""
    from rig.protocol import parse_protocol
    from rig.session import acquire, simulated_rig

    text = """
[run]
settle_s = 0.2
[linear]
frequency_hz = 8.0
amplitude_vpp = 0.4
duration_s = 3.0
[resonance_search]
enabled = false
[nonlinear]
frequency_hz = 14.0
start_vpp = 0.1
step_factor = 2.0
max_vpp = 0.2
dwell_s = 0.5
analysis_s = 0.25
hold_s = 0.0
"""
    live = LiveData(seconds=10.0)
    with simulated_rig(speed=None, seed=3) as (sim, cfg):
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            out = acquire(cfg, parse_protocol(tomllib.loads(text), text, "t"), f"{d}/run.h5", lockstep=True,
                          observers=[live])
        truth = sim.world.truth()
    assert out.status == "complete", out.reason
    assert live.linear is not None, live.linear_error
    # small amplitude: the Bouc-Wen force acts as a spring alpha_m, so K_m = k_m + alpha_m
    assert live.linear.K_m == pytest.approx(truth["k_m"] + truth["alpha_m"], rel=0.01)
    assert live.linear.c_m == pytest.approx(truth["c_m"], rel=0.2)
    assert live.linear.n_samples == 30000
    assert list(live.amplitudes) == ["linear", "nonlinear"]
    assert live.stages_done == [("linear", "complete"), ("nonlinear", "complete")]
    t, xb, xt = live.traces(2.0)
    assert t.size == 20000 and np.all(np.diff(t) > 0)


def test_lag_grows_when_blocks_fall_behind_real_time():
    import time

    from rig.instruments import Block

    def block(i0, n=500):
        x = np.zeros(n)
        return Block(index0=i0, fs=10000.0, x_base=x, x_tip=x, flags_base=np.zeros(n, np.uint8),
                     flags_tip=np.zeros(n, np.uint8))

    live = LiveData()
    assert live.lag(1.0) == 0.0
    live.on_block(block(0))
    time.sleep(0.3)
    live.on_block(block(500))          # 0.05 s of rig time in 0.3 s of wall time
    assert live.lag(1.0) == pytest.approx(0.25, abs=0.05)
    assert live.lag(2.0) == pytest.approx(0.55, abs=0.1)
    assert live.lag(0.0) == 0.0         # lockstep: no real-time clock to fall behind


STAGES_TEXT = """
[run]
settle_s = 0.2
[linear]
frequency_hz = 8.0
amplitude_vpp = 0.4
duration_s = 1.0
[resonance_search]
start_hz = 8.0
stop_hz = 25.0
steps = 3
refine_steps = 0
amplitude_vpp = 0.05
settle_s = 0.3
measure_s = 0.2
[nonlinear]
start_vpp = 0.1
step_factor = 2.0
max_vpp = 0.2
dwell_s = 0.4
analysis_s = 0.2
hold_s = 0.0
"""


@pytest.mark.parametrize("speed", [None, 3.0], ids=["lockstep", "3x"])
def test_stage_amplitudes_are_measured_on_the_stage_s_own_samples(speed, tmp_path):
    """Real runner, real simulated rig over its sockets, lockstep and at 3 x real time (blocks of 0.15 s
    of rig time): every live amplitude is half the peak-to-peak of y = x_tip - x_base over the newest
    0.2 s (every drive frequency here is above 7.5 Hz: 1.5 periods < 0.2 s) of the samples recorded
    under the stage it is filed under, i.e. the window is cut at the stage's first sample. Without the
    cut a stage's first windows reached back into the samples before it (the previous stage's
    ramp-down ringing, the rest before it)."""
    from rig.protocol import parse_protocol
    from rig.session import acquire, simulated_rig
    from shakerlab.runfile.reader import read_run

    live = LiveData(seconds=10.0)
    with simulated_rig(speed=speed, seed=3) as (sim, cfg):
        out = acquire(cfg, parse_protocol(tomllib.loads(STAGES_TEXT), STAGES_TEXT, "t"), tmp_path / "run.h5",
                      lockstep=speed is None, observers=[live])
    assert out.status == "complete", out.reason
    run = read_run(out.path)
    series = live.amplitude_series()
    assert list(series) == ["linear", "resonance_search", "nonlinear"]
    fs, n_window = live.fs, int(round(0.2 * live.fs))
    checked = 0
    for name, (times, amps) in series.items():
        st = run.stages[name]
        index = np.round((st.t + st.settings["t0"]) * fs).astype(int)   # the stage's sample indices
        assert np.all(np.diff(index) == 1)
        y = st.channels["x_tip"] - st.channels["x_base"]
        for t_rec, amp in zip(times, amps):
            end = int(round(t_rec * fs))
            assert index[0] < end <= index[-1] + 1, (name, t_rec)      # filed at a time inside the stage
            keep = (index >= end - n_window) & (index < end)
            assert amp == pytest.approx(0.5 * np.ptp(y[keep]), rel=1e-9, abs=1e-15), (name, t_rec)
            checked += 1
    assert checked >= 30

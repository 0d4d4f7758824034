"""A velocity record's stage that starts in motion, however small against the stage's motion, is
not taken for a stage recorded from rest when its start stands out of the noise
(recon.signals.at_rest, recon.model.HystereticModel.measured_start).

The rule used to call a start at rest when its velocity was within 5 % of the stage's rms: a stage
that starts in a small motion then kept its free decay in every fit. On the independent generator
at 60 dB (rig protocol, seed 9) the nonlinear stage starts at 1 % of its rms velocity, 16 times its
noise: the damping came out 7 % off and a spurious y^3 was kept (0.16 % and the exact terms with
the start fitted)."""
import numpy as np
import pytest

from recon.model import HystereticModel
from recon.signals import at_rest
from shakerlab.run_data import Stage

FS = 2000.0
TRUTH = dict(excitation="base", c_m=1.0, k_m=4000.0, alpha_m=2500.0, gamma=240.0, delta=650.0,
             fn_m={"y^2": -9.5e4})


def _stage(start, snr_db=60.0, seed=0, seconds=6.0, offset=0.0):
    """A base-excited stage recorded as relative tip velocity, simulated from ``start`` = (y, y', z);
    ``offset``: the velocity sensor's constant offset, as a share of the channel's rms."""
    m = HystereticModel(**TRUTH)
    t = np.arange(int(seconds * FS)) / FS
    w = 2 * np.pi * 10.0
    xb = 2e-3 * np.sin(w * t)
    u = 2e-3 * w * w * np.sin(w * t)             # -x_base''
    y, dy, _ = m.simulate(t, u, initial=start)
    vb = 2e-3 * w * np.cos(w * t)
    rng = np.random.default_rng(seed)
    v_tip = vb + dy
    v_tip = v_tip + offset * np.sqrt(np.mean(v_tip ** 2)) \
        + rng.normal(0.0, np.sqrt(np.mean(v_tip ** 2)) / 10 ** (snr_db / 20), t.size)
    xb = xb + rng.normal(0.0, np.sqrt(np.mean(xb ** 2)) / 10 ** (snr_db / 20), t.size)
    return m, Stage("nonlinear", t, {"x_base": xb, "v_tip": v_tip}, "base"), y, dy


def test_a_small_start_in_motion_is_fitted_not_taken_for_rest():
    # a start at about 1 % of the stage's rms velocity: above the noise of its edge estimate
    m, st, y, dy = _stage((-1e-4, 8e-3, -0.3))
    v_rms = float(np.sqrt(np.mean(dy ** 2)))
    assert abs(dy[0]) < 0.05 * v_rms                 # what the old rule called rest
    y0, v0, z0 = m.stage_start(st)
    assert (y0, v0, z0) != (0.0, 0.0, 0.0)
    assert v0 == pytest.approx(8e-3, rel=0.2)
    # from the estimated start the model follows the record's first second to its noise; from rest it
    # would carry the start's free decay
    t = st.t[:int(FS)]
    u = m.stage_input(st)[:t.size]
    from_est = m.simulate_quantity(t, u, (y0, v0, z0), 1)
    from_rest = m.simulate_quantity(t, u, (0.0, 0.0, 0.0), 1)
    err_est = float(np.sqrt(np.mean((from_est - dy[:t.size]) ** 2)))
    err_rest = float(np.sqrt(np.mean((from_rest - dy[:t.size]) ** 2)))
    assert err_est < 0.2 * err_rest, (err_est, err_rest)


def test_a_stage_recorded_from_rest_is_still_at_rest():
    m, st, _, _ = _stage((0.0, 0.0, 0.0))
    assert m.stage_start(st) == (0.0, 0.0, 0.0)


def test_a_constant_sensor_offset_is_no_motion():
    # a velocity sensor's constant offset (1 % of the channel's rms) stands out of the noise, so the
    # start is fitted; the fit takes the offset as a nuisance, as the output-error fits do, and the
    # start stays near rest instead of taking the offset for a start velocity
    m, st, _, _ = _stage((0.0, 0.0, 0.0), offset=0.01)
    off = 0.01 * float(np.sqrt(np.mean(st.measured["v_tip"] ** 2)))
    assert abs(m.stage_start(st)[1]) < 0.2 * off
    m, st, _, _ = _stage((-1e-4, 8e-3, -0.3), offset=0.01)
    assert m.stage_start(st)[1] == pytest.approx(8e-3, rel=0.2)


def test_rest_needs_both_the_value_and_its_derivative_within_the_noise():
    # a turning point of the motion: velocity near 0, acceleration near its peak
    assert not at_rest(value=1e-6, noise=1e-6, slope=0.5, slope_noise=0.01, slope_rms=0.7)
    # a value small against the motion but 16 times its noise
    assert not at_rest(value=7e-4, noise=4.4e-5, slope=0.03, slope_noise=0.06, slope_rms=4.9)
    assert at_rest(value=2e-6, noise=1e-6, slope=0.01, slope_noise=0.01, slope_rms=0.7)


def _acceleration_stage(start, snr_db=60.0, seed=0, seconds=6.0):
    """The stage of :func:`_stage` recorded as tip acceleration."""
    m = HystereticModel(**TRUTH)
    t = np.arange(int(seconds * FS)) / FS
    w = 2 * np.pi * 10.0
    xb = 2e-3 * np.sin(w * t)
    u = 2e-3 * w * w * np.sin(w * t)
    y, dy, z = m.simulate(t, u, initial=start)
    a_tip = -u + m.acceleration(t, u, y, dy, z)          # x_base'' + y''
    rng = np.random.default_rng(seed)
    a_tip = a_tip + rng.normal(0.0, np.sqrt(np.mean(a_tip ** 2)) / 10 ** (snr_db / 20), t.size)
    xb = xb + rng.normal(0.0, np.sqrt(np.mean(xb ** 2)) / 10 ** (snr_db / 20), t.size)
    return m, Stage("nonlinear", t, {"x_base": xb, "a_tip": a_tip}, "base")


@pytest.mark.parametrize("seed", range(4))
def test_an_acceleration_record_from_rest_is_at_rest(seed):
    # the velocity integrated from an acceleration carries the integration's constant at its edge,
    # which its white noise floor does not measure: the rule allows 5 % of the stage's rms for it
    m, st = _acceleration_stage((0.0, 0.0, 0.0), seed=seed)
    assert m.stage_start(st) == (0.0, 0.0, 0.0)


def test_a_steady_sine_that_starts_at_a_turning_point_is_not_taken_for_rest():
    # a sine record taken in steady state from the instant the tip velocity crosses zero (the real
    # bolted beam's 9.5 Hz sine starts so): the velocity's edge value is within 5 % of its rms, which
    # the old rule called rest, while its derivative is near its peak. From the fitted start the model
    # follows the record in velocity; from rest it carries a free decay over the whole record
    m = HystereticModel(**TRUTH)
    w = 2 * np.pi * 10.0
    t_all = np.arange(int(26.0 * FS)) / FS
    u_all = 2e-3 * w * w * np.sin(w * t_all)
    _, dy_all, _ = m.simulate(t_all, u_all, initial=(0.0, 0.0, 0.0))
    k0 = int(20.0 * FS)
    k0 += int(np.flatnonzero(np.diff(np.sign(dy_all[k0:])) != 0)[0]) + 1     # the next zero crossing
    sl = slice(k0, k0 + int(6.0 * FS))
    t = t_all[sl] - t_all[k0]
    rng = np.random.default_rng(3)
    vb = 2e-3 * w * np.cos(w * t_all[sl])
    v_tip = vb + dy_all[sl]
    v_tip = v_tip + rng.normal(0.0, np.sqrt(np.mean(v_tip ** 2)) / 1000.0, t.size)
    xb = 2e-3 * np.sin(w * t_all[sl])
    xb = xb + rng.normal(0.0, np.sqrt(np.mean(xb ** 2)) / 1000.0, t.size)
    st = Stage("validation", t, {"x_base": xb, "v_tip": v_tip}, "base")
    v_rms = float(np.sqrt(np.mean(dy_all[sl] ** 2)))
    assert abs(dy_all[k0]) < 0.05 * v_rms                  # what the old rule called rest
    start = m.stage_start(st)
    assert start != (0.0, 0.0, 0.0)
    u = m.stage_input(st)
    sim, rec = m.simulate_measured(st)
    from_rest = m.simulate_quantity(t, u, (0.0, 0.0, 0.0), 1)
    err_fit = float(np.sqrt(np.mean((sim - rec) ** 2)))
    err_rest = float(np.sqrt(np.mean((from_rest + np.mean(rec - from_rest) - rec) ** 2)))
    assert err_fit < 0.2 * err_rest, (err_fit, err_rest)

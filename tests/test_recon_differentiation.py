"""Savitzky-Golay differentiation: the known passband loss of the second-derivative filter and
its correction (recon.differentiation.derivative_gain / undo_passband_loss), which the model's
input u = -x_base'' goes through (recon.model.HystereticModel.stage_input)."""
import numpy as np

from recon.differentiation import derivative_gain, derivatives, undo_passband_loss
from recon.model import HystereticModel
from recon.testing.truth import sdof_run

DT = 1.0 / 2000.0
WINDOW, ORDER = 109, 7


def _tone(f, n=20000):
    t = np.arange(n) * DT
    return t, np.sin(2 * np.pi * f * t), -(2 * np.pi * f) ** 2 * np.sin(2 * np.pi * f * t)


def test_gain_is_the_measured_attenuation_of_a_tone():
    for f in (12.5, 40.0, 80.0):
        t, x, xdd = _tone(f)
        est = derivatives(x, DT, WINDOW, ORDER, 2)[2]
        mid = slice(WINDOW, -WINDOW)
        measured = float(est[mid] @ xdd[mid] / (xdd[mid] @ xdd[mid]))
        assert abs(derivative_gain(WINDOW, ORDER, 2, DT, [f])[0] - measured) < 2e-6, f
    g = derivative_gain(WINDOW, ORDER, 2, DT, [0.0, 12.5, 200.0])
    assert g[0] == 1.0 and 0.999 < g[1] < 1.0 and g[2] < 0.5      # passband loss, then the roll-off


def test_undoing_the_loss_recovers_the_exact_derivative_in_the_passband():
    t, x, xdd = _tone(12.5)
    est = derivatives(x, DT, WINDOW, ORDER, 2)[2]
    fixed = undo_passband_loss(est, DT, WINDOW, ORDER)
    mid = slice(2 * WINDOW, -2 * WINDOW)
    before = np.max(np.abs(est[mid] - xdd[mid])) / np.max(np.abs(xdd))
    after = np.max(np.abs(fixed[mid] - xdd[mid])) / np.max(np.abs(xdd))
    assert before > 5e-4 and after < 0.05 * before, (before, after)
    # outside the passband nothing is amplified: white noise keeps its level within 1 %
    e = derivatives(np.random.default_rng(0).normal(size=t.size), DT, WINDOW, ORDER, 2)[2]
    assert np.std(undo_passband_loss(e, DT, WINDOW, ORDER)) < 1.01 * np.std(e)


def test_model_input_carries_no_filter_bias():
    # the base-excited model's input against the exact -x_base'' of the ground truth; at 60 dB
    # the filter chosen (109 samples, order 7) loses 0.083 % at the drive without the correction
    run, truth = sdof_run("base", snr_db=60.0, seed=0)
    st = run.stage("nonlinear")
    model = HystereticModel(excitation="base", c_m=3.0, k_m=4000.0, alpha_m=5000.0, gamma=500.0, delta=300.0)
    u, exact = model.stage_input(st), st.settings["truth"]["u"]
    mid = slice(u.size // 10, -u.size // 10)
    gain = float(u[mid] @ exact[mid] / (exact[mid] @ exact[mid]))
    assert abs(gain - 1.0) < 2e-5, gain

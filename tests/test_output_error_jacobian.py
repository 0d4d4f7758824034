"""The output-error fits' Jacobian from forward sensitivities (recon.simulation.sensitivity,
OutputError.jacobian) against central differences of the residual itself, and the cases where the
fits keep forward differences (the checked fallback)."""
import numpy as np
import pytest
from scipy.optimize._numdiff import approx_derivative

from recon.model import HystereticModel
from recon.output_error.problem import OutputError, term_scale


def _item(model, n=3000, dt=1e-3, start=None, order=0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    u = 30 * np.sin(2 * np.pi * 7 * t) + 10 * np.sin(2 * np.pi * 13 * t + 0.3)
    init = None
    if start is not None:
        y0, v0, a0 = start
        init = (y0, v0, model.start_z(u[0], y0, v0, a0))
    y, dy, _ = model.simulate(t, u, initial=init)
    y = y + rng.normal(0, 1e-3 * np.std(y), n)
    item = (t, u, y, start if start is not None else (0.0, 0.0, 0.0))
    if order:
        item = item + ((1, dy + rng.normal(0, 1e-3 * np.std(dy), n)),)
    return item


def _model(**kw):
    base = dict(excitation="base", c_m=2.0, k_m=1500.0, alpha_m=1100.0, gamma=900.0, delta=280.0,
                fn_m={"y^2": 2e5, "y^3": 6e8, "y^2*dy": 3e3})
    base.update(kw)
    return HystereticModel(**base)


def _check(prob, tol=1e-4):
    assert prob.analytic
    p0 = np.random.default_rng(1).normal(size=len(prob.keys)) * 1e-3
    ja = prob.jacobian(p0)
    # central differences with a step small enough that few |y'| and |z| kinks fall inside it (the
    # residual is piecewise smooth: a step that moves a stage's y' across zero sees the kink)
    jc = approx_derivative(prob.residual, p0, method="3-point", abs_step=1e-8)
    assert ja.shape == jc.shape
    err = np.max(np.abs(ja - jc), axis=0) / np.max(np.abs(jc), axis=0)
    assert np.all(err < tol), dict(zip(prob.keys, err))


def test_displacement_from_rest_and_in_motion_with_masks_and_weights():
    m = _model()
    a = _item(m)
    b = _item(m, start=(2e-4, 5e-3, 0.4), seed=1)
    mask = np.arange(b[2].size) % 3 == 0
    _check(OutputError(m, [a, b], masks=[None, mask], noise=[1e-6, 2e-6]))


def test_velocity_target_takes_its_mean_out():
    m = _model()
    _check(OutputError(m, [_item(m, order=1, start=(1e-4, 2e-3, 0.1))]))


def test_force_excitation_gain_and_input_offset():
    m = _model(excitation="force", inv_m=2.5, input_offset=0.3)
    _check(OutputError(m, [_item(m, start=(1e-4, 2e-3, 0.1))]))


def test_coarse_sampling_with_substeps():
    m = _model(k_m=40000.0, alpha_m=50000.0)          # f_n ~ 48 Hz at 1150 Hz: 3 sub-steps
    _check(OutputError(m, [_item(m, dt=1 / 1150.0)]))


def test_no_hysteresis_and_a_subset_of_free_parameters():
    m = _model(alpha_m=0.0, gamma=0.0, delta=0.0)
    _check(OutputError(m, [_item(m, start=(1e-4, 2e-3, 0.1))], free=["c_m", "k_m", "fn:y^3"]))


def test_diverged_trial_has_a_zero_jacobian():
    m = _model()
    prob = OutputError(m, [_item(m)])
    p = np.zeros(len(prob.keys))
    p[prob.keys.index("k_m")] = -1e4             # k = -1.5e7: the simulation blows up
    assert np.all(prob.residual(p) == prob.residual(p)[0])
    assert not np.any(prob.jacobian(p))


@pytest.mark.parametrize("case", ["exciter", "acceleration"])
def test_forward_differences_where_sensitivities_do_not_reach(case):
    if case == "exciter":
        m = _model(excitation="force", inv_m=2.0, drive_u2=0.1, drive_hp=1.0)
        item = _item(_model(excitation="force", inv_m=2.0))
    else:
        m = _model()
        item = _item(m)
        item = item + ((2, np.gradient(np.gradient(item[2], 1e-3), 1e-3)),)
    prob = OutputError(m, [item])
    assert not prob.analytic
    assert prob.jac_option() == "2-point"


def test_a_small_fn_term_is_scaled_by_the_size_at_which_it_matters():
    m = _model(fn_m={"y^2": 2e5, "y^3": 1.0})
    item = _item(_model())
    prob = OutputError(m, [item])
    i = prob.keys.index("fn:y^3")
    y = item[2]
    v = np.diff(y) / 1e-3
    expected = term_scale("y^3", m.K_m, float(np.std(y)), float(np.sqrt(np.mean(v ** 2))))
    assert prob.scale[i] == pytest.approx(expected, rel=1e-9)
    assert prob.scale[i] > 1e3


def test_overflowing_sensitivities_give_way_to_forward_differences():
    from recon.output_error.problem import finite_or_differences, forward_differences

    def residual(p):
        return np.array([p[0] ** 2, np.sin(p[1]), p[0] * p[1]])

    def overflowing(p):
        return np.full((3, 2), np.inf)

    p = np.array([0.3, -1.2])
    J = finite_or_differences(overflowing, residual)(p)
    assert np.all(np.isfinite(J))
    assert np.array_equal(J, forward_differences(residual, p))
    assert J == pytest.approx(np.array([[0.6, 0.0], [0.0, np.cos(-1.2)], [-1.2, 0.3]]), abs=1e-5)
    exact = lambda q: np.array([[2 * q[0], 0.0], [0.0, np.cos(q[1])], [q[1], q[0]]])  # noqa: E731
    assert np.array_equal(finite_or_differences(exact, residual)(p), exact(p))

"""The diagnosis's candidate fits take their Jacobian from forward sensitivities
(recon.diagnosis.jacobian, recon.simulation.sensitivity.simulate_extended_sensitivities): checked
against central differences of the fit's own residual for every kind of column (the baseline's,
the extra physics that act through the simulation, the reading's own parameters), and the
extended kernel's states against the simulation kernel's."""
import numpy as np
import pytest
from scipy.optimize._numdiff import approx_derivative

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.jacobian import fit_jacobian, supported
from recon.output_error.problem import get_parameter, parameter_scales, set_parameter
from recon.simulation import rk4
from recon.simulation.sensitivity import extended_column_codes, simulate_extended_sensitivities
from recon.testing.concealed import concealed_run

CASES = {
    "baseline": ({}, None),
    "friction": ({"mu": 0.05, "v0": 1e-3}, ["x:mu", "x:v0", "c_m", "k_m"]),
    "quadratic damping": ({"c2": 5.0}, ["x:c2", "c_m", "alpha_m"]),
    "contact": ({"kc": 300.0, "gap": 5e-4}, ["x:kc", "x:gap", "k_m"]),
    "drift": ({"drift": 1e-3}, ["x:drift", "k_m"]),
    "higher mode": ({"w2": 2 * np.pi * 60, "zeta2": 0.02, "phi2": 0.05}, ["x:w2", "x:phi2", "c_m"]),
    "mode on the point": ({"w2": 2 * np.pi * 60, "zeta2": 0.05, "phi2": 0.05, "drive2": 0.5},
                          ["x:w2", "x:drive2", "x:zeta2"]),
    "reading": ({"delay": 3.3e-4, "tip_scale": 0.01}, ["x:delay", "x:tip_scale", "k_m"]),
    "reading from zero": ({}, ["x:tip_scale", "gamma"]),
}


@pytest.fixture(scope="module", params=["base", "force"])
def prepared(request):
    run, truth, _, baseline = concealed_run(None, excitation=request.param, duration=2.0, seed=3)
    return baseline, [d.thinned() for d in rank.prepare(run, baseline)]


@pytest.mark.parametrize("case", sorted(CASES))
def test_candidate_fit_jacobian_equals_central_differences(prepared, case):
    baseline, data = prepared
    extras, keys = CASES[case]
    keys = keys or rank.baseline_keys(baseline)
    am = AugmentedModel(baseline, dict(extras))
    assert supported(am, keys)
    data = rank.own_starts(am, data)
    x0 = np.array([get_parameter(am, k) for k in keys])
    sc = parameter_scales(keys, x0, baseline.gamma + baseline.delta, {"x:delay": 1e-4, "x:tip_scale": 1e-2})

    def build(p):
        m = am.copy()
        for i, k in enumerate(keys):
            set_parameter(m, k, x0[i] + p[i] * sc[i])
        return m

    jac = fit_jacobian(build, keys, sc, data, rank.initial_for, rank.fit_scale, am)
    p0 = np.full(len(keys), 1e-4)
    ja = jac(p0)
    # a small central step (the residual is piecewise smooth: |y'|, |z|, a contact and the delay's
    # interpolation have kinks a larger step would straddle)
    jc = approx_derivative(lambda p: rank.fit_residual(build(p), data), p0, method="3-point", abs_step=1e-8)
    err = np.max(np.abs(ja - jc), axis=0) / np.max(np.abs(jc), axis=0)
    limit = {"x:delay": 2e-3, "x:zeta2": 2e-2}       # columns an order smaller: rounding in the step
    for k, e in zip(keys, err):
        assert e < limit.get(k, 1e-4), (k, e)


def test_extended_kernel_states_equal_the_simulation_kernels():
    n, dt = 3000, 1e-3
    t = np.arange(n) * dt
    u = rk4.kernel_input(2 * np.sin(2 * np.pi * 9 * t))
    coef, p, r = np.array([2e5, 3e3]), np.array([2, 2]), np.array([0, 1])
    P = rk4.kernel_parameters(g=1.0, c=1.6, k=1500.0, alpha=1100.0, gamma=900.0, delta=280.0, mu=0.05, v0=1e-2,
                              c2=2.0, kc=500.0, gap=1e-3, drift=1e-3, w2=300.0, zeta2=0.02, drive2=0.3, gu2=1.0)
    codes = extended_column_codes(["c", "mu", "w2", 0])
    st, _, _ = simulate_extended_sensitivities(u, 0.5, dt, 2, P, coef, p, r, 1e-4, 0.0, 0.0, codes,
                                               np.zeros((5, 4)), 0, False)
    ref = rk4.simulate_extended(u, 0.5, dt, 2, P, coef, p, r, 1e-4, 0.0, 0.0)
    assert np.all(np.isfinite(ref)) and np.any(ref[3])
    assert np.array_equal(st, ref)


def test_an_exciter_model_keeps_forward_differences(prepared):
    baseline, data = prepared
    m = baseline.__class__.from_dict(baseline.to_dict())
    m.drive_u2, m.drive_hp = 0.1, 1.0
    assert not supported(AugmentedModel(m), ["c_m"])
    assert fit_jacobian(lambda p: AugmentedModel(m), ["c_m"], np.ones(1), data, rank.initial_for,
                        rank.fit_scale, AugmentedModel(m)) is None

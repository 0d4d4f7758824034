"""The forward sensitivities of the extended RK4 kernel
(recon.simulation.sensitivity.simulate_extended_sensitivities) against forward differences of the
simulation kernel, for every parameter of the extended model and every fn coefficient: the
sensitivities are the derivatives of the discrete simulation, so the two agree to the differences'
own truncation error. The states are the simulation kernel's, to the bit."""
import numpy as np
import pytest

from recon.simulation.rk4 import I_C, I_SIDE, N_P, P_INDEX, P_NAMES, kernel_input, kernel_parameters, simulate_extended
from recon.simulation.sensitivity import X_COLUMNS, extended_column_codes, simulate_extended_sensitivities


def simulate_sensitivities(u, t0, dt, n_sub, P, coef, p, r, y0, v0, z0, cols, S0):
    """The extended kernel's sensitivities to theta[cols], theta = (P, coef) (kernel slots by index,
    fn coefficients after them): (states, dy/dtheta, dq/dtheta)."""
    names = [P_NAMES[c] if c < N_P else int(c - N_P) for c in cols]
    return simulate_extended_sensitivities(u, t0, dt, n_sub, P, coef, p, r, y0, v0, z0,
                                           extended_column_codes(names), S0, 0, False)


def record(n=3000, dt=1e-3, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    return kernel_input(40.0 * np.sin(2 * np.pi * 7 * t) + 4.0 * rng.standard_normal(n)), dt


# every extra switched on (friction, quadratic damping, a contact that the motion reaches, a stiffness
# drift and a higher mode driven through the measured point's acceleration), two fn terms
PLAIN = dict(g=1.0, c=2.0, k=2000.0, alpha=1500.0, gamma=300.0, delta=100.0)
P = kernel_parameters(**PLAIN, mu=0.3, v0=0.01, c2=5.0, kc=3000.0, gap=0.003, side=1.0, drift=0.01, w2=400.0,
                      zeta2=0.03, drive2=0.2, gu2=1.0)
COEF, PE, RE = np.array([1e6, 50.0]), np.array([3, 2]), np.array([0, 1])


@pytest.mark.parametrize("n_sub", [1, 2])
def test_sensitivities_are_the_derivatives_of_the_simulation(n_sub):
    u, dt = record()
    # every slot the sensitivities take (side is a sign; gu2 follows from drive2 and the excitation)
    cols = np.array([P_INDEX[n] for n in X_COLUMNS] + [N_P + j for j in range(COEF.size)])
    S0 = np.zeros((5, cols.size))
    states, sy, sq = simulate_sensitivities(u, 0.0, dt, n_sub, P, COEF, PE, RE, 0.0, 0.0, 0.0, cols, S0)
    plain = simulate_extended(u, 0.0, dt, n_sub, P, COEF, PE, RE, 0.0, 0.0, 0.0)
    # the states are the simulation kernel's: to the bit, or within the last bits where the higher
    # mode's drive holds the point's acceleration (the compiler may order that product differently)
    np.testing.assert_allclose(states, plain, rtol=1e-12, atol=1e-14 * np.max(np.abs(plain)))
    theta = np.concatenate([P, COEF])
    for i, c in enumerate(cols):
        h = 1e-6 * max(abs(theta[c]), 1e-3)
        moved = theta.copy()
        moved[c] += h
        other = simulate_extended(u, 0.0, dt, n_sub, moved[:N_P], moved[N_P:], PE, RE, 0.0, 0.0, 0.0)
        name = P_NAMES[c] if c < N_P else f"coef[{c - N_P}]"
        for got, fd in ((sy[:, i], (other[0] - plain[0]) / h), (sq[:, i], (other[3] - plain[3]) / h)):
            scale = np.max(np.abs(fd))
            if scale == 0.0:
                assert np.max(np.abs(got)) < 1e-9, name
                continue
            assert np.max(np.abs(got - fd)) < 1e-4 * scale, name


def test_initial_sensitivities_are_carried():
    """A start state that depends on a parameter (z0 from the equation of motion) enters through S0:
    d/dc of a run started at z0 = -c v0 equals the run's sensitivity with S0[z] = -v0."""
    u, dt = record(n=1500)
    P1 = kernel_parameters(**PLAIN)
    v0 = 0.02
    cols = np.array([I_C])
    S0 = np.zeros((5, 1))
    S0[2, 0] = -v0
    _, sy, _ = simulate_sensitivities(u, 0.0, dt, 1, P1, COEF, PE, RE, 0.0, v0, -P1[I_C] * v0, cols, S0)
    h = 1e-6 * P1[I_C]
    P2 = kernel_parameters(**{**PLAIN, "c": PLAIN["c"] + h})
    a = simulate_extended(u, 0.0, dt, 1, P1, COEF, PE, RE, 0.0, v0, -P1[I_C] * v0)[0]
    b = simulate_extended(u, 0.0, dt, 1, P2, COEF, PE, RE, 0.0, v0, -P2[I_C] * v0)[0]
    fd = (b - a) / h
    assert np.max(np.abs(sy[:, 0] - fd)) < 1e-4 * np.max(np.abs(fd))


def test_the_parameter_vector_is_built_by_name():
    """kernel_parameters: every slot by its P_NAMES name, v0 and side 1 unless given, the rest 0;
    an unknown name is refused with its name."""
    P = kernel_parameters(mu=0.5, gu2=2.0)
    assert P.shape == (N_P,) and P[P_NAMES.index("mu")] == 0.5 and P[P_NAMES.index("gu2")] == 2.0
    assert {n for n, v in zip(P_NAMES, P) if v != 0.0} == {"mu", "gu2", "v0", "side"}
    assert P[P_NAMES.index("v0")] == 1.0 and P[I_SIDE] == 1.0
    with pytest.raises(ValueError, match="'friction'"):
        kernel_parameters(mu=0.5, friction=1.0)

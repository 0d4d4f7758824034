"""The plain RK4 kernel (recon.simulation.rk4.simulate_plain) is the extended kernel with every
extra off, specialised: the same states to the bit, including where a simulation diverges, and
simulate_states picks it only when no extra acts."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from recon.simulation import rk4

DT = 1e-3


def _input(seed, n=3000):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    return rk4.kernel_input(3.0 * np.sin(2 * np.pi * 7.0 * t) + 0.2 * rng.normal(size=n))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 1000), n_sub=st.integers(1, 3), c=st.floats(0.0, 50.0), k=st.floats(100.0, 5000.0),
       alpha=st.floats(0.0, 3000.0), gamma=st.floats(-500.0, 800.0), delta=st.floats(-500.0, 800.0),
       a2=st.floats(-1e6, 1e6), a3=st.floats(-1e8, 1e8), c3=st.floats(-1e6, 1e6),
       start=st.tuples(st.floats(-1e-3, 1e-3), st.floats(-0.05, 0.05), st.floats(-1.0, 1.0)))
def test_plain_kernel_equals_the_extended_one_to_the_bit(seed, n_sub, c, k, alpha, gamma, delta, a2, a3, c3, start):
    u = _input(seed)
    coef, p, r = np.array([a2, a3, c3]), np.array([2, 3, 2]), np.array([0, 0, 1])
    P = rk4.kernel_parameters(g=1.0, c=c, k=k, alpha=alpha, gamma=gamma, delta=delta)
    ext = rk4.simulate_extended(u, 0.0, DT, n_sub, P, coef, p, r, *start)
    plain = rk4.simulate_plain(u, DT, n_sub, 1.0, c, k, alpha, gamma, delta, coef, p, r, *start)
    assert np.array_equal(ext[:3], plain, equal_nan=True)
    assert np.array_equal(rk4.simulate_states(u, 0.0, DT, n_sub, P, coef, p, r, *start), ext, equal_nan=True)


def test_a_diverging_simulation_is_nan_from_the_same_step_in_both():
    u = _input(1)
    coef, p, r = np.array([-1e12]), np.array([3]), np.array([0])       # a softening cubic that runs away
    P = rk4.kernel_parameters(g=1.0, c=1.0, k=1000.0)
    ext = rk4.simulate_extended(u, 0.0, DT, 1, P, coef, p, r, 0.0, 0.0, 0.0)
    plain = rk4.simulate_states(u, 0.0, DT, 1, P, coef, p, r, 0.0, 0.0, 0.0)
    assert np.isnan(ext[0, -1]) and not np.isnan(ext[0, 0])
    assert np.array_equal(ext, plain, equal_nan=True)


@pytest.mark.parametrize("slot,value", [("mu", 0.5), ("c2", 3.0), ("kc", 500.0), ("drift", 0.01), ("w2", 300.0)])
def test_an_acting_extra_takes_the_extended_kernel(slot, value):
    u = _input(2)
    coef, p, r = np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64)
    P = rk4.kernel_parameters(g=1.0, c=5.0, k=2000.0, alpha=500.0, gamma=100.0, delta=100.0, **{slot: value})
    assert not rk4.extras_off(P)
    got = rk4.simulate_states(u, 0.0, DT, 1, P, coef, p, r, 0.0, 0.0, 0.0)
    assert np.array_equal(got, rk4.simulate_extended(u, 0.0, DT, 1, P, coef, p, r, 0.0, 0.0, 0.0))
    off = P.copy()
    off[rk4.P_INDEX[slot]] = 0.0
    assert rk4.extras_off(off)
    row = 3 if slot == "w2" else 0          # the higher mode is its own state (q), the others act on y
    assert not np.allclose(got[row], rk4.simulate_states(u, 0.0, DT, 1, off, coef, p, r, 0.0, 0.0, 0.0)[row])


def test_every_input_reaches_the_kernels_as_one_array_type():
    """A writable and a read-only input reach the kernel as the same numba type (kernel_input), so
    each kernel is compiled, cached and loaded once, not once per kind of array."""
    u = 3.0 * np.sin(2 * np.pi * 7.0 * np.arange(500) * DT)          # writable
    frozen = u.copy()
    frozen.flags.writeable = False
    coef, p, r = np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64)
    P = rk4.kernel_parameters(g=1.0, c=5.0, k=2000.0, alpha=500.0, gamma=100.0, delta=100.0)
    a = rk4.simulate_states(u, 0.0, DT, 1, P, coef, p, r, 0.0, 0.0, 0.0)
    b = rk4.simulate_states(frozen, 0.0, DT, 1, P, coef, p, r, 0.0, 0.0, 0.0)
    assert np.array_equal(a, b)
    assert u.flags.writeable                       # the caller's array is left as it was
    sigs = rk4.simulate_plain.signatures
    assert sigs and all(not sig[0].mutable for sig in sigs), sigs

"""The sparse regression's folds without a normalised copy of the matrix: the column norms by
blocks of rows equal numpy's whole-matrix sum to the bit, and the selection gives the same answer."""
import numpy as np
import pytest

from recon.regression.sparse import CompressedFolds, GroupedSparseSelector, column_sum_squares


@pytest.mark.parametrize("rows", [1, 7, 16384, 16385, 50000])
def test_column_sum_squares_is_numpys_to_the_bit(rows):
    rng = np.random.default_rng(rows)
    A = rng.normal(size=(rows, 9)) * np.logspace(-4, 4, 9)
    assert np.array_equal(column_sum_squares(A), np.sum(A * A, axis=0))
    assert np.array_equal(column_sum_squares(A, rows=5), np.sum(A * A, axis=0))


def test_folds_hold_only_the_callers_matrix_and_select_as_before():
    rng = np.random.default_rng(1)
    n, p = 6000, 8
    A = rng.normal(size=(n, p)) * np.logspace(-2, 2, p)
    x = np.zeros(p)
    x[[0, 3, 5]] = [1.0, -0.02, 0.5]
    b = A @ x + 1e-3 * rng.normal(size=n)
    cf = CompressedFolds(A, b)
    big = [k for k, v in vars(cf).items() if isinstance(v, np.ndarray) and v.size >= n * p]
    assert big == ["A"] and cf.A is A
    fit = GroupedSparseSelector([[j] for j in range(1, p)], [0]).fit(A, b)
    assert set(np.flatnonzero(fit.support)) == {0, 3, 5}
    assert np.allclose(fit.coef[[0, 3, 5]], x[[0, 3, 5]], rtol=1e-2)


@pytest.mark.parametrize("form, correction, order", [("joint", True, 5), ("joint", False, 4), ("ab", False, 5)])
def test_library_matrix_built_on_demand_is_the_whole_matrix_to_the_bit(form, correction, order):
    """The agent library read a block of rows or a set of columns at a time (LibraryMatrix) equals
    the whole matrix, and the selection on it (folds built one at a time) is the same to the bit."""
    from recon.library.agent import AgentLibrary, dphi, phi
    rng = np.random.default_rng(3)
    n = 40000
    y, dy, ddy, Fn, dFn = (rng.normal(size=n) * s for s in (1e-3, 0.2, 30.0, 5.0, 800.0))
    h = rng.choice([-1, 0, 1], size=n)
    lib = AgentLibrary(order, form, linear_correction=correction, offset=correction)
    theta = np.empty((int(lib.rows(h).sum()), len(lib.columns)))      # the columns by phi and dphi
    yy, dd, d2, F, s = (a[lib.rows(h)] for a in (y, dy, ddy, Fn, h.astype(float)))
    for k, c in enumerate(lib.columns):
        theta[:, k] = {"a": lambda: s * dphi(yy, dd, d2, c.p, c.r), "psi": lambda: dphi(yy, dd, d2, c.p, c.r),
                       "lam_a": lambda: dd * phi(yy, dd, c.p, c.r), "xi": lambda: dd * phi(yy, dd, c.p, c.r),
                       "lam_alpha": lambda: yy * dd, "yy": lambda: yy * dd, "const": lambda: dd,
                       "lin": lambda: s * d2 if c.r == 0 else (s * dd if c.r == 1 else dd * dd)}.get(c.role,
                                                                                               lambda: dd * F)()
    built, target = lib.build(y, dy, ddy, Fn, dFn, h)
    assert np.array_equal(built, theta) and built.flags["C_CONTIGUOUS"]
    matrix, target2 = lib.matrix(y, dy, ddy, Fn, dFn, h)
    assert matrix.shape == theta.shape and np.array_equal(target, target2)
    sl = (np.arange(theta.shape[0]) // 997) % 5 == 2
    assert np.array_equal(matrix.rows(sl), theta[sl]) and matrix.rows(sl).flags["C_CONTIGUOUS"]
    idx = np.array([0, 4, 17, theta.shape[1] - 1])
    cols = matrix.columns(idx)
    assert np.array_equal(cols, theta[:, idx]) and cols.strides == theta[:, idx].strides
    assert np.array_equal(column_sum_squares(matrix, rows=4096), np.sum(theta * theta, axis=0))
    groups, core = lib.groups()
    whole = GroupedSparseSelector(groups, core).fit(theta, target)
    built = GroupedSparseSelector(groups, core).fit(matrix, target)
    assert np.array_equal(whole.coef, built.coef) and np.array_equal(whole.stderr, built.stderr)
    assert np.array_equal(whole.cv_error, built.cv_error) and whole.threshold == built.threshold

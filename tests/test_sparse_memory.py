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

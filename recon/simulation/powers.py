"""Whole powers inside the numba kernels.

``ipow(x, k)`` is x**k for a whole k >= 0 by repeated squaring: the same products, in the same order,
as numba's own ``x ** k`` for an integer k, so the results are identical to the bit; but numba's
operator, reached with an exponent read from an array, is not inlined and cost 2-20x the whole RK4
step of the hysteretic model (one to three fn terms). Every kernel that evaluates y^p y'^r uses this.
"""
from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True, inline="always")
def ipow(x, k):
    out = 1.0
    b = x
    while k:
        if k & 1:
            out *= b
        k >>= 1
        if k:
            b *= b
    return out

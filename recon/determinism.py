"""Same input, same answer: the estimators run with single-threaded BLAS.

Multi-threaded BLAS splits sums across threads, so the last bits of a product can depend on the
thread count; an output-error fit then amplifies them into different iterations and, in a
diagnosis, a different ranking. Every estimator entry point (reconstruct, parameter_intervals,
diagnose) runs inside :func:`single_thread_blas`, so its result does not depend on the BLAS
thread count, the machine's load or how many workers a batch uses. The fits' Jacobians are tall
and thin, so one thread is also the fastest on shared cores (40x faster SVDs measured on 2 cores).
"""
from __future__ import annotations

import functools

from threadpoolctl import threadpool_limits


def single_thread_blas(func):
    """Decorator: run ``func`` with BLAS (and OpenMP BLAS back ends) limited to one thread."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with threadpool_limits(1, user_api="blas"):
            return func(*args, **kwargs)

    return wrapper

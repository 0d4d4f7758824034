"""A thread pool for the finite-difference Jacobians of the output-error fits.

An output-error fit (scipy ``least_squares``) whose Jacobian is not taken from forward sensitivities
(an exciter law, an acceleration record, the diagnosis's held-out starts) takes finite differences:
one simulation of the record per free parameter per iteration. The columns are independent, and the
simulation kernels (``recon.simulation.rk4``) are compiled without the GIL, so they run side by side
on threads. A Jacobian from sensitivities does not use the pool (one pass per stage, a few
milliseconds: side by side they cost more CPU than they saved wall time, docs/architecture.md).
The results are the same to the bit as serial ones: the same points are evaluated, only at the
same time (scipy's ``workers`` map, 1.16 on).

``SHAKERLAB_THREADS`` sets the number of threads (1: serial); the default is the number of cores,
at most MAX_THREADS. A process forked after the pool was made (Dask, multiprocessing) makes its own.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

MAX_THREADS = 8
POOL_PREFIX = "shakerlab-fd"

_pool: ThreadPoolExecutor | None = None
_pool_pid: int | None = None
_pool_size = 0


def thread_count() -> int:
    """Threads for the finite differences: ``SHAKERLAB_THREADS`` or the cores (at most MAX_THREADS)."""
    env = os.environ.get("SHAKERLAB_THREADS", "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            raise ValueError(f"SHAKERLAB_THREADS must be a whole number of threads, got {env!r}") from None
        if n < 1:
            raise ValueError(f"SHAKERLAB_THREADS must be at least 1, got {n}")
        return n
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:      # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_THREADS))


def fd_map():
    """The ``workers`` map for ``least_squares``: a thread pool's ordered map, or the built-in
    ``map`` (serial) with one thread. The threads keep the caller's floating-point error handling
    (``np.errstate`` is per thread): a fit run under ``errstate(all="ignore")`` stays quiet."""
    global _pool, _pool_pid, _pool_size
    n = thread_count()
    if n == 1 or threading.current_thread().name.startswith(POOL_PREFIX):
        return map      # serial; and never a pool's task waiting on tasks queued behind it in the same pool
    if _pool is None or _pool_pid != os.getpid() or _pool_size != n:
        _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix=POOL_PREFIX)
        _pool_pid = os.getpid()
        _pool_size = n
    pool = _pool

    def ordered_map(fun, items):
        err = np.geterr()

        def call(x):
            with np.errstate(**err):
                return fun(x)

        return pool.map(call, items)

    return ordered_map

"""Time of the simulation kernels, with and without forward sensitivities (one core).

Run:  .venv/bin/python bench/kernel_speed.py [--samples 15000] [--repeat 7]

The output-error fits spend most of their time in these kernels (recon.simulation.rk4 and
recon.simulation.sensitivity): a Jacobian from sensitivities is one pass of a sensitivity kernel,
a fit's residual one simulation. The table gives each kernel's best time over ``--repeat`` calls
(numba compilation excluded) on a 1 kHz record with a cubic, a y^2 y' and a y'^3 term and a
Bouc-Wen law, and its ratio to the plain simulation's. A column costs a few multiply-adds per step:
a sensitivity kernel's time beyond the simulation's should come from its columns, not from the
stage it shares with the simulation (docs/architecture.md, "features as values").
"""
from __future__ import annotations

import argparse
import os
import sys
import time

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from recon.simulation.rk4 import kernel_input, kernel_parameters, simulate_extended, simulate_plain  # noqa: E402
from recon.simulation.sensitivity import (column_codes, extended_column_codes,  # noqa: E402
                                          simulate_extended_sensitivities, simulate_plain_sensitivities)


def best_ms(fun, repeat: int) -> float:
    fun()       # compile (or load from the cache)
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fun()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=15000)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args(argv)
    n, dt = args.samples, 1e-3
    t = np.arange(n) * dt
    u = kernel_input(2.0 * np.sin(2 * np.pi * 8.0 * t) + 0.01 * np.random.default_rng(0).standard_normal(n))
    k = (2 * np.pi * 8.0) ** 2
    g, c, alpha, gamma, delta = 1.0, 1.0, 100.0, 1000.0, 500.0
    coef = np.array([1e5, 1e3, 10.0])
    p = np.array([3, 2, 0], np.int64)
    r = np.array([0, 1, 3], np.int64)
    P = kernel_parameters(g=g, c=c, k=k, alpha=alpha, gamma=gamma, delta=delta, mu=0.05, v0=0.01)

    rows = []
    plain = best_ms(lambda: simulate_plain(u, dt, 1, g, c, k, alpha, gamma, delta, coef, p, r, 0.0, 0.0, 0.0),
                    args.repeat)
    rows.append(("plain", "simulation", 0, plain))
    for names in (["c"], ["c", "k", "alpha"], ["c", "k", "alpha", "gamma", "delta", 0, 1, 2]):
        fi, eq = column_codes(names)
        S0 = np.zeros((3, len(names)))
        rows.append(("plain", "sensitivities", len(names), best_ms(
            lambda: simulate_plain_sensitivities(u, dt, 1, g, c, k, alpha, gamma, delta, coef, p, r, 0.0, 0.0, 0.0,
                                                 fi, eq, S0, 0), args.repeat)))
    ext = best_ms(lambda: simulate_extended(u, 0.0, dt, 1, P, coef, p, r, 0.0, 0.0, 0.0), args.repeat)
    rows.append(("extended (friction on)", "simulation", 0, ext))
    for names in (["mu"], ["mu", "c", "k"], ["mu", "v0", "c", "k", "alpha", "gamma", "delta", 0]):
        codes = extended_column_codes(names)
        S0 = np.zeros((5, len(names)))
        rows.append(("extended (friction on)", "sensitivities", len(names), best_ms(
            lambda: simulate_extended_sensitivities(u, 0.0, dt, 1, P, coef, p, r, 0.0, 0.0, 0.0, codes, S0, 0, False),
            args.repeat)))

    print(f"{n} samples at 1 kHz, one sub-step, best of {args.repeat}")
    print(f"{'model':24s} {'kernel':14s} {'columns':>7s} {'ms':>8s} {'x simulation':>13s}")
    for model, kernel, m, ms in rows:
        base = plain if model == "plain" else ext
        print(f"{model:24s} {kernel:14s} {m:7d} {ms:8.3f} {ms / base:13.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

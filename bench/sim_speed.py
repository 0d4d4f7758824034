"""Real-time factor of the simulated rig's integrator (one core).

    python bench/sim_speed.py [--seconds 60]

Prints simulated seconds per wall-clock second at the configured sample rate
(10 kHz by default) for the kernel alone and for the world (ring buffer and
chunking included), with the default specimen and with every optional effect
on.  The target is >= 200x real time.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from sim_backend import physics as ph  # noqa: E402
from sim_backend.world import World  # noqa: E402

ALL_EFFECTS = {"effects": {"coulomb_friction": 0.2, "quadratic_damping": 5.0, "contact_gap": 2e-3,
                           "contact_stiffness": 1e5, "channel_delay": 1e-4, "tip_scale_error": 0.01,
                           "base_scale_error": -0.01, "stiffness_drift": 1e-4,
                           "higher_mode_frequency": 120.0}}


def drive(w: World) -> None:
    w.G[ph.G_OUT], w.G[ph.G_VPP], w.G[ph.G_FREQ] = 1.0, 0.5, 14.0
    w.A[ph.A_ENABLE], w.A[ph.A_GAIN] = 1.0, 1.0


def kernel_rtf(config, seconds: float) -> float:
    w = World(config, speed=None)
    drive(w)
    n = int(seconds * w.sample_rate)
    xb, xt = np.empty(n), np.empty(n)
    ph.advance(w.P, w.X, w.G, w.A, 0, 1000, xb, xt)  # warm
    t0 = time.perf_counter()
    ph.advance(w.P, w.X, w.G, w.A, 1000, n, xb, xt)
    return seconds / (time.perf_counter() - t0)


def world_rtf(config, seconds: float, chunk_s: float) -> float:
    w = World(config, speed=None)
    drive(w)
    chunk = max(1, int(chunk_s * w.sample_rate))
    total = int(seconds * w.sample_rate)
    t0 = time.perf_counter()
    done = 0
    while done < total:
        w.advance(chunk)
        done += chunk
    return done / w.sample_rate / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per measurement")
    args = ap.parse_args()
    rows = []
    for label, cfg in (("default specimen", None), ("all effects on", ALL_EFFECTS)):
        rows.append((label, "kernel, one call", kernel_rtf(cfg, args.seconds)))
        rows.append((label, "world, 10 ms chunks", world_rtf(cfg, args.seconds / 4, 0.01)))
        rows.append((label, "world, 100 ms chunks", world_rtf(cfg, args.seconds, 0.1)))
    print(f"simulator real-time factor at 10 kHz, one core ({args.seconds:g} s simulated), target >= 200x")
    print(f"{'config':18s} {'mode':22s} {'x real time':>12s}")
    for label, mode, rtf in rows:
        print(f"{label:18s} {mode:22s} {rtf:12.0f}")


if __name__ == "__main__":
    main()

"""Sustained acquisition: 2 channels x 10 kHz through the whole controller path.

The simulated rig runs in a separate process (so the CPU figure is the
controller's own: drivers, alignment, supervision, HDF5 recording, heartbeat)
on its real-time clock, optionally faster than real time to stress the path.
The controller runs one long stage (a sine at a moderate level) through the
same Runner, Supervisor and Recorder as ``shakerlab acquire`` and records it.

Reported per mode: simulated time, wall time, samples per channel, samples
lost (gaps in the sample index seen by the runner, sensor buffer-overflow
alarms, and gaps in the recorded file; must be 0), resident memory at the
start and the end and its growth, the controller's CPU use (percent of one
core) and the file size.

    python bench/acquisition.py                    # 10 min simulated at 4x real time (2.5 min)
    python bench/acquisition.py --minutes 10 --speed 1     # 10 min in real time
    python bench/acquisition.py --minutes 1 --speed 2      # quick look
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def _serve(speed, conn):
    from sim_backend.rig import SimulatedRig

    rig = SimulatedRig(None, speed=speed, seed=1)
    rig.start()
    conn.send(rig.addresses)
    conn.recv()  # until told to stop
    rig.stop()


def _rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


class Meter:
    """Observer: samples RSS once per simulated 10 s after a warm-up, counts blocks."""

    def __init__(self):
        self.blocks = 0
        self.rss = []
        self.next_t = 10.0

    def on_block(self, block):
        self.blocks += 1
        if block.run_time >= self.next_t:
            self.next_t += 10.0
            self.rss.append((block.run_time, _rss_mb()))


def endurance_plan(minutes: float, hz: float, vpp: float):
    from rig.messages import Acquire, BeginStage, EndStage, Ramp, SetFrequency

    yield BeginStage("endurance", {"kind": "harmonic", "frequency_hz": hz, "amplitude_vpp": vpp})
    yield SetFrequency(hz)
    yield Ramp(vpp)
    left = minutes * 60.0
    while left > 0:
        yield Acquire(min(10.0, left))  # windows are returned and dropped: memory must stay flat
        left -= 10.0
    yield EndStage({})


def run_mode(minutes: float, speed: float | None, path: Path) -> dict:
    from rig.config import load_config
    from rig.instruments import RigInstruments
    from rig.recorder import Recorder
    from rig.runner import Runner
    from rig.safety import Supervisor

    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_serve, args=(speed, child), daemon=True)
    proc.start()
    try:
        addresses = parent.recv()
        config = load_config(None).with_addresses(addresses)
        inst = RigInstruments(config, lockstep=speed is None)
        inst.connect()
        meter = Meter()
        rec = Recorder(path, overwrite=True, fs=inst.fs, flush_interval=config.acquisition["flush_interval_s"])
        runner = Runner(inst, Supervisor(config.limits), observers=[rec, meter])
        rss0 = _rss_mb()
        cpu0 = os.times()
        t0 = time.monotonic()
        outcome = runner.run(endurance_plan(minutes, 12.0, 0.3), {"attrs": {"bench": "acquisition"}})
        wall = time.monotonic() - t0
        cpu1 = os.times()
        overflow = [inst.base.check_errors(), inst.tip.check_errors()] if outcome.status == "complete" else []
        inst.close()
    finally:
        parent.send("stop")
        proc.join(timeout=10)
    import h5py

    rss_end = _rss_mb()
    file_gaps, prev = 0, None
    with h5py.File(path, "r") as f:  # read in chunks: the check must not inflate the memory figure
        ds = f["entry/stages/endurance/sample_index"]
        for i in range(0, ds.shape[0], 1 << 20):
            idx = ds[i:i + (1 << 20)]
            if prev is not None:
                file_gaps += int(idx[0] - prev - 1)
            file_gaps += int(np.sum(np.diff(idx) - 1))
            prev = idx[-1]
    cpu = (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system)
    warm = [r for t, r in meter.rss if t >= 30.0] or [r for _, r in meter.rss]
    return {
        "mode": "lockstep (max)" if speed is None else f"real time x{speed:g}",
        "status": outcome.status + (f" ({outcome.reason})" if outcome.reason else ""),
        "sim_s": outcome.run_time_s, "wall_s": wall, "samples": outcome.n_samples,
        "lost": outcome.samples_lost + file_gaps + sum("buffer overflow" in e for o in overflow for e in o),
        "rss0": rss0, "rss_warm": warm[0] if warm else float("nan"), "rss_end": rss_end,
        "cpu_pct": 100.0 * cpu / wall, "file_mb": path.stat().st_size / 1e6,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="simulated minutes per mode (default 10)")
    ap.add_argument("--speed", type=float, default=4.0,
                    help="simulated time per wall time for the real-time mode (default 4)")
    ap.add_argument("--no-lockstep", action="store_true", help="skip the as-fast-as-possible mode")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        modes = [args.speed] + ([] if args.no_lockstep else [None])
        for speed in modes:
            rows.append(run_mode(args.minutes, speed, Path(tmp) / "bench.h5"))
    print(f"\nsustained acquisition, 2 channels x 10 kHz, {args.minutes:g} min simulated per mode "
          f"(controller and simulator in separate processes)\n")
    head = (f"{'mode':<16} {'status':<10} {'sim s':>7} {'wall s':>7} {'samples/ch':>11} {'lost':>5} "
            f"{'RSS start':>9} {'RSS @30s':>9} {'RSS end':>8} {'growth':>7} {'CPU %':>6} {'file MB':>8}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['mode']:<16} {r['status']:<10} {r['sim_s']:7.1f} {r['wall_s']:7.1f} {r['samples']:11d} "
              f"{r['lost']:5d} {r['rss0']:8.1f}M {r['rss_warm']:8.1f}M {r['rss_end']:7.1f}M "
              f"{r['rss_end'] - r['rss_warm']:+6.1f}M {r['cpu_pct']:6.1f} {r['file_mb']:8.1f}")
    print("\nRSS growth is measured from 30 s of simulated time (after imports, numba and HDF5 warm-up) "
          "to the end. CPU % is the controller process only (100 % = one core).")


if __name__ == "__main__":
    main()

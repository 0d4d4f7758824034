"""Round-trip latency and sustained sample throughput of each driver against the simulated rig.

    python bench/driver_throughput.py [--n 300] [--seconds 20]

Latency: median and 95th percentile of a short query per driver over loopback
TCP (and over a pty for the line instruments).  Throughput: samples per second
through LaserSensor.fetch in lockstep mode (the simulator runs as fast as the
fetches pull), for one sensor and for both sensors alternately, and the
real-time check: at speed 1.0 can both sensors keep up with 10 kHz?
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from drivers.laser_sensor import LaserSensor  # noqa: E402
from drivers.power_amplifier import PowerAmplifier  # noqa: E402
from drivers.signal_generator import SignalGenerator  # noqa: E402
from sim_backend.rig import SimulatedRig  # noqa: E402


def latency(func, n: int) -> tuple[float, float]:
    func()
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        func()
        times.append(time.perf_counter() - t0)
    times.sort()
    return statistics.median(times) * 1e3, times[int(0.95 * (len(times) - 1))] * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=300, help="round trips per latency figure")
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per throughput figure")
    args = ap.parse_args()

    print(f"round-trip latency over loopback ({args.n} queries)")
    print(f"{'driver':18s} {'call':34s} {'transport':10s} {'median ms':>10s} {'p95 ms':>8s}")
    with SimulatedRig(speed=None, pty=True) as rig:
        a, p = rig.addresses, rig.pty_paths
        gen = SignalGenerator(a["generator"])
        gen_pty = SignalGenerator(p["generator"])
        amp = PowerAmplifier(a["amplifier"])
        tip = LaserSensor(a["sensor_tip"])
        tip_pty = LaserSensor(p["sensor_tip"])
        rows = [
            ("SignalGenerator", "frequency (FREQ?)", "tcp", lambda: gen.frequency),
            ("SignalGenerator", "frequency = (FREQ x;:SYST:ERR?)", "tcp", lambda: setattr(gen, "frequency", 14.0)),
            ("SignalGenerator", "frequency (FREQ?)", "pty", lambda: gen_pty.frequency),
            ("PowerAmplifier", "output_current (1 register)", "modbus", lambda: amp.output_current),
            ("PowerAmplifier", "heartbeat (write register)", "modbus", amp.heartbeat),
            ("LaserSensor", "read (M0)", "tcp", tip.read),
            ("LaserSensor", "read (M0)", "pty", tip_pty.read),
        ]
        for drv, call, tr, func in rows:
            med, p95 = latency(func, args.n)
            print(f"{drv:18s} {call:34s} {tr:10s} {med:10.3f} {p95:8.3f}")
        for d in (gen, gen_pty, amp, tip, tip_pty):
            d.close()

    print()
    print(f"sustained sample throughput, lockstep ({args.seconds:g} simulated s at 10 kHz per figure)")
    print(f"{'sensors':22s} {'block':>8s} {'transport':10s} {'samples/s':>12s} {'x 10 kHz':>9s}")
    for block in (1000, 10000):
        for transport in ("tcp", "pty"):
            for both in (False, True):
                with SimulatedRig(speed=None, pty=transport == "pty") as rig:
                    a = rig.addresses if transport == "tcp" else rig.pty_paths
                    g = SignalGenerator(rig.addresses["generator"])
                    amp = PowerAmplifier(rig.addresses["amplifier"])
                    g.frequency, g.amplitude, g.output = 14.0, 0.5, True
                    amp.gain, amp.enabled = 1.0, True
                    sensors = [LaserSensor(a["sensor_base"])] + ([LaserSensor(a["sensor_tip"])] if both else [])
                    for s in sensors:
                        s.arm(None)
                    g.trigger()
                    total = int(args.seconds * 10000)
                    got = 0
                    t0 = time.perf_counter()
                    while got < total:
                        for s in sensors:
                            got += len(s.fetch(block))
                    rate = got / (time.perf_counter() - t0)
                    label = "base + tip" if both else "base only"
                    print(f"{label:22s} {block:8d} {transport:10s} {rate:12.0f} {rate / 10000 / len(sensors):9.1f}")
                    for d in (g, amp, *sensors):
                        d.close()

    print()
    print("real time (speed 1.0): both sensors fetched every 50 ms for 5 s")
    with SimulatedRig(speed=1.0) as rig:
        a = rig.addresses
        base, tip = LaserSensor(a["sensor_base"]), LaserSensor(a["sensor_tip"])
        g = SignalGenerator(a["generator"])
        base.arm(None)
        tip.arm(None)
        g.trigger()
        n_b = n_t = 0
        t0 = time.monotonic()
        while time.monotonic() - t0 < 5.0:
            time.sleep(0.05)
            n_b += len(base.fetch())
            n_t += len(tip.fetch())
        wall = time.monotonic() - t0
        print(f"{'acquired base/tip':22s} {n_b:d}/{n_t:d} samples in {wall:.2f} s "
              f"= {n_b / wall:.0f}/{n_t / wall:.0f} samples/s (target 10000)")
        for d in (base, tip, g):
            d.close()


if __name__ == "__main__":
    main()

"""Operator window: frame rate, redraw cost, event-loop stalls and CPU while acquiring 2 x 10 kHz.

The simulated rig runs in a separate process on its real-time clock (optionally faster, to push more
samples per second through the window); the window (offscreen) connects to it as to real instruments
and runs a long linear stage through the same runner, supervisor and recorder as ``shakerlab acquire``,
with the live plots redrawing from the ring buffers at the window's FPS.

Reported per mode: frames (timer redraws) per second, paint events of the plot area per second,
redraw time (mean, 95th percentile, max), the longest event-loop stall (a 10 ms timer's worst
lateness), CPU of the GUI thread and of the whole process (GUI + runner + drivers + HDF5 recorder)
in percent of one core, samples lost.

    QT_QPA_PLATFORM=offscreen python bench/gui_fps.py                  # 20 s at 1x and 10 s at 4x
    QT_QPA_PLATFORM=offscreen python bench/gui_fps.py --seconds 60 --speeds 1
    QT_QPA_PLATFORM=offscreen python bench/gui_fps.py --speeds 1 --sim-in-process   # both placements
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _serve(speed, conn):
    from sim_backend.rig import SimulatedRig

    rig = SimulatedRig(None, speed=speed, seed=1)
    rig.start()
    conn.send(rig.addresses)
    conn.recv()
    rig.stop()


PROTOCOL = """
[run]
settle_s = 0.2
[linear]
frequency_hz = 14.0
amplitude_vpp = 0.4
duration_s = {duration}
[resonance_search]
enabled = false
[nonlinear]
frequency_hz = 14.0
start_vpp = 0.1
step_factor = 2.0
max_vpp = 0.2
dwell_s = 0.5
analysis_s = 0.25
hold_s = 0.0
"""


def _rig_toml(addresses: dict, path: Path) -> Path:
    from rig.config import DEFAULT_RIG_PATH

    text = DEFAULT_RIG_PATH.read_text()
    sections = {"generator": addresses["generator"], "amplifier": addresses["amplifier"],
                "sensors.base": addresses["sensor_base"], "sensors.tip": addresses["sensor_tip"]}
    for section, address in sections.items():
        key = "address" if section == "amplifier" else "url"
        text = re.sub(rf"(\[{re.escape(section)}\][^\[]*?^{key} = )\"[^\"]*\"", rf'\g<1>"{address}"', text,
                      count=1, flags=re.M | re.S)
    path.write_text(text)
    return path


class _PaintCounter:
    def __init__(self, QtCore):
        class Filter(QtCore.QObject):
            def __init__(self):
                super().__init__()
                self.paints = 0

            def eventFilter(self, obj, event):  # noqa: N802 - Qt name
                if event.type() == QtCore.QEvent.Paint:
                    self.paints += 1
                return False

        self.filter = Filter()


def run_mode(app, speed: float, seconds: float, workdir: Path, in_process: bool = False) -> dict:
    from PySide6 import QtCore

    from rig.gui.window import MainWindow

    parent, child = mp.Pipe()
    proc = None
    if not in_process:
        proc = mp.get_context("spawn").Process(target=_serve, args=(speed, child), daemon=True)
        proc.start()
        addresses = parent.recv()
    try:
        if in_process:  # the window's own simulated rig (threads in this process), as `shakerlab gui`
            w = MainWindow(simulated=True, speed=speed, seed=1, output_dir=workdir, auto_reconstruct=False)
        else:
            cfg = _rig_toml(addresses, workdir / f"rig-{speed:g}.toml")
            w = MainWindow(config_path=cfg, simulated=False, output_dir=workdir, auto_reconstruct=False)
        w.resize(1400, 900)
        w.show()
        # the linear stage lasts longer (in rig time) than the measurement
        w.set_protocol_text(PROTOCOL.format(duration=seconds * speed + 10), "bench protocol")
        counter = _PaintCounter(QtCore)
        w.plots.viewport().installEventFilter(counter.filter)
        lateness = []
        probe = {"due": None}

        def tick():
            now = time.perf_counter()
            if probe["due"] is not None:
                lateness.append(now - probe["due"])
            probe["due"] = now + 0.010

        ticker = QtCore.QTimer()
        ticker.setInterval(10)
        ticker.setTimerType(QtCore.Qt.PreciseTimer)
        ticker.timeout.connect(tick)

        def spin(cond, limit):
            t_end = time.monotonic() + limit
            while not cond() and time.monotonic() < t_end:
                app.processEvents(QtCore.QEventLoop.AllEvents, 5)
                time.sleep(0.001)

        if not w.start_run():
            raise SystemExit(f"run did not start: {w.last_error}")
        # measure once the linear stage is at its level (1 s of rig time after the ramp)
        spin(lambda: w.live.stage == "linear" and w.live.drive.amplitude_vpp >= 0.4, 30)
        spin(lambda: False, 1.0)
        f0, p0 = w.frames, counter.filter.paints
        w.redraw_times.clear()
        ticker.start()
        t0, c0, g0 = time.perf_counter(), time.process_time(), time.thread_time()
        s0 = w.live.drive.run_time
        spin(lambda: False, seconds)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        gui_cpu = time.thread_time() - g0
        samples = (w.live.drive.run_time - s0) * w.live.fs
        ticker.stop()
        frames, paints = w.frames - f0, counter.filter.paints - p0
        redraw = np.array(w.redraw_times) * 1e3
        w.abort()
        spin(lambda: w.last_outcome is not None, 30)
        out = w.last_outcome
        w.close()
        app.processEvents()
        return {
            "sim": "in process" if in_process else "own process",
            "throttled": w.throttled_ticks,
            "speed": speed, "seconds": wall, "rate": samples / wall,
            "fps": frames / wall, "paints": paints / wall,
            "redraw_mean": float(redraw.mean()) if redraw.size else float("nan"),
            "redraw_p95": float(np.percentile(redraw, 95)) if redraw.size else float("nan"),
            "redraw_max": float(redraw.max()) if redraw.size else float("nan"),
            "stall_max": 1e3 * max(lateness) if lateness else float("nan"),
            "gui_cpu": 100 * gui_cpu / wall, "cpu": 100 * cpu / wall,
            "lost": out.samples_lost if out is not None else -1,
            "status": out.status if out is not None else "?",
        }
    finally:
        if proc is not None:
            parent.send("stop")
            proc.join(10)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="operator window frame rate and CPU while acquiring")
    ap.add_argument("--seconds", type=float, default=20.0, help="measured wall time per mode")
    ap.add_argument("--speeds", type=float, nargs="+", default=[1.0, 4.0],
                    help="simulated time per wall time (1 = 2 x 10 kHz real time)")
    ap.add_argument("--sim-in-process", action="store_true",
                    help="also measure with the simulated rig inside the window's process (as `shakerlab gui`)")
    args = ap.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6 import QtWidgets

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(["bench"])
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for speed in args.speeds:
            secs = args.seconds if speed == 1 else max(5.0, args.seconds / 2)
            rows.append(run_mode(app, speed, secs, Path(d)))
            if args.sim_in_process:
                rows.append(run_mode(app, speed, secs, Path(d), in_process=True))
    print(f"\noperator window (offscreen, {os.cpu_count()} cores, target {1000 // 40} fps = 40 ms timer)")
    head = ("simulator", "speed", "samples/s/ch", "wall s", "frames/s", "paints/s", "redraw ms mean/p95/max",
            "max stall ms", "GUI thread CPU %", "process CPU %", "throttled ticks", "lost", "run")
    print(" | ".join(head))
    print(" | ".join("---" for _ in head))
    for r in rows:
        print(f"{r['sim']} | {r['speed']:g}x | {r['rate']:.0f} | {r['seconds']:.1f} | {r['fps']:.1f} | {r['paints']:.1f} | "
              f"{r['redraw_mean']:.1f} / {r['redraw_p95']:.1f} / {r['redraw_max']:.1f} | {r['stall_max']:.0f} | "
              f"{r['gui_cpu']:.0f} | {r['cpu']:.0f} | {r['throttled']} | {r['lost']} | {r['status']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Console display of a run: progress lines, the final summary, Ctrl-C as abort."""
from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time

from shakerlab.runfile.reader import read_info


class ConsoleProgress:
    """A runner observer that prints events and, every few seconds, where the run is."""

    def __init__(self, quiet: bool = False, every_s: float = 5.0, stream=None):
        self.quiet = quiet
        self.every_s = every_s
        self.stream = stream or sys.stdout
        self._last = time.monotonic()
        self.stage = None

    def _print(self, text: str) -> None:
        print(text, file=self.stream, flush=True)

    def on_event(self, level: str, message: str, run_time: float) -> None:
        if self.quiet and level in ("debug", "info"):
            return
        if level == "debug":
            return
        tag = "" if level == "info" else f"{level.upper()}: "
        self._print(f"[{run_time:8.2f} s] {tag}{message}")

    def on_block(self, block) -> None:
        now = time.monotonic()
        if self.quiet or now - self._last < self.every_s:
            return
        self._last = now
        y = block.x_tip - block.x_base
        amp = 0.5 * float(y.max() - y.min()) if y.size else 0.0
        self._print(f"[{block.run_time:8.2f} s]   {block.stage or 'rest'}: {block.amplitude_vpp:.3f} Vpp at "
                    f"{block.frequency_hz:.3f} Hz, relative motion +-{amp * 1e3:.3f} mm")


def print_summary(outcome, stream=None) -> None:
    out = stream or sys.stdout
    p = lambda s="": print(s, file=out)  # noqa: E731
    p()
    p(f"run {outcome.status}" + (f": {outcome.reason}" if outcome.reason else ""))
    p(f"  file          {outcome.path}")
    if getattr(outcome, "file_note", ""):
        p(f"                {outcome.file_note}")
    p(f"  acquired      {outcome.n_samples} samples per channel, {outcome.run_time_s:.1f} s of rig time "
      f"in {outcome.wall_time_s:.1f} s wall time; samples lost: {outcome.samples_lost}")
    pk = outcome.peaks
    p(f"  peaks         base {pk.get('x_base', 0) * 1e3:.3f} mm, tip {pk.get('x_tip', 0) * 1e3:.3f} mm, "
      f"amplifier current {pk.get('current', 0):.3f} A")
    if outcome.path is None:
        return
    try:
        info = read_info(outcome.path)
    except Exception as exc:  # noqa: BLE001 - the summary must not hide the run's own result
        p(f"  (cannot read the run file back: {exc})")
        return
    for name, st in info["stages"].items():
        s = st["summary"]
        extra = ""
        if "resonance_hz" in s:
            extra = f"resonance {s['resonance_hz']:.3f} Hz"
        elif "final_vpp" in s:
            extra = f"final level {s['final_vpp']:.3f} Vpp at {s['drive_frequency_hz']:.3f} Hz: {s['stop_reason']}"
        elif "response" in s:
            r = s["response"]
            extra = f"relative amplitude {r['relative_amplitude'] * 1e3:.3f} mm at {r['frequency_hz']:.3f} Hz"
        p(f"  {name:<17s} {st['status']:<11s} {st['n_samples'] / max(st['fs'], 1):7.2f} s  {extra}")


@contextlib.contextmanager
def sigint_aborts():
    """While active, Ctrl-C (and SIGTERM) call runner.abort() (a second one cuts) instead of raising.

    Yields the hook to pass as ``acquire(on_runner=...)``.
    """
    holder = {}

    def hook(runner):
        holder["runner"] = runner

    def handler(signum, frame):
        runner = holder.get("runner")
        if runner is None:
            raise KeyboardInterrupt
        name = "Ctrl-C" if signum == signal.SIGINT else "SIGTERM"
        first = runner._abort_count == 0
        runner.abort(name)
        print(f"\n{name}: ramping the output down ({name} again cuts at once)" if first
              else f"\n{name} again: cutting the output", file=sys.stderr, flush=True)

    if threading.current_thread() is not threading.main_thread():
        yield hook
        return
    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield hook
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)

"""What the GUI shows live, gathered off the GUI thread (no Qt in this module).

:class:`LiveData` is a runner observer (see :mod:`rig.runner`). The runner
calls it from its acquisition thread; it hands every block to a
:class:`rig.live.LiveBuffer` (the ring buffer of the newest samples) and
keeps the latest drive and instrument state. The GUI's redraw timer reads
snapshots (a short lock around a copy), never the run file.

It also derives two things the plots need:

- the *linear step* (:func:`linear_step`): when the ``linear`` stage ends,
  the stiffness and damping per unit mass ``K_m`` and ``c_m`` from the
  fundamental harmonic of the full-amplitude window (the restoring force per
  unit mass is ``r = -x_tip''``, and for a linear specimen
  ``r = c_m y' + K_m y``, so ``K_m + i w c_m = w^2 X_tip / Y``);
- the *live loop* (:func:`nonlinear_loop`): over the last whole periods at
  the drive frequency, the harmonics of ``x_tip`` and ``y`` give one periodic
  cycle of ``y`` and of the nonlinear restoring force
  ``Fn = r - c_m y' - K_m y``, i.e. what is left when the linear step is
  taken away (hysteresis and the nonlinear spring).
- the response amplitude per stage: ``(max(y) - min(y)) / 2`` over the last
  ``max(1.5 drive periods, 0.2 s)`` of the stage's own samples (a window never reaches back
  before the stage began), every 0.1 s of rig time. It is the motion as recorded, transients
  included (a ramp's steps set the specimen ringing at its natural frequency).
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from rig.analysis import harmonics
from rig.live import LiveBuffer


@dataclass
class LinearStep:
    """Linear stiffness and damping per unit mass from the linear stage's fundamental."""

    K_m: float
    c_m: float
    frequency_hz: float
    relative_amplitude: float
    n_samples: int

    def text(self) -> str:
        return (f"K_m = {self.K_m:.4g} 1/s^2, c_m = {self.c_m:.4g} 1/s "
                f"(fn = {math.sqrt(max(self.K_m, 0.0)) / (2 * math.pi):.3f} Hz)")


def linear_step(x_base: np.ndarray, x_tip: np.ndarray, fs: float, f: float) -> LinearStep:
    """``K_m`` and ``c_m`` from a steady-state window at drive frequency ``f`` (whole periods used)."""
    if x_base.size < fs / f:
        raise ValueError(f"linear step: {x_base.size} samples hold less than one period at {f:g} Hz")
    hb = harmonics(x_base, fs, f, 1)[0]
    ht = harmonics(x_tip, fs, f, 1)[0]
    y1 = ht - hb
    w = 2 * math.pi * f
    h = w * w * ht / y1          # K_m + i w c_m
    return LinearStep(K_m=float(h.real), c_m=float(h.imag / w), frequency_hz=float(f),
                      relative_amplitude=float(abs(y1)), n_samples=int(x_base.size))


def nonlinear_loop(x_base: np.ndarray, x_tip: np.ndarray, fs: float, f: float, step: LinearStep,
                   n_harmonics: int = 5, n_points: int = 200):
    """One periodic cycle (y, Fn) from the harmonics of the window; ``Fn = -x_tip'' - c_m y' - K_m y``."""
    ht = harmonics(x_tip, fs, f, n_harmonics)
    hy = ht - harmonics(x_base, fs, f, n_harmonics)
    w = 2 * math.pi * f
    k = np.arange(1, n_harmonics + 1)[:, None]
    phi = np.linspace(0.0, 2 * math.pi, n_points + 1)
    e = np.exp(1j * k * phi[None, :])
    y = np.real(hy[:, None] * e).sum(axis=0)
    dy = np.real(1j * k * w * hy[:, None] * e).sum(axis=0)
    r = np.real(((k * w) ** 2) * ht[:, None] * e).sum(axis=0)
    return y, r - step.c_m * dy - step.K_m * y


@dataclass
class DriveState:
    """The latest block's drive and instrument readings."""

    run_time: float = 0.0
    amplitude_vpp: float = 0.0
    frequency_hz: float = 0.0
    output: bool = False
    current_a: float | None = None
    faults: list = field(default_factory=list)
    stage: str | None = None


class LiveData:
    """Runner observer feeding the GUI: ring buffers, drive state, stage amplitudes, linear step.

    Every method may be called from the runner's thread; readers take
    snapshots. ``seconds`` is the ring's length in rig time.
    """

    AMPLITUDE_EVERY_S = 0.1

    def __init__(self, fs: float = 10000.0, seconds: float = 30.0):
        self.fs = float(fs)
        self.seconds = float(seconds)
        self._lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        with self._lock:
            self.buffer = LiveBuffer(self.seconds, self.fs)
            self.rest = None                      # (x_base, x_tip) mean of the first 0.1 s
            self._rest_acc: list = []
            self.drive = DriveState()
            self.stage = None
            self.stage_start_index = 0
            self.stage_settings: dict = {}
            self.stages_done: list[tuple[str, str]] = []
            self.amplitudes: dict[str, list] = {}   # stage -> [(run time, amplitude)], insertion = run order
            self._next_amp_index = 0
            self._level_index: int | None = None
            self.last_change_index = 0            # sample index of the last amplitude/frequency setpoint
            self.linear: LinearStep | None = None
            self.linear_error = ""
            self.blocks = 0
            self._t0 = None                       # (wall clock, rig time) at the first block
            self.state = "idle"
            self.max_faults: set = set()
            self.control: list[tuple] = []        # closed-loop windows: (run time, target, achieved, error dB)

    # -- observer interface (runner thread) ----------------------------------------------------
    def on_run_start(self, info: dict) -> None:
        fs = info.get("settings", {}).get("sensor_base", {}).get("sampling_rate_hz")
        if fs and float(fs) != self.fs:
            self.fs = float(fs)
            self.buffer = LiveBuffer(self.seconds, self.fs)

    def on_state(self, state: str) -> None:
        self.state = state
        self.buffer.on_state(state)

    def on_event(self, level: str, message: str, run_time: float) -> None:
        self.buffer.on_event(level, message, run_time)

    def on_stage_begin(self, name: str, settings: dict, index: int) -> None:
        with self._lock:
            self.stage, self.stage_start_index, self.stage_settings = name, index, dict(settings)
            self.amplitudes.setdefault(name, [])
            self._level_index = None

    def on_setpoint(self, index: int, vpp: float, hz: float, label: str) -> None:
        self.last_change_index = index
        if self.stage == "linear" and label.startswith("level"):
            self._level_index = index

    def on_stage_end(self, name: str, status: str, summary: dict) -> None:
        with self._lock:
            self.stages_done.append((name, status))
            self.stage = None
        if name == "linear" and status == "complete":
            self._fit_linear()

    def on_block(self, block) -> None:
        xb, xt = block.x_base, block.x_tip
        if self.rest is None:
            self._rest_acc.append((xb, xt))
            n = sum(a.size for a, _ in self._rest_acc)
            if n >= 0.1 * self.fs:
                self.rest = (float(np.mean(np.concatenate([a for a, _ in self._rest_acc]))),
                             float(np.mean(np.concatenate([b for _, b in self._rest_acc]))))
                self._rest_acc = []
        self.buffer.on_block(block)
        if self._t0 is None:
            self._t0 = (time.monotonic(), block.run_time)
        self.blocks += 1
        self.drive = DriveState(run_time=block.run_time, amplitude_vpp=block.amplitude_vpp,
                                frequency_hz=block.frequency_hz, output=block.output, current_a=block.current_a,
                                faults=list(block.amplifier_faults), stage=block.stage)
        if block.amplifier_faults:
            self.max_faults.update(block.amplifier_faults)
        if block.stage is not None and block.end_index >= self._next_amp_index:
            self._next_amp_index = block.end_index + int(self.AMPLITUDE_EVERY_S * self.fs)
            f = block.frequency_hz if block.output and block.frequency_hz > 0 else 0.0
            window = max(1.5 / f if f else 0.0, 0.2)
            # the newest samples (this block's own, and earlier ones of the same stage when the block is
            # shorter than the window), never those before the stage began: a stage's first windows
            # would otherwise hold the previous stage's ramp-down ringing or the rest before it
            n = min(int(round(window * self.fs)), block.end_index - self.stage_start_index)
            _, b, t = self.buffer.latest(n / self.fs)
            y = t - b
            if y.size:
                amp = 0.5 * float(y.max() - y.min())
                with self._lock:
                    self.amplitudes.setdefault(block.stage, []).append((block.run_time, amp))

    def on_control(self, record: dict) -> None:
        """A closed-loop sine-control window (rig.sine_control): target against achieved."""
        with self._lock:
            self.control.append((record["sample_index"] / self.fs, record["effective_target_m"],
                                 record["achieved_m"], record["error_db"]))

    def control_series(self):
        """(run time, effective base target, achieved base amplitude, error dB) arrays, or None."""
        with self._lock:
            if not self.control:
                return None
            a = np.array(self.control, float)
        return a[:, 0], a[:, 1], a[:, 2], a[:, 3]

    # -- derived -----------------------------------------------------------------------------
    def _fit_linear(self) -> None:
        s = self.stage_settings
        f = float(s.get("frequency_hz", 0.0) or 0.0)
        if self._level_index is None or f <= 0:
            self.linear_error = "linear step: the linear stage never reached its level"
            return
        n = int(float(s.get("duration_s", 0.0)) * self.fs)
        t, xb, xt = self.buffer.latest()
        keep = t >= self._level_index / self.fs - 0.5 / self.fs
        xb, xt = xb[keep][:n], xt[keep][:n]
        try:
            self.linear = linear_step(xb, xt, self.fs, f)
            self.linear_error = ""
        except (ValueError, ZeroDivisionError, np.linalg.LinAlgError) as exc:
            self.linear_error = str(exc)

    def lag(self, speed: float) -> float:
        """How far [s of rig time] the newest block is behind a rig running at ``speed`` x real time
        (0 for lockstep, ``speed`` <= 0): grows when the acquisition thread does not keep up."""
        t0 = self._t0
        if t0 is None or speed <= 0:
            return 0.0
        return max(0.0, (time.monotonic() - t0[0]) * speed - (self.drive.run_time - t0[1]))

    def traces(self, seconds: float):
        """(t [s], x_base, x_tip) of the newest ``seconds`` of rig time, relative to the rest readings."""
        t, xb, xt = self.buffer.latest(seconds)
        if self.rest is not None:
            xb = xb - self.rest[0]
            xt = xt - self.rest[1]
        return t, xb, xt

    LOOP_SETTLE_S = 0.5

    def live_loop(self, periods: int = 3):
        """(y, Fn) of the newest whole ``periods`` at the drive frequency, or None: no linear step yet,
        output off, or the window starts less than ``LOOP_SETTLE_S`` after the last setpoint change
        (the harmonic cycle stands for a steady state only)."""
        d, step = self.drive, self.linear
        if step is None or not d.output or d.frequency_hz <= 0:
            return None
        n = int(round(periods * self.fs / d.frequency_hz))
        t, xb, xt = self.buffer.latest(n / self.fs)
        if xb.size < n or t[0] < self.last_change_index / self.fs + self.LOOP_SETTLE_S:
            return None
        return nonlinear_loop(xb, xt, self.fs, d.frequency_hz, step)

    def amplitude_series(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        with self._lock:
            items = [(k, list(v)) for k, v in self.amplitudes.items()]
        out = {}
        for name, pts in items:
            a = np.array(pts, float).reshape(-1, 2)
            out[name] = (a[:, 0], a[:, 1])
        return out

"""In-memory ring buffers of the latest samples, fed by the runner (for live plots).

>>> live = LiveBuffer(seconds=10.0, fs=10000.0)
>>> acquire(config, protocol, "run.h5", observers=[live])     # from a worker thread
>>> t, x_base, x_tip = live.latest(2.0)                        # from the GUI thread, any time

Thread-safe: the runner writes under a lock, readers get copies.
"""
from __future__ import annotations

import threading

import numpy as np


class LiveBuffer:
    """Keeps the last ``seconds`` of both channels plus the run's state, stage and recent events."""

    def __init__(self, seconds: float, fs: float, max_events: int = 200):
        self.fs = float(fs)
        self.capacity = max(1, int(round(seconds * fs)))
        self._data = np.full((3, self.capacity), np.nan)  # index, x_base, x_tip
        self._written = 0           # samples written in total
        self._lock = threading.Lock()
        self.state = "idle"
        self.stage: str | None = None
        self.amplitude_vpp = 0.0
        self.frequency_hz = 0.0
        self.events: list[tuple[str, str, float]] = []
        self.max_events = max_events

    # -- observer side ------------------------------------------------------------------------
    def on_block(self, block) -> None:
        n = block.n
        if n == 0:
            return
        rows = np.vstack([np.arange(block.index0, block.end_index, dtype=float), block.x_base, block.x_tip])
        if n > self.capacity:
            rows = rows[:, -self.capacity:]
            n = self.capacity
        with self._lock:
            pos = self._written % self.capacity
            first = min(n, self.capacity - pos)
            self._data[:, pos:pos + first] = rows[:, :first]
            self._data[:, :n - first] = rows[:, first:]
            self._written += n
            self.amplitude_vpp = block.amplitude_vpp
            self.frequency_hz = block.frequency_hz
            self.stage = block.stage

    def on_state(self, state: str) -> None:
        self.state = state

    def on_event(self, level: str, message: str, run_time: float) -> None:
        with self._lock:
            self.events.append((level, message, run_time))
            del self.events[:-self.max_events]

    # -- reader side ----------------------------------------------------------------------------
    def latest(self, seconds: float | None = None):
        """(t [s since the trigger], x_base, x_tip) of the newest samples, oldest first (copies)."""
        with self._lock:
            n = min(self._written, self.capacity)
            if seconds is not None:
                n = min(n, int(round(seconds * self.fs)))
            end = self._written % self.capacity
            idx = (np.arange(end - n, end)) % self.capacity
            rows = self._data[:, idx].copy()
        return rows[0] / self.fs, rows[1], rows[2]

"""The simulated world: physics state, the shared simulation clock and the sensor history.

One :class:`World` is shared by all simulated instruments of a rig.  It advances
in steps of ``1/sample_rate`` with the numba kernel of :mod:`sim_backend.physics`
and keeps the last ``ring_seconds`` of both laser readings in a ring buffer so
the sensors' buffered acquisition can read any sample since the common trigger.

Clock modes
-----------
``speed`` > 0
    simulated time follows the wall clock times ``speed`` (1.0 = real time); a
    background thread keeps the world caught up, and every instrument command
    first catches up, so a setting takes effect at the simulated time it is
    received.
``speed`` None
    lockstep, as fast as possible: the world advances only when a sensor fetch
    asks for samples beyond the current simulated time.  Deterministic given the
    seed and the sequence of commands.
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from sim_backend import physics as ph
from sim_backend.config import load_config


class World:
    def __init__(self, config=None, speed: float | None = 1.0, seed: int = 0):
        if speed is not None and not (isinstance(speed, (int, float)) and speed > 0):
            raise ValueError(f"speed must be > 0 or None (lockstep), got {speed!r}")
        self.config = cfg = load_config(config)
        self.speed = speed
        self.seed = int(seed)
        self.sample_rate = float(cfg["clock"]["sample_rate"])
        self.dt = 1.0 / self.sample_rate
        self.lock = threading.RLock()
        self.P = ph.parameter_vector(cfg, self.seed)
        self.X = np.zeros(ph.N_X)
        self.X[ph.X_T] = cfg["amplifier"]["ambient_temperature"]
        self.G = np.zeros(ph.N_G)
        self.A = np.zeros(ph.N_A)
        self.A[ph.A_LIMIT] = cfg["amplifier"]["current_limit"]
        self.step = 0
        self.capacity = int(math.ceil(cfg["clock"]["ring_seconds"] * self.sample_rate))
        # rows 0/1: base/tip displacement readings; rows 2/3: base/tip velocity readings (velocity mode)
        self.ring = np.zeros((4, self.capacity))
        self.delay_steps = int(round(cfg["effects"]["channel_delay"] * self.sample_rate))
        self.lockstep_block = max(1, int(round(cfg["clock"]["lockstep_block_s"] * self.sample_rate)))
        self.trigger_step: int | None = None
        self.trigger_steps: list[int] = []
        self.trigger_count = 0
        self._t0_wall: float | None = None
        self._t0_step = 0
        self._thread: threading.Thread | None = None
        self._running = False
        self.generator_alive = True
        self.amplifier_alive = True
        # compile (or load from cache) before any server starts answering
        ph.advance_with_velocity(self.P, self.X.copy(), self.G.copy(), self.A.copy(), 0, 1,
                                 np.empty(1), np.empty(1), np.empty(1), np.empty(1))

    # ---- clock -----------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Current simulated time [s]."""
        return self.step * self.dt

    @property
    def lockstep(self) -> bool:
        return self.speed is None

    def start_clock(self) -> None:
        """Start following the wall clock (no-op in lockstep mode)."""
        if self.lockstep or self._running:
            return
        with self.lock:
            self._t0_wall = time.monotonic()
            self._t0_step = self.step
        self._running = True
        self._thread = threading.Thread(target=self._run, name="sim-clock", daemon=True)
        self._thread.start()

    def stop_clock(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def _run(self) -> None:
        while self._running:
            self.catch_up()
            time.sleep(0.005)

    def target_step(self) -> int:
        """The step the clock says the world should be at now."""
        if self.lockstep or self._t0_wall is None:
            return self.step
        elapsed = (time.monotonic() - self._t0_wall) * self.speed
        return self._t0_step + int(elapsed * self.sample_rate)

    def catch_up(self) -> None:
        """Advance to the wall-clock time (real-time mode); nothing in lockstep."""
        with self.lock:
            target = self.target_step()
            if target > self.step:
                self._advance(target - self.step)

    def advance(self, n_steps: int) -> None:
        """Advance the world explicitly by n steps (tests, lockstep fetches)."""
        with self.lock:
            self._advance(int(n_steps))

    def ensure_step(self, step: int) -> None:
        """Make samples up to (excluding) ``step`` available: advances in lockstep mode,
        only catches up with the clock in real-time mode."""
        with self.lock:
            if self.lockstep:
                if step > self.step:
                    self._advance(step - self.step)
            else:
                self.catch_up()

    def _advance(self, n: int) -> None:
        while n > 0:
            pos = self.step % self.capacity
            chunk = min(n, self.capacity - pos, 1 << 16)
            ring = self.ring[:, pos:pos + chunk]
            ph.advance_with_velocity(self.P, self.X, self.G, self.A, self.step, chunk,
                                     ring[0], ring[1], ring[2], ring[3])
            self.step += chunk
            n -= chunk

    # ---- instruments' view -------------------------------------------------------------
    def apply(self, func):
        """Catch up with the clock, then run func() under the world lock (a setting change
        takes effect at the simulated time it is received)."""
        with self.lock:
            self.catch_up()
            return func()

    def fire_trigger(self) -> None:
        """The common trigger line (generator *TRG): sample 0 of every armed sensor."""
        with self.lock:
            self.catch_up()
            self.trigger_step = self.step
            self.trigger_steps.append(self.step)
            self.trigger_count += 1

    def readings(self, channel: int, steps: np.ndarray, velocity: bool = False) -> np.ndarray:
        """Raw laser readings (0 base, 1 tip) at the given global steps (must be < self.step
        and within the ring): displacement [m], or velocity [m/s] when ``velocity``.  The tip
        channel includes the configured channel delay."""
        steps = np.asarray(steps, dtype=np.int64)
        if channel == 1 and self.delay_steps:
            steps = np.maximum(steps - self.delay_steps, 0)
        return self.ring[channel + (2 if velocity else 0), steps % self.capacity]

    def oldest_step(self) -> int:
        return max(0, self.step - self.capacity)

    # ---- for tests and the rig's supervision -------------------------------------------
    def is_driven(self) -> bool:
        """True when the armature can receive current: generator output on with a nonzero
        signal (a burst waiting for its trigger outputs only its offset) AND amplifier
        enabled, gain > 0 and not muted by a fault."""
        with self.lock:
            G, A = self.G, self.A
            waiting_burst = G[ph.G_BURST] != 0.0 and G[ph.G_BURST_ACTIVE] == 0.0
            signal = G[ph.G_OFFS] != 0.0 or (G[ph.G_VPP] > 0.0 and not waiting_burst)
            gen = G[ph.G_OUT] != 0.0 and signal
            amp = (A[ph.A_ENABLE] != 0.0 and A[ph.A_GAIN] > 0.0
                   and A[ph.A_OC] == 0.0 and A[ph.A_OT] == 0.0 and A[ph.A_WD] == 0.0)
            return bool(gen and amp)

    @property
    def specimen_mass(self) -> float:
        return float(self.config["specimen"]["mass"])

    def truth(self) -> dict:
        """The specimen's true per-unit-mass parameters, in recon's naming."""
        sp = self.config["specimen"]
        return {
            "c_m": float(sp["c_m"]),
            "k_m": float(sp["k_m"]),
            "alpha_m": float(sp["alpha_m"]),
            "gamma": float(sp["gamma"]),
            "delta": float(sp["delta"]),
            "fn_m": {k: float(v) for k, v in sp["fn_m"].items()},
        }

    def state(self) -> dict:
        """True mechanical state now (for tests)."""
        with self.lock:
            X = self.X
            return {"t": self.time, "x_base": X[ph.X_XB], "v_base": X[ph.X_VB], "y": X[ph.X_Y],
                    "dy": X[ph.X_VY], "z": X[ph.X_Z], "temperature": X[ph.X_T],
                    "current": self.A[ph.A_I], "voltage": self.A[ph.A_V]}

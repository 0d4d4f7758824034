"""The one runner that executes plans (headless, in the GUI, in tests).

:class:`Runner` executes the messages of a plan (:mod:`rig.messages`) against
:class:`~rig.instruments.RigInstruments`. While the output runs, every
acquired block is

1. checked by the :class:`~rig.safety.Supervisor` (interlocks),
2. handed to the observers (the HDF5 recorder, progress display, GUI buffers),
3. followed by a look at the abort and pause requests.

So a trip, an abort or a pause acts within one block (``acquisition.block_s``)
inside any step, not only between steps.

Stopping: on abort, a tripped interlock, lost communication, Ctrl-C or any
error, the amplitude ramps from its level to zero in ``limits.abort_ramp_s``
(still supervised and recorded), then the generator output goes off and the
amplifier is muted (``safe_state``); the reason is in the event log. A second
:meth:`Runner.abort` during that ramp cuts at once. If the generator is
unreachable the amplifier is muted at once; if the amplifier is unreachable,
the generator is ramped down and its watchdog mutes it.

Observers are plain objects with any of these methods (all optional)::

    on_run_start(info)                 info: identities, settings, config texts
    on_state(state)                    "running", "paused", "stopping", "done"
    on_stage_begin(name, settings, index)
    on_block(block)                    rig.instruments.Block, block.stage = stage name or None
    on_setpoint(index, vpp, hz, label)
    on_stage_end(name, status, summary)
    on_event(level, message, run_time)
    on_run_end(status, reason)
    on_control(record)                 one closed-loop window (rig.sine_control): target, achieved, error
"""
from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass, field

import numpy as np

from rig.instruments import MIN_VPP, SamplesLost
from rig.messages import (Acquire, BeginStage, Checkpoint, CheckSetpoint, ControlSine, EndStage, Log, Ramp, Rest,
                          SetFrequency, Window)
from rig.safety import LimitError, Supervisor
from rig.sine_control import SineControlExecutor


class _Stop(Exception):
    """Ends the plan: abort, trip or lost communication (status, reason)."""

    def __init__(self, status: str, reason: str):
        super().__init__(reason)
        self.status = status
        self.reason = reason


class _Cut(Exception):
    """A second abort: cut the output at once."""


@dataclass
class RunOutcome:
    status: str                     # complete, aborted, tripped, error
    reason: str = ""
    stages: dict = field(default_factory=dict)   # name -> status
    n_samples: int = 0
    samples_lost: int = 0
    peaks: dict = field(default_factory=dict)
    wall_time_s: float = 0.0
    run_time_s: float = 0.0
    plan_result: object = None
    no_space: str = ""              # the run file's disk filled up: what happened and where the data is


class Runner:
    def __init__(self, instruments, supervisor: Supervisor, observers=()):
        self.inst = instruments
        self.sup = supervisor
        self.observers = list(observers)
        lim = supervisor.limits
        self.ramp_rate = lim["ramp_rate_vpp_per_s"]
        self._long_ramp_blocks = False      # a long block on a ramp was reported (_ramp_to)
        self.abort_ramp_s = lim["abort_ramp_s"]
        self.fs = instruments.fs
        self.state = "idle"
        self.stage: str | None = None
        self.stage_status: dict[str, str] = {}
        self.index = 0                 # next sample index
        self._abort_count = 0
        self._abort_reason = ""
        self._lock = threading.Lock()
        self._pause_requested = threading.Event()
        self._pause_serial = 0
        self._in_pause = False
        self._stopping = False
        self._aborts_at_stop = 0
        self.samples_lost = 0
        self.handlers = {BeginStage: self._begin_stage, EndStage: self._end_stage,
                         SetFrequency: self._set_frequency, Ramp: self._ramp, Acquire: self._acquire_window,
                         Rest: self._rest, Log: self._log_message, Checkpoint: self._checkpoint,
                         CheckSetpoint: self._check_setpoint,
                         ControlSine: self._control_sine}
        self.sine_control = SineControlExecutor(self)   # runs ControlSine messages

    # -- control (thread-safe; also from a signal handler) --------------------------------------
    def subscribe(self, observer) -> None:
        self.observers.append(observer)

    def abort(self, reason: str = "abort requested") -> None:
        """First call: ramp down and stop. A call while already stopping (after an abort, a trip
        or an error) cuts the output at once."""
        with self._lock:
            self._abort_count += 1
            if self._abort_count == 1:
                self._abort_reason = reason

    def pause(self) -> None:
        """Ramp the output to zero at the next block and wait (inside a step too)."""
        self._pause_requested.set()

    def resume(self) -> None:
        self._pause_requested.clear()

    # -- notifications ------------------------------------------------------------------------------
    def _notify(self, method: str, *args) -> None:
        for obs in self.observers:
            fn = getattr(obs, method, None)
            if fn is None:
                continue
            if self._stopping:
                try:
                    fn(*args)
                except Exception:  # noqa: BLE001 - stopping safely matters more than an observer
                    traceback.print_exc()
            else:
                fn(*args)

    def log(self, level: str, message: str) -> None:
        self._notify("on_event", level, message, self.index / self.fs)

    def _set_state(self, state: str) -> None:
        self.state = state
        self._notify("on_state", state)

    # -- blocks ---------------------------------------------------------------------------------------
    def _block(self):
        """Acquire, supervise, record one block; then honour abort/pause requests."""
        try:
            block = self.inst.fetch()
        except SamplesLost as exc:
            self.samples_lost += exc.n
            raise
        block.stage = self.stage
        self.index = block.end_index
        trip = self.sup.check_block(block) if (block.output or not self._stopping) else None
        self._notify("on_block", block)
        if self._stopping and self._abort_count > self._aborts_at_stop:
            raise _Cut()
        if trip is not None and not self._stopping:
            raise _Stop("tripped", f"interlock {trip.limit}: {trip.message}")
        if self.inst.heartbeat_error is not None and not self._stopping:
            raise _Stop("error", f"amplifier heartbeat failed: {self.inst.heartbeat_error}")
        if self._abort_count and not self._stopping:
            raise _Stop("aborted", self._abort_reason)
        if self._pause_requested.is_set() and not self._in_pause and not self._stopping:
            self._pause()
        return block

    def _pause(self):
        self._in_pause = True
        try:
            saved = self.inst.vpp if self.inst.output else 0.0
            self.log("info", f"paused at {saved:.3f} Vpp: ramping the output to zero")
            self._ramp_to(0.0, self.ramp_rate)
            self._set_state("paused")
            while self._pause_requested.is_set():
                if self._abort_count:
                    raise _Stop("aborted", self._abort_reason)
                if self.inst.lockstep:
                    self.inst.mark_alive()
                    time.sleep(0.02)  # simulated world frozen: nothing to acquire
                else:
                    self._block()
            self._set_state("running")
            self.log("info", f"resumed: ramping back to {saved:.3f} Vpp")
            if saved > 0:
                self._ramp_to(saved, self.ramp_rate)
            self._pause_serial += 1
        finally:
            self._in_pause = False

    def _ramp_to(self, target: float, rate: float) -> None:
        """Ramp the amplitude to ``target`` at ``rate`` [Vpp/s of acquired time], one block per step.
        A step is never larger than ``rate`` times the nominal block: a runner that fell behind (a
        slow observer, a loaded machine, a stalled link) fetches one long block, and a step sized on
        it would be a jump of the drive, which sets the specimen ringing. The ramp then takes longer
        than planned; it never steps."""
        if target > 0:
            self.sup.check_amplitude(target)
        current = self.inst.vpp if self.inst.output else 0.0
        if target <= 0 and not self.inst.output:
            return
        nominal = self.inst.block_n / self.fs
        block_dt = nominal
        while True:
            step = rate * block_dt
            if abs(target - current) <= step:
                current = target
            else:
                current += step if target > current else -step
            self.inst.set_amplitude(max(current, MIN_VPP) if current > MIN_VPP else 0.0)
            blk = self._block()
            block_dt = max(blk.n, 1) / self.fs
            if block_dt > nominal:
                if not self._long_ramp_blocks and block_dt > 2 * nominal:
                    # said once a run: a simulated rig faster than real time gives such blocks on every ramp
                    self._long_ramp_blocks = True
                    self.log("warning", f"a block of {block_dt:.3g} s during a ramp (nominal {nominal:.3g} s: the "
                                        f"acquisition fell behind, or a simulated rig runs faster than real time): "
                                        f"ramps keep their steps and take longer")
                block_dt = nominal
            if current == target:
                return

    # -- messages -------------------------------------------------------------------------------------
    def _acquire(self, duration_s: float) -> Window:
        n_target = max(1, int(round(duration_s * self.fs)))
        while True:
            serial = self._pause_serial
            xb, xt, start = [], [], None
            n = 0
            while n < n_target:
                blk = self._block()
                if self._pause_serial != serial:
                    break  # paused inside the window: start it again
                if start is None:
                    start = blk.index0
                xb.append(blk.x_base)
                xt.append(blk.x_tip)
                n += blk.n
            else:
                xb = np.concatenate(xb)[:n_target]
                xt = np.concatenate(xt)[:n_target]
                return Window(start, self.fs, xb, xt, self.inst.vpp if self.inst.output else 0.0, self.inst.frequency)

    # The message-type -> handler table (bluesky's RunEngine command registry, kept small): each
    # handler takes the message and returns what the plan receives back from its ``yield``.
    def _begin_stage(self, msg: BeginStage) -> None:
        if msg.pre_trigger_s > 0:
            self.sup.check_duration(msg.pre_trigger_s)
        self.stage = msg.name
        self.stage_status[msg.name] = "recording"
        settings = dict(msg.settings)
        if msg.pre_trigger_s > 0:
            settings["pre_trigger_s"] = msg.pre_trigger_s
        self._notify("on_stage_begin", msg.name, settings, self.index)
        self.log("info", f"stage {msg.name} begins")
        if msg.pre_trigger_s > 0:
            # the pre-trigger: recorded before the plan's first drive command of the stage
            if self.inst.output:
                self.log("warning", f"stage {msg.name}: the pre-trigger is recorded with the output on "
                                    f"({self.inst.vpp:.3f} Vpp)")
            self._acquire(msg.pre_trigger_s)

    def _end_stage(self, msg: EndStage) -> None:
        self._ramp_to(0.0, self.ramp_rate)
        name = self.stage
        self.stage = None
        self.stage_status[name] = "complete"
        self._notify("on_stage_end", name, "complete", dict(msg.summary))
        self.log("info", f"stage {name} complete")

    def _set_frequency(self, msg: SetFrequency) -> None:
        self.sup.check_frequency(msg.hz)
        self.inst.set_frequency(msg.hz)
        self._notify("on_setpoint", self.index, self.inst.vpp if self.inst.output else 0.0, msg.hz, "frequency")

    def _ramp(self, msg: Ramp) -> None:
        self._notify("on_setpoint", self.index, msg.vpp, self.inst.frequency, f"ramp to {msg.vpp:g} Vpp {msg.label}".strip())
        self._ramp_to(msg.vpp, self.ramp_rate)
        self._notify("on_setpoint", self.index, msg.vpp, self.inst.frequency, f"level {msg.label}".strip())

    def _acquire_window(self, msg: Acquire) -> Window:
        self.sup.check_duration(msg.duration_s)
        return self._acquire(msg.duration_s)

    def _rest(self, msg: Rest) -> None:
        self.sup.check_duration(msg.duration_s)
        self._ramp_to(0.0, self.ramp_rate)
        if msg.duration_s > 0:
            self._acquire(msg.duration_s)

    def _log_message(self, msg: Log) -> None:
        self.log(msg.level, msg.message)

    def _check_setpoint(self, msg: CheckSetpoint) -> None:
        try:
            if msg.vpp is not None:
                self.sup.check_amplitude(msg.vpp)
            if msg.hz is not None:
                self.sup.check_frequency(msg.hz)
        except LimitError as exc:
            raise LimitError(f"{msg.origin}: {exc}") from None

    def _control_sine(self, msg: ControlSine):
        return self.sine_control.execute(msg)

    def _checkpoint(self, msg: Checkpoint) -> None:
        if self._abort_count:
            raise _Stop("aborted", self._abort_reason)
        if self._pause_requested.is_set() and not self._in_pause:
            self._pause()

    def register_command(self, message_type: type, handler) -> None:
        """Execute plan messages of ``message_type`` with ``handler(msg)`` (its return value is sent
        back to the plan)."""
        self.handlers[message_type] = handler

    def _execute(self, msg):
        handler = self.handlers.get(type(msg))
        if handler is None:
            raise TypeError(f"unknown plan message {msg!r}")
        return handler(msg)

    # -- the run ---------------------------------------------------------------------------------------
    def run(self, plan, run_info: dict | None = None) -> RunOutcome:
        """Prepare the instruments, execute ``plan`` to its end or until stopped, make safe."""
        t_wall = time.monotonic()
        status, reason, result = "complete", "", None
        self._set_state("running")
        try:
            try:
                self.inst.prepare(self.sup)
                info = dict(run_info or {})
                info["identities"] = dict(self.inst.identities)
                info["settings"] = self.inst.settings()
                self._notify("on_run_start", info)
                self.inst.start_heartbeat()
                self.inst.start_acquisition()
                rest = self._acquire(0.1)
                self.sup.set_rest(float(np.mean(rest.x_base)), float(np.mean(rest.x_tip)))
                self.log("info", f"rest readings: base {self.sup.rest['x_base'] * 1e3:.4f} mm, "
                                 f"tip {self.sup.rest['x_tip'] * 1e3:.4f} mm")
                send = None
                while True:
                    try:
                        msg = plan.send(send)
                    except StopIteration as stop:
                        result = stop.value
                        break
                    send = self._execute(msg)
            except _Stop as exc:
                status, reason = exc.status, exc.reason
            except LimitError as exc:
                status, reason = "tripped", f"setpoint refused: {exc}"
            except KeyboardInterrupt:
                status, reason = "aborted", "Ctrl-C"
            except SamplesLost as exc:
                status, reason = "error", f"acquisition: {exc}"
            except Exception as exc:  # noqa: BLE001 - instrument errors, observer errors: stop safely
                status, reason = "error", f"{type(exc).__name__}: {exc}"
            if status != "complete":
                self._stop_safely(status, reason)
        finally:
            plan.close()
            self._stopping = True
            safe_state = self.inst.mute()
            if self.stage is not None:
                self.stage_status[self.stage] = status if status != "complete" else "interrupted"
                self._notify("on_stage_end", self.stage, self.stage_status[self.stage], {"stop_reason": reason})
                self.stage = None
            self.inst.stop_heartbeat()
            if self.inst.heartbeat_stalled:
                self.log("warning", "the runner stalled: the heartbeat was withheld so the amplifier watchdog "
                                    "could mute the output")
            self.log("debug", f"longest gap between amplifier heartbeats: {self.inst.max_heartbeat_gap:.3f} s")
            self.log("info" if status == "complete" and safe_state.confirmed else "error",
                     f"run {status}" + (f": {reason}" if reason else "") + f"; {safe_state}")
            self._notify("on_run_end", status, reason)
            self._set_state("done")
        return RunOutcome(status=status, reason=reason, stages=dict(self.stage_status), n_samples=self.index,
                          samples_lost=self.samples_lost, peaks=dict(self.sup.peak),
                          wall_time_s=time.monotonic() - t_wall, run_time_s=self.index / self.fs,
                          plan_result=result)

    def _stop_safely(self, status: str, reason: str) -> None:
        """Ramp to zero in abort_ramp_s (supervised, recorded); a second abort cuts at once."""
        self._stopping = True
        # the abort that caused this stop (if any) is used up; any further one cuts at once
        self._aborts_at_stop = min(self._abort_count, 1) if status == "aborted" else 0
        self._set_state("stopping")
        level = "warning" if status == "aborted" else "error"
        vpp = self.inst.vpp if self.inst.output else 0.0
        self.log(level, f"stopping ({status}): {reason}; ramping {vpp:.3f} Vpp to zero in {self.abort_ramp_s:g} s")
        if vpp <= 0:
            return
        if self._abort_count > self._aborts_at_stop:
            self.log("warning", "second abort: output cut at once")
            return
        rate = vpp / self.abort_ramp_s
        try:
            self._ramp_to(0.0, rate)
            return
        except _Cut:
            self.log("warning", "second abort: output cut at once")
            return
        except Exception as exc:  # noqa: BLE001 - a dead instrument during the ramp
            self.log("error", f"ramp-down while acquiring failed ({type(exc).__name__}: {exc})")
        # Sensors (or the recorder) gone: ramp the generator down on the wall clock, without acquiring.
        try:
            n = max(1, int(self.abort_ramp_s / 0.02))
            for i in range(n - 1, -1, -1):
                if self._abort_count > self._aborts_at_stop:
                    self.log("warning", "second abort: output cut at once")
                    return
                self.inst.set_amplitude(vpp * i / n)
                self.inst.mark_alive()
                time.sleep(0.02)
            self.log("info", "generator ramped down on the wall clock")
        except Exception as exc:  # noqa: BLE001 - the generator itself is gone
            self.log("error", f"generator unreachable ({type(exc).__name__}: {exc}): muting the amplifier at once")

"""The rig's instruments behind one object: connect, prepare, acquire aligned blocks, make safe.

:class:`RigInstruments` owns the four drivers (generator, amplifier, base and
tip sensors) at the addresses of a :class:`~rig.config.RigConfig`, the
amplifier heartbeat thread, and the alignment of the two sensor streams on
their shared sample index (both are armed before one common trigger).

A sensor set to report velocity (``[sensors.*] quantity = "velocity"``) is
integrated here, block by block, into the displacement every consumer of a
:class:`Block` works with (supervisor limits, plans, control, live plots; all in
metres); the velocity itself travels in ``Block.measured`` to the recorder.
See :class:`VelocityIntegrator` for the integrator and its error.

Each sensor's ``sensitivity`` (its calibration factor, ``[sensors.*]``)
multiplies every reading here, before anything else sees it.

The amplifier is one of three kinds (``[amplifier] kind``): the shakerlab
register map, a declared vendor Modbus map, or a *manual* amplifier with no
remote control.  A manual amplifier cannot be muted from here: stopping then
means ramping the generator down and switching its output off, and
:class:`SafeStateReport` says so.

The heartbeat feeds the amplifier's comms watchdog from a background thread
only while the runner keeps making progress (:meth:`mark_alive`): if the
controller process dies or its loop stalls for ``stall_timeout_s``, the
heartbeat stops and the amplifier mutes itself within its watchdog timeout.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from drivers.base import InstrumentError
from drivers.laser_sensor import LaserSensor
from drivers.line_link import SerialSettings
from drivers.modbus_amplifier import RegisterMap, modbus_amplifier
from drivers.power_amplifier import PowerAmplifier
from drivers.signal_generator import SignalGenerator

MIN_VPP = 0.001  # the generator's lowest amplitude; "zero" = this, then output off
# time constant of the real-time integration of a velocity sensor [s]: a leak that keeps an offset or
# the integrated noise bounded, far below every drive frequency (see VelocityIntegrator)
VELOCITY_LEAK_S = 10.0


class VelocityIntegrator:
    """Causal, real-time displacement from a velocity sensor's blocks [m/s -> m].

    Trapezoidal integration with a leak: ``x[n] = a x[n-1] + dt (v[n] + v[n-1]) / 2``,
    ``a = exp(-dt / tau)``, started at zero on the first sample (the rig starts at rest). For a
    tone at ``f`` the leak scales the amplitude by ``1 / sqrt(1 + 1/(w tau)^2)`` and advances
    the phase by ``atan(1/(w tau))``; the trapezoid scales it by ``(w dt/2) / tan(w dt/2)``:
    at 5 Hz and tau = 10 s, 5e-6 and 3 mrad; at the highest drive frequency 500 Hz
    (fs = 10 kHz), -0.8 %. Both sensors are integrated alike, so ratios and phases between
    them (gain, transmissibility, loss factor) are unchanged. A constant velocity offset ``b``
    becomes a displacement offset ``b tau`` (about the rest reading, which the supervisor
    removes); white noise of std ``s`` becomes ``s sqrt(dt tau / 2)`` rms (2e-5 m/s at 10 kHz:
    0.45 um)."""

    def __init__(self, fs: float, tau_s: float = VELOCITY_LEAK_S):
        self.dt = 1.0 / fs
        self.a = float(np.exp(-self.dt / tau_s))
        self.b = np.array([self.dt / 2, self.dt / 2])
        self.den = np.array([1.0, -self.a])
        self.zi: np.ndarray | None = None

    def __call__(self, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        if v.size == 0:
            return v.copy()
        if self.zi is None:
            self.zi = np.array([-self.dt / 2 * v[0]])   # x[0] = 0
        x, self.zi = lfilter(self.b, self.den, v, zi=self.zi)
        return x


@dataclass
class Block:
    """Samples ``index0 .. index0+n-1`` of both sensors, aligned, plus the drive state.

    ``x_base``/``x_tip`` are always displacement [m]: as measured, or integrated in real time
    from a velocity sensor (:class:`VelocityIntegrator`). ``measured`` holds what a velocity
    sensor reported, by channel name (``{"v_tip": ...}``, m/s); empty when both give
    displacement."""

    index0: int
    fs: float
    x_base: np.ndarray
    x_tip: np.ndarray
    flags_base: np.ndarray
    flags_tip: np.ndarray
    amplitude_vpp: float = 0.0
    frequency_hz: float = 0.0
    output: bool = False
    current_a: float | None = None
    amplifier_faults: list = field(default_factory=list)
    stage: str | None = None
    measured: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.x_base.size)

    @property
    def end_index(self) -> int:
        return self.index0 + self.n

    @property
    def run_time(self) -> float:
        """Time of the block's end since the common trigger [s]."""
        return self.end_index / self.fs


class _Aligner:
    """Joins two sensor streams on their sample index; counts lost samples."""

    def __init__(self):
        self.pending = {0: [], 1: []}  # per channel: list of (index0, values, flags)
        self.next_expected = {0: 0, 1: 0}
        self.emitted = 0
        self.lost = 0

    def add(self, ch: int, block) -> None:
        n = len(block.values)
        if n == 0:
            return
        if block.index0 != self.next_expected[ch]:
            gap = block.index0 - self.next_expected[ch]
            raise SamplesLost(f"sensor {'tip' if ch else 'base'}: {gap} sample(s) lost before index {block.index0} "
                              f"(expected {self.next_expected[ch]})", gap)
        self.next_expected[ch] = block.index0 + n
        self.pending[ch].append((block.index0, np.asarray(block.values, float), np.asarray(block.flags, np.uint8)))

    def take(self):
        """The aligned samples available on both channels: (index0, [values, flags] x 2)."""
        end = min(self.next_expected[0], self.next_expected[1])
        if end <= self.emitted:
            return None
        out = []
        for ch in (0, 1):
            vals = np.concatenate([p[1] for p in self.pending[ch]])
            flags = np.concatenate([p[2] for p in self.pending[ch]])
            first = self.pending[ch][0][0]
            cut = end - first
            out.append((vals[:cut], flags[:cut]))
            self.pending[ch] = [(end, vals[cut:], flags[cut:])] if cut < vals.size else []
        index0 = self.emitted
        self.emitted = end
        return index0, out


@dataclass(frozen=True)
class SafeStateReport:
    """What :meth:`RigInstruments.mute` confirmed by reading the instruments back ("" = confirmed)."""

    generator_problem: str
    amplifier_problem: str
    watchdog_timeout_s: float | None
    manual_amplifier: bool = False

    @property
    def confirmed(self) -> bool:
        return not (self.generator_problem or self.amplifier_problem)

    def __str__(self) -> str:
        generator = ("generator output off (read back)" if not self.generator_problem else
                     f"generator output NOT confirmed off ({self.generator_problem})")
        if self.manual_amplifier:
            return (f"{generator}; manual amplifier: not muted (no remote control), the generator was stopped "
                    f"instead")
        if self.watchdog_timeout_s is None:
            watchdog = "it has no comms watchdog: switch it off at its front panel"
        else:
            watchdog = f"its comms watchdog mutes it after {self.watchdog_timeout_s:g} s of silence"
        amplifier = ("amplifier muted (read back: disabled, gain 0)" if not self.amplifier_problem else
                     f"amplifier NOT confirmed muted ({self.amplifier_problem}); {watchdog}")
        return f"{generator}; {amplifier}"


class SamplesLost(Exception):
    def __init__(self, message: str, n: int):
        super().__init__(message)
        self.n = n


class ManualAmplifier:
    """An amplifier with no remote control: the gain the operator set on its front panel, as data."""

    name = "manual amplifier"

    def __init__(self, gain: float):
        self.gain = float(gain)

    def identify(self) -> str:
        return f"manual amplifier (gain {self.gain:g} set on the front panel; no remote control)"

    def close(self) -> None:
        pass


def serial_settings(table: dict) -> SerialSettings:
    """The serial line settings of one instrument's rig-config table."""
    return SerialSettings(baudrate=table["baudrate"], data_bits=table["data_bits"], parity=table["parity"],
                          stop_bits=table["stop_bits"] if table["stop_bits"] == 1.5 else int(table["stop_bits"]),
                          flow_control=table["flow_control"])


def link_options(table: dict) -> dict:
    """Keyword arguments of a text-protocol driver from its rig-config table."""
    return {"timeout": table["timeout_s"], "read_term": table["read_termination"],
            "write_term": table["write_termination"], "serial_settings": serial_settings(table)}


def register_map(table: dict) -> RegisterMap:
    return RegisterMap(**{k: v for k, v in table.items() if v is not None})


class RigInstruments:
    """Drivers for one rig configuration. ``lockstep=True`` for a simulated rig run as fast as possible."""

    def __init__(self, config, lockstep: bool = False):
        self.config = config
        self.lockstep = lockstep
        self.fs = float(config.acquisition["sample_rate_hz"])
        self.block_n = max(1, int(round(config.acquisition["block_s"] * self.fs)))
        self.gen = self.amp = self.base = self.tip = None
        self.amp_lock = threading.RLock()
        self._aligner = _Aligner()
        self._last_fetch = 0.0
        self._alive = time.monotonic()
        self._hb_thread: threading.Thread | None = None
        self._hb_stop = threading.Event()
        self.heartbeat_error: Exception | None = None
        self.heartbeat_stalled = False
        self.max_heartbeat_gap = 0.0  # longest time between two heartbeats [s] (diagnostic)
        self.identities: dict[str, str] = {}
        self.quantities = config.quantities          # {"base": ..., "tip": ...}
        self.amp_kind = config.data["amplifier"]["kind"]
        self.sensitivity = {p: float(config.data["sensors"][p]["sensitivity"]) for p in ("base", "tip")}
        self._integrators: dict[str, VelocityIntegrator] = {}
        self.vpp = 0.0
        self.frequency = 0.0
        self.output = False

    # -- connection -------------------------------------------------------------------------
    def connect(self) -> dict:
        """Open every driver and identify it; return {name: identity}."""
        d = self.config.data
        g = d["generator"]
        self.gen = SignalGenerator(g["resource"] or g["url"], visa_library=g["visa_library"], **link_options(g))
        a = d["amplifier"]
        if self.amp_kind == "manual":
            self.amp = ManualAmplifier(a["gain"])
        elif self.amp_kind == "modbus":
            self.amp = modbus_amplifier(a["address"], register_map(a["registers"]), device_id=a["device_id"],
                                        timeout=a["timeout_s"])
        else:
            self.amp = PowerAmplifier(a["address"], device_id=a["device_id"], timeout=a["timeout_s"])
        self.base = LaserSensor(d["sensors"]["base"]["url"], name="base", **link_options(d["sensors"]["base"]))
        self.tip = LaserSensor(d["sensors"]["tip"]["url"], name="tip", **link_options(d["sensors"]["tip"]))
        self.identities = {"generator": self.gen.identify(), "amplifier": self.amp.identify(),
                           "sensor_base": self.base.identify(), "sensor_tip": self.tip.identify()}
        return self.identities

    def prepare(self, supervisor) -> None:
        """Put every instrument in a known, silent state and set the hardware limits."""
        d = self.config.data
        lim = self.config.limits
        gen = self.gen
        gen.reset()
        gen.output = False
        gen.offset = 0.0
        gen.amplitude = MIN_VPP
        half = lim["max_generator_vpp"] / 2
        gen.set_voltage_limits(-half, half)
        gen.check_errors()
        for point, s in (("base", self.base), ("tip", self.tip)):
            s.sampling_rate = self.fs
            if self.quantities[point] != "displacement":
                # only then: a displacement-only controller (a real LK-G) does not know the MD command,
                # and the displacement default sends exactly what it always sent
                s.quantity = self.quantities[point]
                got = s.quantity
                if got != self.quantities[point]:
                    raise InstrumentError(s.name, "MD", f"measuring mode reads back {got!r}, "
                                                        f"[sensors.{point}] quantity asks {self.quantities[point]!r}")
            want = self.config.data["sensors"][point]["range_m"]
            if want is not None:
                got = s.measuring_range if self.quantities[point] == "displacement" else s.velocity_range
                if abs(got - want) > 1e-3 * want:
                    raise InstrumentError(s.name, "RG" if self.quantities[point] == "displacement" else "VR",
                                          f"the controller reports a half range of {got:g}, [sensors.{point}] "
                                          f"range_m asks {want:g}")
        supervisor.check_gain(d["amplifier"]["gain"])
        if self.amp_kind != "manual":
            with self.amp_lock:
                amp = self.amp
                amp.enabled = False
                amp.reset_faults()
                if self.amp_kind == "shakerlab":
                    amp.gain = d["amplifier"]["gain"]
                    amp.current_limit = d["amplifier"]["current_limit_a"]
                    amp.watchdog_timeout = d["amplifier"]["watchdog_timeout_s"]
                else:
                    if amp.register_map.gain is not None:
                        amp.gain = d["amplifier"]["gain"]
                    if amp.has_watchdog:
                        amp.watchdog_timeout = d["amplifier"]["watchdog_timeout_s"]
                amp.enabled = True  # the generator output is off: nothing flows yet
        self.vpp, self.output = MIN_VPP, False

    @property
    def watchdog_timeout_s(self) -> float | None:
        """The amplifier's comms watchdog [s]; None when it has none (manual, or a map without one)."""
        if self.amp_kind == "shakerlab" or (self.amp_kind == "modbus" and self.amp.has_watchdog):
            return self.config.data["amplifier"]["watchdog_timeout_s"]
        return None

    def settings(self) -> dict:
        """Every setting read back from the instruments (for the run file)."""
        out = {}
        g = self.gen
        out["generator"] = {"address": self.config.data["generator"]["url"], "frequency_hz": g.frequency,
                            "amplitude_vpp": g.amplitude, "offset_v": g.offset, "output": g.output,
                            "voltage_limit_vpp": self.config.limits["max_generator_vpp"]}
        if self.config.data["generator"]["resource"]:
            out["generator"]["visa_library"] = self.config.data["generator"]["visa_library"] or "auto"
        ca = self.config.data["amplifier"]
        with self.amp_lock:
            a = self.amp
            if self.amp_kind == "shakerlab":
                out["amplifier"] = {"address": ca["address"], "device_id": ca["device_id"],
                                    "enabled": a.enabled, "gain": a.gain, "current_limit_a": a.current_limit,
                                    "watchdog_timeout_s": a.watchdog_timeout}
            elif self.amp_kind == "modbus":
                m = a.register_map
                out["amplifier"] = {"kind": "modbus", "address": ca["address"], "device_id": ca["device_id"],
                                    "enabled": a.enabled,
                                    "gain": a.gain if m.gain is not None else ca["gain"],
                                    "gain_source": "register" if m.gain is not None else "front panel (rig config)",
                                    "watchdog_timeout_s": a.watchdog_timeout if a.has_watchdog else "none",
                                    "register_map": {k: v for k, v in ca["registers"].items() if v is not None}}
            else:
                out["amplifier"] = {"kind": "manual", "gain": a.gain, "gain_source": "front panel (rig config)",
                                    "remote_control": False,
                                    "on_stop": "the generator is ramped down and its output switched off; the "
                                               "amplifier is not muted (no remote control)"}
        for name, s in (("sensor_base", self.base), ("sensor_tip", self.tip)):
            point = name.split("_")[1]
            cs = self.config.data["sensors"][point]
            out[name] = {"address": cs["url"],
                         "sampling_rate_hz": s.sampling_rate, "measuring_range_m": s.measuring_range}
            if (cs["sensitivity"], cs["serial_number"], cs["calibration_date"]) != (1.0, "", ""):
                # the uncalibrated default keeps the settings it always had (the same run file)
                out[name].update(sensitivity=cs["sensitivity"], serial_number=cs["serial_number"],
                                 calibration_date=cs["calibration_date"])
            if self.quantities[name.split("_")[1]] != "displacement":
                # the displacement default keeps the settings it always had (the same run file)
                out[name].update(quantity=s.quantity, velocity_range_m_s=s.velocity_range)
        return out

    # -- heartbeat --------------------------------------------------------------------------
    def mark_alive(self) -> None:
        self._alive = time.monotonic()

    def start_heartbeat(self) -> None:
        if self.watchdog_timeout_s is None:
            return  # no comms watchdog to feed
        period = self.watchdog_timeout_s / 8
        stall = self.config.acquisition["stall_timeout_s"]
        self._hb_stop.clear()
        self.mark_alive()

        def loop():
            last = time.monotonic()
            while not self._hb_stop.wait(period):
                if time.monotonic() - self._alive > stall:
                    self.heartbeat_stalled = True  # let the watchdog mute the amplifier
                    continue
                try:
                    with self.amp_lock:
                        self.amp.heartbeat()
                except Exception as exc:  # noqa: BLE001 - reported to the runner
                    self.heartbeat_error = exc
                    return
                now = time.monotonic()
                self.max_heartbeat_gap = max(self.max_heartbeat_gap, now - last)
                last = now

        self._hb_thread = threading.Thread(target=loop, name="amplifier-heartbeat", daemon=True)
        self._hb_thread.start()

    def stop_heartbeat(self) -> None:
        self._hb_stop.set()
        if self._hb_thread is not None:
            self._hb_thread.join(timeout=2.0)
            self._hb_thread = None

    # -- acquisition --------------------------------------------------------------------------
    def start_acquisition(self) -> None:
        """Arm both sensors (continuous) and fire the common trigger: sample 0 of both."""
        self.base.arm(None)
        self.tip.arm(None)
        self.gen.trigger()
        self._aligner = _Aligner()
        self._integrators = {p: VelocityIntegrator(self.fs) for p, q in self.quantities.items() if q == "velocity"}
        self._last_fetch = time.monotonic()

    def fetch(self) -> Block:
        """The next aligned block of both sensors (waits for it in real time)."""
        while True:
            if self.lockstep:
                self._aligner.add(0, self.base.fetch(self.block_n))
                self._aligner.add(1, self.tip.fetch(self.block_n))
            else:
                wait = self._last_fetch + self.block_n / self.fs - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                self._last_fetch = time.monotonic()
                self._aligner.add(0, self.base.fetch())
                self._aligner.add(1, self.tip.fetch())
            got = self._aligner.take()
            if got is not None:
                break
        index0, ((xb, fb), (xt, ft)) = got
        if self.sensitivity["base"] != 1.0:
            xb = xb * self.sensitivity["base"]
        if self.sensitivity["tip"] != 1.0:
            xt = xt * self.sensitivity["tip"]
        measured = {}
        if self._integrators:
            readings = {"base": xb, "tip": xt}
            for point, integrate in self._integrators.items():
                v = readings[point]
                measured[f"v_{point}"] = v
                # a flagged (NaN) sample would poison the integrator for good: the supervisor trips on
                # the flag in this block; the integrator carries on from zero velocity
                readings[point] = integrate(np.where(np.isfinite(v), v, 0.0))
            xb, xt = readings["base"], readings["tip"]
        current, faults = None, []
        if self.amp_kind != "manual":
            with self.amp_lock:
                current = self.amp.output_current
                faults = self.amp.check_errors()
        self.mark_alive()
        return Block(index0=index0, fs=self.fs, x_base=xb, x_tip=xt, flags_base=fb, flags_tip=ft,
                     amplitude_vpp=self.vpp if self.output else 0.0, frequency_hz=self.frequency,
                     output=self.output, current_a=current, amplifier_faults=list(faults), measured=measured)

    # -- drive ----------------------------------------------------------------------------------
    def set_frequency(self, hz: float) -> None:
        self.gen.frequency = hz
        self.frequency = hz

    def set_amplitude(self, vpp: float) -> None:
        """Set the generator amplitude; at or below MIN_VPP the output is switched off."""
        if vpp <= MIN_VPP:
            if self.output:
                self.gen.amplitude = MIN_VPP
                self.gen.output = False
            self.vpp, self.output = MIN_VPP, False
            return
        self.gen.amplitude = vpp
        self.vpp = vpp
        if not self.output:
            self.gen.output = True
            self.output = True

    def mute(self) -> "SafeStateReport":
        """Generator output off and amplifier muted, each tried even if the other fails, each read back;
        report what was confirmed. A manual amplifier cannot be muted: the generator output off is the
        safe state."""
        generator_problem = amplifier_problem = ""
        try:
            self.gen.safe_state()  # OUTP OFF, then OUTP? must read 0
            self.output = False
        except Exception as exc:  # noqa: BLE001 - reported, the amplifier is still muted
            generator_problem = str(exc)
        if self.amp_kind == "manual":
            return SafeStateReport(generator_problem, "", None, manual_amplifier=True)
        try:
            with self.amp_lock:
                self.amp.safe_state()
                has_gain = self.amp_kind == "shakerlab" or self.amp.register_map.gain is not None
                if self.amp.enabled or (has_gain and self.amp.gain != 0.0):
                    amplifier_problem = "ENABLE/GAIN still read non-zero after the write"
        except Exception as exc:  # noqa: BLE001 - reported; its comms watchdog mutes it
            amplifier_problem = str(exc)
        return SafeStateReport(generator_problem, amplifier_problem, self.watchdog_timeout_s)

    def close(self) -> None:
        self.stop_heartbeat()
        for drv in (self.base, self.tip):
            if drv is not None:
                try:
                    drv.stop()
                except Exception:  # noqa: BLE001 - closing anyway
                    pass
        for drv in (self.gen, self.amp, self.base, self.tip):
            if drv is not None:
                try:
                    drv.close()
                except Exception:  # noqa: BLE001
                    pass

"""Simulated laser displacement sensor controller (ASCII protocol in the style of Keyence LK-G).

Requests and replies end with CR.  Readings are in millimetres with five
decimals (10 nm), or in mm/s in velocity mode (``MD,1``: the controller as a
vibrometer's velocity decoder).  See docs/protocols.md for the command set.  Both simulated
sensors read the same world, so buffered acquisitions armed before a common
trigger (the generator's ``*TRG``) share one time base: sample ``n`` of either
sensor is world step ``trigger_step + n * decimation``.
"""
from __future__ import annotations

import math

import numpy as np

from sim_backend.line_server import is_printable_ascii

MODEL = "shakerlab SIM-LKG5001"
RATES = (1000, 2000, 5000, 10000, 20000, 50000)  # the controller's selectable sampling rates [Hz]
MAX_PER_REPLY = 100_000
MAX_ARM = 1_000_000_000
OVER_POS, OVER_NEG, LOSS = "+FFFFFFF", "-FFFFFFF", "XXXXXXXX"
MODES = ("displacement", "velocity")  # MD,0 / MD,1

E_COMMAND, E_PARAM, E_RANGE, E_STATE = "00", "20", "22", "30"
INVALID_REQUEST = f"ER,??,{E_COMMAND}"   # a non-ASCII or control byte: the command cannot be named
LINE_TOO_LONG = f"ER,??,{E_PARAM}"


class _Err(Exception):
    def __init__(self, cmd: str, code: str):
        self.cmd = cmd
        self.code = code


class SimLaserSensor:
    def __init__(self, world, channel: int, name: str):
        self.world = world
        self.channel = channel  # 0 base, 1 tip
        self.name = name
        cfg = world.config["sensors"]
        self.range_m = float(cfg["range"])
        self.velocity_range = float(cfg["velocity_range"])
        self.mode = "displacement"
        self.resolution = float(cfg["resolution"])
        self.signal_loss = False  # test hook: the laser spot is lost (e.g. dust, specimen edge)
        self.rate = int(world.sample_rate) if int(world.sample_rate) in RATES else RATES[0]
        self.state = "IDLE"
        self.n_target: int | None = None
        self.armed_at_trigger = 0
        self.start_step = 0
        self.next_index = 0
        self.overflow = False
        self.loss_seen = False

    @property
    def decimation(self) -> int:
        return int(round(self.world.sample_rate / self.rate))

    # ---- protocol ---------------------------------------------------------------------------
    def handle(self, line: str) -> str:
        if not is_printable_ascii(line):
            return INVALID_REQUEST
        cmd, *args = [p.strip() for p in line.split(",")]
        cmd = cmd.upper()
        try:
            handler = getattr(self, f"_cmd_{cmd}", None)
            if handler is None:
                raise _Err(cmd, E_COMMAND)
            return handler(args)
        except _Err as exc:
            # the reply names the command only where it is printable as sent (a tab inside it is
            # accepted on input as whitespace but would put a control byte in the reply)
            name = exc.cmd if is_printable_ascii(exc.cmd, tab=False) else "??"
            return f"ER,{name},{exc.code}"

    def _cmd_ID(self, args):
        self._no_args("ID", args)
        return f"ID,{MODEL},{self.name}"

    def _cmd_RG(self, args):
        self._no_args("RG", args)
        return f"RG,{self.range_m * 1e3:.3f}"

    def _cmd_VR(self, args):
        self._no_args("VR", args)
        return f"VR,{self.velocity_range * 1e3:.3f}"

    def _cmd_MD(self, args):
        """Measuring mode: 0 displacement (mm), 1 velocity (mm/s); not while armed or running."""
        if not args:
            return f"MD,{MODES.index(self.mode)}"
        code = self._one_count("MD", args)
        if code >= len(MODES):
            raise _Err("MD", E_RANGE)
        self._idle("MD")
        self.mode = MODES[code]
        return "MD"

    def _cmd_SS(self, args):
        if not args:
            return f"SS,{self.rate}"
        rate = self._one_count("SS", args)
        if rate not in RATES or self.world.sample_rate % rate:
            raise _Err("SS", E_RANGE)
        self._idle("SS")
        self.rate = rate
        return "SS"

    def _cmd_M0(self, args):
        self._no_args("M0", args)
        w = self.world
        with w.lock:
            w.catch_up()
            if w.step == 0:
                w.advance(1)
            value = w.readings(self.channel, np.array([w.step - 1]), self.mode == "velocity")[0]
        return "M0," + self._format(np.array([value]))[0]

    def _cmd_AS(self, args):
        n = self._one_count("AS", args)
        if n > MAX_ARM:
            raise _Err("AS", E_RANGE)
        with self.world.lock:
            self.n_target = n or None
            self.armed_at_trigger = self.world.trigger_count
            self.state = "ARMED"
            self.next_index = 0
            self.overflow = False
        return "AS"

    def _cmd_AQ(self, args):
        self._no_args("AQ", args)
        self.state = "IDLE"
        return "AQ"

    def _cmd_ST(self, args):
        self._no_args("ST", args)
        with self.world.lock:
            self._update_state()
            acquired = self._available() if self.state in ("RUNNING", "DONE") else 0
        return f"ST,{self.state},{acquired},{self.next_index}"

    def _cmd_EQ(self, args):
        """Alarm bits since the last EQ: bit0 buffer overflow, bit1 signal loss."""
        self._no_args("EQ", args)
        bits = (1 if self.overflow else 0) | (2 if (self.loss_seen or self.signal_loss) else 0)
        self.overflow = False
        self.loss_seen = False
        return f"EQ,{bits}"

    def _cmd_AO(self, args):
        if len(args) > 1 or (args and not args[0].isdigit()):
            raise _Err("AO", E_PARAM)
        max_n = int(args[0]) if args else None
        if max_n is not None and not 1 <= max_n <= MAX_PER_REPLY:
            raise _Err("AO", E_RANGE)
        w = self.world
        with w.lock:
            self._update_state()
            if self.state == "IDLE":
                raise _Err("AO", E_STATE)
            if self.state == "ARMED":
                return "AO,0,0"
            k = self.decimation
            want = max_n if max_n is not None else MAX_PER_REPLY
            if w.lockstep:
                goal = self.next_index + (max_n if max_n is not None else max(1, w.lockstep_block // k))
                if max_n is None and self._available() > self.next_index:
                    goal = self.next_index  # something new already: return it without advancing
                if self.n_target is not None:
                    goal = min(goal, self.n_target)
                if goal > 0:
                    w.ensure_step(self.start_step + (goal - 1) * k + 1)
            else:
                w.catch_up()
            avail = self._available()
            # samples that fell out of the ring are lost: flag the overflow and skip ahead
            # (the tip channel reads delay_steps back: its oldest reading is that much later, once the
            # ring has wrapped; before, the delayed channel reads the first sample)
            oldest = w.oldest_step()
            if self.channel == 1 and oldest > 0:
                oldest += w.delay_steps
            first_ok = max(0, math.ceil((oldest - self.start_step) / k))
            if self.next_index < first_ok:
                self.overflow = True
                self.next_index = min(first_ok, avail)
            n = max(0, min(want, avail - self.next_index))
            index0 = self.next_index
            steps = self.start_step + (index0 + np.arange(n, dtype=np.int64)) * k
            values = w.readings(self.channel, steps, self.mode == "velocity")
            self.next_index += n
            self._update_state()
        parts = self._format(values)
        return f"AO,{index0},{n}" + ("," + ",".join(parts) if n else "")

    # ---- helpers --------------------------------------------------------------------------------
    @staticmethod
    def _no_args(cmd, args):
        if args:
            raise _Err(cmd, E_PARAM)

    @staticmethod
    def _one_count(cmd, args) -> int:
        """The command's single non-negative integer argument (else a parameter error)."""
        if len(args) != 1 or not args[0].isdigit():
            raise _Err(cmd, E_PARAM)
        return int(args[0])

    def _idle(self, cmd) -> None:
        """A setting that may not change while the sensor is armed or acquiring."""
        if self.state in ("ARMED", "RUNNING"):
            raise _Err(cmd, E_STATE)

    def _update_state(self) -> None:
        w = self.world
        if self.state == "ARMED" and w.trigger_count > self.armed_at_trigger:
            self.start_step = w.trigger_steps[self.armed_at_trigger]
            self.state = "RUNNING"
        if self.state == "RUNNING" and self.n_target is not None and self.next_index >= self.n_target:
            self.state = "DONE"

    def _available(self) -> int:
        """Samples acquired so far (index < world.step)."""
        k = self.decimation
        n = max(0, math.ceil((self.world.step - self.start_step) / k))
        if self.n_target is not None:
            n = min(n, self.n_target)
        return n

    def _format(self, values: np.ndarray) -> list[str]:
        if self.signal_loss:
            self.loss_seen = True
            return [LOSS] * len(values)
        q = np.round(values / self.resolution) * self.resolution
        limit = self.velocity_range if self.mode == "velocity" else self.range_m
        out = []
        for v in q:
            if v > limit:
                out.append(OVER_POS)
            elif v < -limit:
                out.append(OVER_NEG)
            else:
                out.append(f"{v * 1e3:+.5f}")
        return out

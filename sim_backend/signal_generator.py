"""Simulated function generator: an SCPI subset modelled on the Keysight 33500B.

See docs/protocols.md for the command set.  The generator's output voltage is
part of the physics (:mod:`sim_backend.physics`); this module parses SCPI,
validates, keeps the error queue and pushes settings into the world at the
simulated time the command is received.
"""
from __future__ import annotations

import re

from sim_backend import physics as ph
from sim_backend.line_server import MAX_LINE, is_printable_ascii

IDN = "shakerlab,SIM33521B,SIM0001,0.1.0"
QUEUE_LEN = 20

ERRORS = {
    -101: "Invalid character",
    -102: "Syntax error",
    -104: "Data type error",
    -108: "Parameter not allowed",
    -109: "Missing parameter",
    -113: "Undefined header",
    -221: "Settings conflict",
    -222: "Data out of range",
    -223: "Too much data",
    -224: "Illegal parameter value",
    -350: "Queue overflow",
}

LIMITS = {
    "FREQ": (1e-6, 30e6, 1000.0),
    "VOLT": (1e-3, 10.0, 0.1),
    "OFFS": (-5.0, 5.0, 0.0),
    "LIM": (-5.0, 5.0, None),
    "SWE:TIME": (1e-3, 3600.0, 1.0),
    "NCYC": (1, 100_000_000, 1),
}
LINE_TOO_LONG = f'-223,"Too much data; request line longer than {MAX_LINE} bytes: connection closed"'
MAX_OUTPUT = 5.0  # V peak into 50 ohm: |offset| + Vpp/2 must stay within this

_UNITS = {
    "HZ": 1.0, "KHZ": 1e3, "MAHZ": 1e6, "V": 1.0, "VPP": 1.0, "MV": 1e-3, "MVPP": 1e-3,
    "S": 1.0, "MS": 1e-3, "US": 1e-6,
}
_NUM = re.compile(r"^([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*([A-Za-z]*)$")


class ScpiError(Exception):
    def __init__(self, code: int, detail: str = ""):
        self.code = code
        self.detail = detail
        super().__init__(code, detail)


def _compile(pattern: str):
    """'[SOURce:]FREQuency[:CW]' -> [(short, long, optional), ...]"""
    nodes = []
    for m in re.finditer(r"(\[?):?([A-Za-z*]+)\]?", pattern):
        word = m.group(2)
        short = "".join(c for c in word if c.isupper() or c == "*")
        nodes.append((short, word.upper(), m.group(1) == "["))
    return nodes


def _match(nodes, parts) -> bool:
    if not nodes:
        return not parts
    short, long_, optional = nodes[0]
    if parts:
        p = parts[0]
        if p[-1:] == "1" and p[:-1] in (short, long_) and not short.startswith("*"):
            p = p[:-1]
        if p in (short, long_) and _match(nodes[1:], parts[1:]):
            return True
    return optional and _match(nodes[1:], parts)


def _fmt(v: float) -> str:
    return f"{v:+.14E}"


class SimSignalGenerator:
    """The SCPI instrument; ``handle(line)`` returns the reply or None."""

    def __init__(self, world):
        self.world = world
        self.errors: list[tuple[int, str]] = []
        self.commands = [(_compile(p), q, f) for p, q, f in self._table()]
        self.reset()

    # ---- state --------------------------------------------------------------------------
    def reset(self) -> None:
        self.func = "SIN"
        self.freq = 1000.0
        self.vpp = 0.1
        self.offset = 0.0
        self.output = False
        self.lim_high = 5.0
        self.lim_low = -5.0
        self.lim_state = False
        self.f_start = 100.0
        self.f_stop = 1000.0
        self.sweep_time = 1.0
        self.sweep = False
        self.burst = False
        self.ncycles = 1
        self.trig_source = "IMM"
        self._push(restart=True)

    def _push(self, restart: bool = False) -> None:
        def apply():
            G = self.world.G
            alive = self.world.generator_alive
            G[ph.G_OUT] = 1.0 if (self.output and alive) else 0.0
            G[ph.G_VPP] = self.vpp
            G[ph.G_OFFS] = self.offset
            G[ph.G_FREQ] = self.freq
            G[ph.G_F0] = self.f_start
            G[ph.G_F1] = self.f_stop
            G[ph.G_TSWEEP] = self.sweep_time
            if self.sweep and G[ph.G_SWEEP] == 0.0:
                G[ph.G_TS] = 0.0
            G[ph.G_SWEEP] = 1.0 if self.sweep else 0.0
            if self.burst and G[ph.G_BURST] == 0.0:
                G[ph.G_BURST_ACTIVE] = 0.0
            G[ph.G_BURST] = 1.0 if self.burst else 0.0
            if restart:
                G[ph.G_PHASE] = 0.0
        self.world.apply(apply)

    def power_off(self) -> None:
        """Instrument dies (server killed): output goes to zero."""
        def apply():
            self.world.generator_alive = False
            self.world.G[ph.G_OUT] = 0.0
        self.world.apply(apply)

    def trigger(self) -> None:
        def apply():
            G = self.world.G
            if self.sweep:
                G[ph.G_TS] = 0.0
                G[ph.G_PHASE] = 0.0
            if self.burst:
                G[ph.G_BURST_ACTIVE] = 1.0
                G[ph.G_BURST_LEFT] = 2.0 * 3.141592653589793 * self.ncycles
                G[ph.G_PHASE] = 0.0
            self.world.fire_trigger()
        self.world.apply(apply)

    # ---- protocol -----------------------------------------------------------------------
    def push_error(self, code: int, detail: str = "") -> None:
        if len(self.errors) >= QUEUE_LEN:
            self.errors[-1] = (-350, ERRORS[-350])
            return
        text = ERRORS.get(code, "Error")
        if detail:
            text = f"{text}; {detail}"
        self.errors.append((code, text))

    def handle(self, line: str) -> str | None:
        if not is_printable_ascii(line):
            self.push_error(-101, "a non-ASCII or control byte in the request")
            return None
        replies = []
        for part in line.split(";"):
            part = part.strip()
            if not part:
                continue
            try:
                r = self._one(part)
            except ScpiError as exc:
                self.push_error(exc.code, exc.detail)
                continue
            if r is not None:
                replies.append(r)
        return ";".join(replies) if replies else None

    def _one(self, text: str) -> str | None:
        header, _, arg = text.partition(" ")
        header = header.upper().lstrip(":")
        arg = arg.strip()
        query = header.endswith("?")
        if query:
            header = header[:-1]
        parts = header.split(":") if header else []
        for nodes, is_query, func in self.commands:
            if is_query == query and _match(nodes, parts):
                if query and arg:
                    raise ScpiError(-108, text)
                return func(arg)
        raise ScpiError(-113, text)

    # ---- parameter helpers -------------------------------------------------------------
    @staticmethod
    def _number(arg: str, key: str, units=("",)) -> float:
        lo, hi, default = LIMITS[key]
        if not arg:
            raise ScpiError(-109, key)
        word = arg.upper()
        if word in ("MIN", "MINIMUM"):
            return lo
        if word in ("MAX", "MAXIMUM"):
            return hi
        if word in ("DEF", "DEFAULT") and default is not None:
            return default
        m = _NUM.match(arg)
        if not m:
            raise ScpiError(-104, arg)
        value = float(m.group(1))
        unit = m.group(2).upper()
        if unit:
            if unit not in units:
                raise ScpiError(-104, f"unit {unit} not allowed for {key}")
            value *= _UNITS[unit]
        if not lo <= value <= hi:
            raise ScpiError(-222, f"{key} {value:g} outside {lo:g}..{hi:g}")
        return value

    @staticmethod
    def _bool(arg: str) -> bool:
        word = arg.upper()
        if word in ("ON", "1"):
            return True
        if word in ("OFF", "0"):
            return False
        if not word:
            raise ScpiError(-109, "expected ON|OFF")
        raise ScpiError(-224, f"expected ON|OFF, got {arg}")

    def _check_levels(self, vpp: float, offset: float, high: float, low: float, state: bool) -> None:
        if abs(offset) + vpp / 2 > MAX_OUTPUT + 1e-12:
            raise ScpiError(-221, f"|offset|+Vpp/2 = {abs(offset) + vpp / 2:g} V exceeds {MAX_OUTPUT:g} V")
        if state and (offset + vpp / 2 > high + 1e-12 or offset - vpp / 2 < low - 1e-12):
            raise ScpiError(-221, f"output {offset - vpp / 2:g}..{offset + vpp / 2:g} V outside the "
                                  f"voltage limits {low:g}..{high:g} V")

    # ---- command handlers ----------------------------------------------------------------
    def _table(self):
        return [
            ("*IDN", True, lambda a: IDN),
            ("*RST", False, lambda a: self.reset()),
            ("*CLS", False, lambda a: self.errors.clear()),
            ("*OPC", True, lambda a: "1"),
            ("*OPC", False, lambda a: None),
            ("*WAI", False, lambda a: None),
            ("*TRG", False, lambda a: self.trigger()),
            ("TRIGger[:IMMediate]", False, lambda a: self.trigger()),
            ("TRIGger:SOURce", False, self._set_trig_source),
            ("TRIGger:SOURce", True, lambda a: self.trig_source),
            ("SYSTem:ERRor[:NEXT]", True, self._next_error),
            ("[SOURce:]FUNCtion[:SHAPe]", False, self._set_func),
            ("[SOURce:]FUNCtion[:SHAPe]", True, lambda a: self.func),
            ("[SOURce:]FREQuency:STARt", False, lambda a: self._set("f_start", self._number(a, "FREQ", ("HZ", "KHZ", "MAHZ")))),
            ("[SOURce:]FREQuency:STARt", True, lambda a: _fmt(self.f_start)),
            ("[SOURce:]FREQuency:STOP", False, lambda a: self._set("f_stop", self._number(a, "FREQ", ("HZ", "KHZ", "MAHZ")))),
            ("[SOURce:]FREQuency:STOP", True, lambda a: _fmt(self.f_stop)),
            ("[SOURce:]FREQuency[:CW]", False, lambda a: self._set("freq", self._number(a, "FREQ", ("HZ", "KHZ", "MAHZ")))),
            ("[SOURce:]FREQuency[:CW]", True, lambda a: _fmt(self.freq)),
            ("[SOURce:]VOLTage:UNIT", False, self._set_unit),
            ("[SOURce:]VOLTage:UNIT", True, lambda a: "VPP"),
            ("[SOURce:]VOLTage:LIMit:HIGH", False, lambda a: self._set_limit("high", a)),
            ("[SOURce:]VOLTage:LIMit:HIGH", True, lambda a: _fmt(self.lim_high)),
            ("[SOURce:]VOLTage:LIMit:LOW", False, lambda a: self._set_limit("low", a)),
            ("[SOURce:]VOLTage:LIMit:LOW", True, lambda a: _fmt(self.lim_low)),
            ("[SOURce:]VOLTage:LIMit:STATe", False, self._set_limit_state),
            ("[SOURce:]VOLTage:LIMit:STATe", True, lambda a: "1" if self.lim_state else "0"),
            ("[SOURce:]VOLTage[:LEVel][:IMMediate]:OFFSet", False, self._set_offset),
            ("[SOURce:]VOLTage[:LEVel][:IMMediate]:OFFSet", True, lambda a: _fmt(self.offset)),
            ("[SOURce:]VOLTage[:LEVel][:IMMediate][:AMPLitude]", False, self._set_vpp),
            ("[SOURce:]VOLTage[:LEVel][:IMMediate][:AMPLitude]", True, lambda a: _fmt(self.vpp)),
            ("OUTPut[:STATe]", False, lambda a: self._set("output", self._bool(a))),
            ("OUTPut[:STATe]", True, lambda a: "1" if self.output else "0"),
            ("[SOURce:]SWEep:TIME", False, lambda a: self._set("sweep_time", self._number(a, "SWE:TIME", ("S", "MS")))),
            ("[SOURce:]SWEep:TIME", True, lambda a: _fmt(self.sweep_time)),
            ("[SOURce:]SWEep:SPACing", False, self._set_spacing),
            ("[SOURce:]SWEep:SPACing", True, lambda a: "LIN"),
            ("[SOURce:]SWEep:STATe", False, self._set_sweep),
            ("[SOURce:]SWEep:STATe", True, lambda a: "1" if self.sweep else "0"),
            ("[SOURce:]BURSt:NCYCles", False, self._set_ncycles),
            ("[SOURce:]BURSt:NCYCles", True, lambda a: _fmt(float(self.ncycles))),
            ("[SOURce:]BURSt:MODE", False, self._set_burst_mode),
            ("[SOURce:]BURSt:MODE", True, lambda a: "TRIG"),
            ("[SOURce:]BURSt:STATe", False, self._set_burst),
            ("[SOURce:]BURSt:STATe", True, lambda a: "1" if self.burst else "0"),
        ]

    def _set(self, attr: str, value) -> None:
        setattr(self, attr, value)
        self._push()

    def _next_error(self, arg: str) -> str:
        if not self.errors:
            return '+0,"No error"'
        code, text = self.errors.pop(0)
        return f'{code:+d},"{text}"'

    def _set_func(self, arg: str) -> None:
        word = arg.upper()
        if word in ("SIN", "SINUSOID"):
            self.func = "SIN"
            return
        if not word:
            raise ScpiError(-109, "FUNC")
        raise ScpiError(-224, f"FUNC {arg}: only SIN is available")

    def _set_unit(self, arg: str) -> None:
        if arg.upper() != "VPP":
            raise ScpiError(-224, f"VOLT:UNIT {arg}: only VPP is available")

    def _set_trig_source(self, arg: str) -> None:
        word = arg.upper()
        table = {"IMM": "IMM", "IMMEDIATE": "IMM", "BUS": "BUS", "EXT": "EXT", "EXTERNAL": "EXT"}
        if word not in table:
            raise ScpiError(-224, f"TRIG:SOUR {arg}")
        self.trig_source = table[word]

    def _set_spacing(self, arg: str) -> None:
        if arg.upper() not in ("LIN", "LINEAR"):
            raise ScpiError(-224, f"SWE:SPAC {arg}: only LIN is available")

    def _set_vpp(self, arg: str) -> None:
        vpp = self._number(arg, "VOLT", ("V", "VPP", "MV", "MVPP"))
        self._check_levels(vpp, self.offset, self.lim_high, self.lim_low, self.lim_state)
        self._set("vpp", vpp)

    def _set_offset(self, arg: str) -> None:
        off = self._number(arg, "OFFS", ("V", "MV"))
        self._check_levels(self.vpp, off, self.lim_high, self.lim_low, self.lim_state)
        self._set("offset", off)

    def _set_limit(self, which: str, arg: str) -> None:
        v = self._number(arg, "LIM", ("V", "MV"))
        high = v if which == "high" else self.lim_high
        low = v if which == "low" else self.lim_low
        if low >= high:
            raise ScpiError(-221, f"voltage limit low {low:g} V must be below high {high:g} V")
        self._check_levels(self.vpp, self.offset, high, low, self.lim_state)
        self.lim_high, self.lim_low = high, low

    def _set_limit_state(self, arg: str) -> None:
        state = self._bool(arg)
        self._check_levels(self.vpp, self.offset, self.lim_high, self.lim_low, state)
        self.lim_state = state

    def _set_sweep(self, arg: str) -> None:
        state = self._bool(arg)
        if state and self.burst:
            raise ScpiError(-221, "sweep and burst cannot both be on")
        self._set("sweep", state)

    def _set_burst(self, arg: str) -> None:
        state = self._bool(arg)
        if state and self.sweep:
            raise ScpiError(-221, "sweep and burst cannot both be on")
        self._set("burst", state)

    def _set_burst_mode(self, arg: str) -> None:
        if arg.upper() not in ("TRIG", "TRIGGERED"):
            raise ScpiError(-224, f"BURS:MODE {arg}: only TRIG is available")

    def _set_ncycles(self, arg: str) -> None:
        word = arg.upper()
        if word in ("MIN", "MINIMUM", "MAX", "MAXIMUM"):
            n = self._number(arg, "NCYC")
        else:
            if not re.fullmatch(r"[+]?\d+", arg):
                raise ScpiError(-104, f"BURS:NCYC {arg}: integer expected")
            n = int(arg)
            lo, hi, _ = LIMITS["NCYC"]
            if not lo <= n <= hi:
                raise ScpiError(-222, f"BURS:NCYC {n} outside {lo}..{hi}")
        self._set("ncycles", int(n))

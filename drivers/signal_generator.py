"""Driver for a Keysight 33500B-style function generator over SCPI.

The address is a VISA resource string (``TCPIP0::192.168.1.20::5025::SOCKET``,
``TCPIP0::host::inst0::INSTR``, ``USB0::0x0957::0x2C07::MY1234::INSTR``,
``GPIB0::10::INSTR``; through pyvisa, :mod:`drivers.visa_link`) or a pyserial
URL (``socket://host:port``, a serial device or a pty; :mod:`drivers.line_link`).  Every setting is validated before it
is sent; every write is followed (in the same line) by ``SYST:ERR?`` so an
instrument-side rejection (e.g. a settings conflict with the voltage limits)
raises :class:`InstrumentFault` at once, naming the command.
"""
from __future__ import annotations

import re

from drivers.base import (Instrument, InstrumentError, InstrumentFault, MalformedReply, SettingRangeError,
                          boolean, in_range, int_range, on_off, parse_bool, parse_float)
from drivers.line_link import LineLink
from drivers.visa_link import VisaLink, is_visa_resource

FREQ_RANGE = (1e-6, 30e6)      # Hz (sine)
VPP_RANGE = (1e-3, 10.0)       # Vpp into 50 ohm
OFFSET_RANGE = (-5.0, 5.0)     # V
LIMIT_RANGE = (-5.0, 5.0)      # V
SWEEP_TIME_RANGE = (1e-3, 3600.0)  # s
MAX_CYCLES = 100_000_000
_ERR = re.compile(r'^([+-]?\d+),"(.*)"$')


def _num(v: float) -> str:
    return f"{v:.12g}"


class SignalGenerator(Instrument):
    """One channel of a Keysight 33500B-style generator (sine only)."""

    name = "signal generator"

    def __init__(self, url: str, timeout: float = 1.0, write_term: str = "\n", read_term: str = "\n",
                 visa_library: str = "", **link_options):
        """``url``: a VISA resource string or a pyserial URL; ``visa_library`` applies to the first
        ("": NI/Keysight VISA when installed, else pyvisa-py; "@py"; "@ivi")."""
        self.url = url
        if is_visa_resource(url):
            self.link = VisaLink(self.name, url, timeout=timeout, write_term=write_term, read_term=read_term,
                                 visa_library=visa_library, **link_options)
        else:
            self.link = LineLink(self.name, url, timeout=timeout, write_term=write_term, read_term=read_term,
                                 **link_options)

    # ---- transport primitives used by Setting ------------------------------------------------
    def _query(self, command: str) -> str:
        return self.link.query(command)

    def _write(self, command: str) -> None:
        """Send a command and check the error queue in the same round trip."""
        reply = self.link.query(f"{command};:SYST:ERR?")
        code, text = self._parse_error(command, reply)
        if code != 0:
            more = self.check_errors()
            detail = f"{code:+d},\"{text}\"" + (f" (and {'; '.join(more)})" if more else "")
            raise InstrumentFault(self.name, command, f"rejected by the instrument: {detail}")

    def _parse_error(self, command: str, reply: str) -> tuple[int, str]:
        m = _ERR.match(reply.strip())
        if not m:
            raise MalformedReply(self.name, command, f"expected an error-queue entry, got {reply!r}")
        return int(m.group(1)), m.group(2)

    # ---- settings ------------------------------------------------------------------------------
    frequency = Instrument.control("FREQ?", "FREQ {}", "Output frequency [Hz].",
                                   in_range(*FREQ_RANGE, " Hz"), fmt=_num)
    amplitude = Instrument.control("VOLT?", "VOLT {}", "Output amplitude [Vpp] (into the configured load).",
                                   in_range(*VPP_RANGE, " Vpp"), fmt=_num)
    offset = Instrument.control("VOLT:OFFS?", "VOLT:OFFS {}", "DC offset [V].",
                                in_range(*OFFSET_RANGE, " V"), fmt=_num)
    output = Instrument.control("OUTP?", "OUTP {}", "Output relay on/off.", boolean, parse=parse_bool, fmt=on_off)
    sweep_enabled = Instrument.control("SWE:STAT?", "SWE:STAT {}", "Linear frequency sweep on/off.", boolean,
                                       parse=parse_bool, fmt=on_off)
    burst_enabled = Instrument.control("BURS:STAT?", "BURS:STAT {}", "Triggered burst mode on/off.", boolean,
                                       parse=parse_bool, fmt=on_off)
    voltage_limits_enabled = Instrument.control("VOLT:LIM:STAT?", "VOLT:LIM:STAT {}",
                                                "Output voltage limits active.", boolean, parse=parse_bool,
                                                fmt=on_off)

    @property
    def voltage_limits(self) -> tuple[float, float]:
        """(low, high) output voltage limits [V]."""
        low = self._float("VOLT:LIM:LOW?")
        high = self._float("VOLT:LIM:HIGH?")
        return low, high

    def _float(self, command: str) -> float:
        return parse_float(self.name, command, self._query(command))

    # ---- methods -----------------------------------------------------------------------------------
    def identify(self) -> str:
        reply = self._query("*IDN?")
        if reply.count(",") != 3:
            raise MalformedReply(self.name, "*IDN?", f"expected 'maker,model,serial,firmware', got {reply!r}")
        return reply

    def reset(self) -> None:
        """*RST and *CLS: factory settings, output off, empty error queue."""
        reply = self._query("*RST;*CLS;*OPC?")
        if reply.strip() != "1":
            raise MalformedReply(self.name, "*RST;*CLS;*OPC?", f"expected '1', got {reply!r}")

    def check_errors(self) -> list[str]:
        """Drain the instrument's error queue; [] when there is no error."""
        errors = []
        for _ in range(64):
            code, text = self._parse_error("SYST:ERR?", self._query("SYST:ERR?"))
            if code == 0:
                return errors
            errors.append(f"{code:+d},\"{text}\"")
        raise InstrumentFault(self.name, "SYST:ERR?", f"error queue does not empty: {errors[:3]}...")

    def set_voltage_limits(self, low: float, high: float) -> None:
        """Set and enable the output voltage limits; the current settings must fit inside."""
        low = in_range(*LIMIT_RANGE, " V")(self.name, "VOLT:LIM:LOW", low)
        high = in_range(*LIMIT_RANGE, " V")(self.name, "VOLT:LIM:HIGH", high)
        if not low < high:
            raise SettingRangeError(self.name, "set_voltage_limits", f"low {low:g} V must be below high {high:g} V")
        self._write(f"VOLT:LIM:STAT OFF;:VOLT:LIM:HIGH {_num(LIMIT_RANGE[1])};:VOLT:LIM:LOW {_num(low)};"
                    f":VOLT:LIM:HIGH {_num(high)};:VOLT:LIM:STAT ON")

    def configure_sweep(self, start_hz: float, stop_hz: float, duration_s: float) -> None:
        """Linear sweep from start_hz to stop_hz in duration_s (enable with sweep_enabled)."""
        start = in_range(*FREQ_RANGE, " Hz")(self.name, "FREQ:STAR", start_hz)
        stop = in_range(*FREQ_RANGE, " Hz")(self.name, "FREQ:STOP", stop_hz)
        duration = in_range(*SWEEP_TIME_RANGE, " s")(self.name, "SWE:TIME", duration_s)
        self._write(f"SWE:SPAC LIN;:FREQ:STAR {_num(start)};:FREQ:STOP {_num(stop)};:SWE:TIME {_num(duration)}")

    def configure_burst(self, n_cycles: int, enable: bool = True) -> None:
        """Triggered burst of n_cycles sine cycles per trigger()."""
        n = int_range(1, MAX_CYCLES)(self.name, "BURS:NCYC", n_cycles)
        boolean(self.name, "BURS:STAT", enable)
        self._write(f"BURS:MODE TRIG;:TRIG:SOUR BUS;:BURS:NCYC {n};:BURS:STAT {'ON' if enable else 'OFF'}")

    def trigger(self) -> None:
        """*TRG: fires a burst / restarts a sweep and pulses the trigger output (the common
        trigger line of the displacement sensors).  Returns once the instrument has done it."""
        reply = self._query("*TRG;*OPC?")
        if reply.strip() != "1":
            raise MalformedReply(self.name, "*TRG;*OPC?", f"expected '1', got {reply!r}")

    def safe_state(self) -> None:
        """Output off (raises InstrumentError if the instrument cannot confirm it)."""
        self._write("OUTP OFF")
        if self.output:
            raise InstrumentFault(self.name, "OUTP OFF", "output still reports ON")

    def close(self) -> None:
        if isinstance(self.link, VisaLink):
            self.link.close_library()
        else:
            self.link.close()


__all__ = ["SignalGenerator", "InstrumentError"]

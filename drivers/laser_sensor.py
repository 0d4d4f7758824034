"""Driver for a laser displacement sensor controller (ASCII protocol, Keyence LK-G style).

Readings travel in millimetres (mm/s in velocity mode); this driver speaks
metres (m/s).  The controller's measuring mode is a declared setting,
:attr:`LaserSensor.quantity` (``"displacement"`` or ``"velocity"``, the
``MD`` command, like a vibrometer's decoder setting); every reading, block and
range is in that quantity's unit.  Buffered
acquisition is armed with :meth:`LaserSensor.arm` and starts at the next pulse
of the common trigger line (the signal generator's ``*TRG``), so two sensors
armed before one trigger share a time base: ``SensorBlock.index0`` counts
samples since that trigger on both.  See docs/protocols.md.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.base import (Instrument, InstrumentError, InstrumentFault, MalformedReply, int_range, one_of,
                          parse_float)
from drivers.line_link import LineLink

RATES = (1000, 2000, 5000, 10000, 20000, 50000)
QUANTITIES = ("displacement", "velocity")  # MD,0 / MD,1
UNITS = {"displacement": "m", "velocity": "m/s"}
MAX_PER_REPLY = 100_000
MAX_ARM = 1_000_000_000
FLAG_OUT_OF_RANGE = 1
FLAG_SIGNAL_LOSS = 2
ERROR_CODES = {"00": "unknown command", "20": "bad or missing parameter", "22": "value out of range",
               "30": "not allowed in the current state"}
_SPECIAL = {"+FFFFFFF": (np.nan, FLAG_OUT_OF_RANGE), "-FFFFFFF": (np.nan, FLAG_OUT_OF_RANGE),
            "XXXXXXXX": (np.nan, FLAG_SIGNAL_LOSS)}


class OutOfRange(InstrumentError):
    """The target is outside the measuring range."""


class SignalLoss(InstrumentError):
    """The sensor receives no usable reflected light."""


@dataclass
class SensorBlock:
    """Consecutive samples: ``values[j]`` is sample ``index0 + j`` since the trigger [m, or m/s in
    velocity mode]."""

    index0: int
    values: np.ndarray
    flags: np.ndarray

    def __len__(self) -> int:
        return int(self.values.size)


class LaserSensor(Instrument):
    name = "laser sensor"

    def __init__(self, url: str, timeout: float = 1.0, name: str | None = None, write_term: str = "\r",
                 read_term: str = "\r", **link_options):
        if name:
            self.name = f"laser sensor {name}"
        self.url = url
        self.link = LineLink(self.name, url, timeout=timeout, write_term=write_term, read_term=read_term,
                             **link_options)
        self._pending: list[SensorBlock] = []
        self._last_end = 0

    # ---- protocol primitives ------------------------------------------------------------------
    def _query(self, command: str) -> str:
        reply = self.link.query(command)
        head = command.split(",")[0]
        if reply.startswith("ER,"):
            parts = reply.split(",")
            code = parts[2] if len(parts) > 2 else "?"
            raise InstrumentFault(self.name, command,
                                  f"error {code}: {ERROR_CODES.get(code, 'unknown error code')}")
        if reply != head and not reply.startswith(head + ","):
            raise MalformedReply(self.name, command, f"unexpected reply {reply[:80]!r}")
        return reply

    def _field(self, command: str) -> str:
        reply = self._query(command)
        return reply.split(",", 1)[1] if "," in reply else ""

    def _write(self, command: str) -> None:
        self._query(command)

    # ---- settings -----------------------------------------------------------------------------
    sampling_rate = Instrument.control(lambda s: float(s._int_field("SS")), "SS,{}",
                                       "Sampling rate [Hz], one of 1, 2, 5, 10, 20, 50 kHz (the controller "
                                       "may refuse rates it cannot do).", one_of(RATES), fmt=lambda v: str(int(v)))

    measuring_range = Instrument.measurement(lambda s: s._float_field("RG") * 1e-3,
                                             "Half measuring range [m] (readings span +-range about the "
                                             "reference distance).")

    quantity = Instrument.control(lambda s: s._quantity(), "MD,{}",
                                  "What the readings measure: 'displacement' [m] or 'velocity' [m/s] (the "
                                  "controller's measuring mode; refused while acquiring).",
                                  one_of(QUANTITIES), fmt=lambda v: str(QUANTITIES.index(v)))

    velocity_range = Instrument.measurement(lambda s: s._float_field("VR") * 1e-3,
                                            "Half measuring range in velocity mode [m/s] (readings span "
                                            "+-range).")

    def _quantity(self) -> str:
        code = self._int_field("MD")
        if code >= len(QUANTITIES):
            raise MalformedReply(self.name, "MD", f"unknown measuring mode {code}")
        return QUANTITIES[code]

    def _int_field(self, command: str) -> int:
        text = self._field(command)
        if not text.isdigit():
            raise MalformedReply(self.name, command, f"expected an integer, got {text!r}")
        return int(text)

    def _float_field(self, command: str) -> float:
        return parse_float(self.name, command, self._field(command))

    # ---- methods ---------------------------------------------------------------------------------
    def identify(self) -> str:
        return self._field("ID")

    def read(self) -> float:
        """One reading now [m, or m/s in velocity mode]; raises OutOfRange or SignalLoss."""
        text = self._field("M0")
        if text in ("+FFFFFFF", "-FFFFFFF"):
            raise OutOfRange(self.name, "M0", f"target outside the measuring range ({text[0]})")
        if text == "XXXXXXXX":
            raise SignalLoss(self.name, "M0", "no reflected light (signal loss)")
        try:
            return float(text) * 1e-3
        except ValueError:
            raise MalformedReply(self.name, "M0", f"expected a reading, got {text!r}") from None

    def arm(self, n_samples: int | None = None) -> None:
        """Arm buffered acquisition from the next common trigger: n_samples, or continuous
        (ring buffer, read with fetch) when None."""
        n = 0 if n_samples is None else int_range(1, MAX_ARM)(self.name, "arm", n_samples)
        self._pending.clear()
        self._last_end = 0
        self._write(f"AS,{n}")

    def stop(self) -> None:
        self._write("AQ")

    def status(self) -> tuple[str, int, int]:
        """(state, samples acquired, samples fetched); state IDLE|ARMED|RUNNING|DONE."""
        parts = self._query("ST").split(",")
        if len(parts) != 4 or not parts[2].isdigit() or not parts[3].isdigit():
            raise MalformedReply(self.name, "ST", f"unexpected status {','.join(parts)!r}")
        return parts[1], int(parts[2]), int(parts[3])

    def fetch(self, max_samples: int | None = None) -> SensorBlock:
        """All new samples since the last fetch (at most max_samples).

        In a lock-stepped simulation a fetch is what advances time: with
        max_samples the world advances until that many samples exist (or the
        armed count is reached); without, by one block when nothing new exists."""
        if max_samples is not None:
            max_samples = int_range(1, MAX_ARM)(self.name, "fetch", max_samples)
        blocks: list[SensorBlock] = []
        got = 0
        while self._pending and (max_samples is None or got < max_samples):
            b = self._pending.pop(0)
            if max_samples is not None and got + len(b) > max_samples:
                keep = max_samples - got
                self._pending.insert(0, SensorBlock(b.index0 + keep, b.values[keep:], b.flags[keep:]))
                b = SensorBlock(b.index0, b.values[:keep], b.flags[:keep])
            blocks.append(b)
            got += len(b)
        while max_samples is None or got < max_samples:
            ask = MAX_PER_REPLY if max_samples is None else min(MAX_PER_REPLY, max_samples - got)
            command = "AO" if max_samples is None else f"AO,{ask}"
            block = self._parse_block(command, self._query(command))
            if len(block):
                blocks.append(block)
                got += len(block)
            if len(block) < ask:  # the controller has no more right now
                break
        return self._join(blocks)

    def _join(self, blocks: list[SensorBlock]) -> SensorBlock:
        if not blocks:
            return SensorBlock(self._last_end, np.empty(0), np.empty(0, dtype=np.uint8))
        out = [blocks[0]]
        for b in blocks[1:]:
            if b.index0 != out[-1].index0 + len(out[-1]) or self._pending:
                self._pending.append(b)  # a gap (lost samples): deliver it with the next fetch
            else:
                out.append(b)
        values = np.concatenate([b.values for b in out])
        flags = np.concatenate([b.flags for b in out])
        self._last_end = out[0].index0 + values.size
        return SensorBlock(out[0].index0, values, flags)

    def _parse_block(self, command: str, reply: str) -> SensorBlock:
        parts = reply.split(",")
        if len(parts) < 3 or not parts[1].isdigit() or not parts[2].isdigit():
            raise MalformedReply(self.name, command, f"bad block header {reply[:60]!r}")
        index0, n = int(parts[1]), int(parts[2])
        tokens = parts[3:]
        if len(tokens) != n:
            raise MalformedReply(self.name, command, f"header says {n} samples, reply holds {len(tokens)}")
        flags = np.zeros(n, dtype=np.uint8)
        try:
            values = np.array(tokens, dtype=float) * 1e-3
        except ValueError:
            values = np.empty(n)
            for j, tok in enumerate(tokens):
                special = _SPECIAL.get(tok)
                if special is not None:
                    values[j], flags[j] = special
                    continue
                try:
                    values[j] = float(tok) * 1e-3
                except ValueError:
                    raise MalformedReply(self.name, command, f"sample {index0 + j}: bad value {tok!r}") from None
        return SensorBlock(index0, values, flags)

    def check_errors(self) -> list[str]:
        """Alarms since the last call: 'buffer overflow', 'signal loss'; [] when healthy."""
        text = self._field("EQ")
        if not text.isdigit():
            raise MalformedReply(self.name, "EQ", f"expected alarm bits, got {text!r}")
        bits = int(text)
        names = []
        if bits & 1:
            names.append("buffer overflow")
        if bits & 2:
            names.append("signal loss")
        return names

    def close(self) -> None:
        self.link.close()

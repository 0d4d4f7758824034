"""Common ground of the instrument drivers: errors, strict validators, the :class:`Instrument`
base and the declarative properties.

A driver reads like the instrument's manual (the PyMeasure idea): each setting
is a class attribute declared with :meth:`Instrument.control` /
:meth:`Instrument.measurement` (a text command that reads it, one that writes
it) or :class:`Register` (a Modbus holding register, its scale and range), with
a validator that rejects out-of-range values *before* anything is sent (values
are never clipped).  Every error is an :class:`InstrumentError` whose message
names the instrument and the command.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any


class InstrumentError(Exception):
    """An instrument did not do what was asked.  ``instrument`` and ``command`` say where."""

    def __init__(self, instrument: str, command: str, message: str):
        self.instrument = instrument
        self.command = command
        self.detail = message
        super().__init__(f"{instrument}: {command}: {message}")


class InstrumentTimeout(InstrumentError):
    """No (complete) reply within the timeout."""


class InstrumentFault(InstrumentError):
    """The instrument reported an error or a fault condition."""


class InstrumentConnectionError(InstrumentError):
    """The transport is closed, refused or lost."""


class MalformedReply(InstrumentError):
    """A reply arrived but does not follow the protocol."""


class SettingRangeError(InstrumentError, ValueError):
    """A setpoint outside the instrument's range; nothing was sent."""


# ---- validators: (instrument, command, value) -> validated value --------------------------------
Validator = Callable[[str, str, Any], Any]


def _number(instrument: str, command: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SettingRangeError(instrument, command, f"expected a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise SettingRangeError(instrument, command, f"expected a finite number, got {value!r}")
    return value


def in_range(low: float, high: float, unit: str = "") -> Validator:
    """A float within [low, high]; outside raises SettingRangeError."""
    def check(instrument: str, command: str, value: Any) -> float:
        v = _number(instrument, command, value)
        if not low <= v <= high:
            raise SettingRangeError(instrument, command,
                                    f"{v:g}{unit} is outside the allowed range {low:g}..{high:g}{unit}")
        return v
    check.bounds = (low, high)
    return check


def int_range(low: int, high: int) -> Validator:
    def check(instrument: str, command: str, value: Any) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise SettingRangeError(instrument, command, f"expected an integer, got {value!r}")
        if not low <= value <= high:
            raise SettingRangeError(instrument, command, f"{value} is outside {low}..{high}")
        return value
    return check


def one_of(choices: Iterable[Any]) -> Validator:
    allowed = tuple(choices)

    def check(instrument: str, command: str, value: Any) -> Any:
        if isinstance(value, bool) or value not in allowed:
            raise SettingRangeError(instrument, command, f"{value!r} is not one of {allowed}")
        return value
    return check


def boolean(instrument: str, command: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise SettingRangeError(instrument, command, f"expected True or False, got {value!r}")
    return value


class Setting:
    """A validated instrument property.

    ``get``: a command string sent with ``instrument._query`` (the reply parsed by
    ``parse``) or a callable ``get(instrument)``.  ``set``: a format string
    (``"FREQ {}"``; the validated value formatted by ``fmt``) sent with
    ``instrument._write``, or a callable ``set(instrument, value)``; None makes
    the property read-only.
    """

    def __init__(self, get, set=None, validator: Validator | None = None,
                 parse: Callable[[str], Any] = float, fmt: Callable[[Any], str] = repr,
                 doc: str = ""):
        self.get = get
        self.set = set
        self.validator = validator
        self.parse = parse
        self.fmt = fmt
        self.__doc__ = doc
        self.name = "?"

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, inst, owner=None):
        if inst is None:
            return self
        if callable(self.get):
            return self.get(inst)
        reply = inst._query(self.get)
        try:
            return self.parse(reply)
        except (ValueError, TypeError, KeyError):
            raise MalformedReply(inst.name, self.get, f"cannot read {self.name} from reply {reply!r}") from None

    def __set__(self, inst, value):
        command = self.set if isinstance(self.set, str) else self.name
        if self.set is None:
            raise AttributeError(f"{inst.name}: {self.name} is read-only")
        if self.validator is not None:
            value = self.validator(inst.name, f"{self.name} = {value!r}", value)
        if callable(self.set):
            self.set(inst, value)
        else:
            inst._write(command.format(self.fmt(value)))


def on_off(value: bool) -> str:
    """SCPI boolean argument."""
    return "ON" if value else "OFF"


class Register:
    """One Modbus holding register as a validated property: ``value = raw / scale``.

    ``signed`` reads the 16-bit word as int16; ``kind=bool`` maps 0/1.  Before a
    write, ``validator`` checks the value, or ``bounds(instrument) -> (low, high)``
    for a range the device itself reports (e.g. MAX_GAIN); nothing is sent when
    it fails.  ``writable=False``: read only.  ``cached``: a device constant,
    read once per driver.  The instrument provides ``_read(address, count,
    label)`` and ``_write_register(address, raw, label)``.
    """

    def __init__(self, address: int, label: str, doc: str = "", *, scale: float = 1, signed: bool = False,
                 kind: type = float, writable: bool = True, validator: Validator | None = None,
                 bounds: Callable[[Any], tuple[float, float]] | None = None, unit: str = "",
                 cached: bool = False):
        self.address = address
        self.label = label
        self.scale = scale
        self.signed = signed
        self.kind = kind
        self.writable = writable
        self.validator = boolean if kind is bool and validator is None else validator
        self.bounds = bounds
        self.unit = unit
        self.cached = cached
        self.__doc__ = doc
        self.name = label.lower()

    def __set_name__(self, owner, name):
        self.name = name

    def decode(self, raw: int):
        if self.kind is bool:
            return bool(raw)
        if self.signed and raw >= 0x8000:
            raw -= 0x10000
        return raw if self.kind is int else raw / self.scale

    def __get__(self, inst, owner=None):
        if inst is None:
            return self
        cache = inst.__dict__.setdefault("_register_cache", {})
        if self.cached and self.address in cache:
            return cache[self.address]
        value = self.decode(inst._read(self.address, 1, self.label)[0])
        if self.cached:
            cache[self.address] = value
        return value

    def __set__(self, inst, value):
        if not self.writable:
            raise AttributeError(f"{inst.name}: {self.name} is read-only (register {self.label})")
        if self.validator is not None:
            value = self.validator(inst.name, self.name, value)
        if self.bounds is not None:
            value = in_range(*self.bounds(inst), self.unit)(inst.name, self.name, value)
        raw = int(value) if self.kind is bool else int(round(value * self.scale))
        inst._write_register(self.address, raw, self.label)


class Instrument:
    """Base of every driver: a name for its messages, ``close()`` and the context manager.

    Text-protocol drivers implement ``_query(command) -> reply`` and
    ``_write(command)``, which the properties made by :meth:`control` and
    :meth:`measurement` use.
    """

    name = "instrument"

    @staticmethod
    def control(get, set, doc: str, validator: Validator | None = None, parse: Callable[[str], Any] = float,
                fmt: Callable[[Any], str] = repr) -> Setting:
        """A read/write setting: query ``get``, write ``set`` (a format string) after ``validator``."""
        return Setting(get, set, validator, parse=parse, fmt=fmt, doc=doc)

    @staticmethod
    def measurement(get, doc: str, parse: Callable[[str], Any] = float) -> Setting:
        """A read-only value."""
        return Setting(get, None, parse=parse, doc=doc)

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def parse_bool(reply: str) -> bool:
    text = reply.strip().upper()
    if text in ("1", "ON"):
        return True
    if text in ("0", "OFF"):
        return False
    raise ValueError(reply)


def parse_float(instrument: str, command: str, reply: str) -> float:
    """A numeric reply, or :class:`MalformedReply` naming the instrument and the command."""
    try:
        return float(reply)
    except ValueError:
        raise MalformedReply(instrument, command, f"expected a number, got {reply!r}") from None

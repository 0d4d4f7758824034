"""Common ground of the instrument drivers: errors, strict validators and a property helper.

A driver reads like the instrument's manual: each setting is a class attribute
declared with :class:`Setting`, naming the command that reads it, the command
that writes it and a validator that rejects out-of-range values *before*
anything is sent (values are never clipped).  Every error is an
:class:`InstrumentError` whose message names the instrument and the command.
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

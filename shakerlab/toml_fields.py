"""Reading user TOML files (rig config, protocol, simulator config) against a declared schema.

The one checker of every TOML file the user writes: ``rig.config``,
``rig.protocol`` and ``sim_backend.config`` declare their schemas with
:class:`Field` and call :func:`validate`.

A schema is a dict ``{key: Field | dict}`` (a nested dict is a sub-table).
:func:`load_toml` parses a file and :func:`validate` checks a table: unknown
keys, missing required keys, wrong types and out-of-range values raise
:class:`~shakerlab.errors.UserFacingError` whose message names the file and
the field (``rig.toml: [limits] max_generator_vpp: expected a number > 0,
got -1``).
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shakerlab.errors import UserFacingError

REQUIRED = object()


@dataclass(frozen=True)
class Field:
    """One TOML value: its kind, default, bounds and a one-line description."""

    kind: str  # "number", "int", "str", "bool", "list_number"
    default: Any = REQUIRED
    min: float | None = None
    max: float | None = None
    min_exclusive: bool = False
    choices: tuple | None = None
    help: str = ""

    def describe(self) -> str:
        what = {"number": "a number", "int": "an integer", "str": "a string", "bool": "true or false",
                "list_number": "a list of numbers"}[self.kind]
        if self.choices:
            what = "one of " + ", ".join(f"{c:g}" if isinstance(c, (int, float)) else repr(c)
                                          for c in self.choices)
        bounds = []
        if self.min is not None:
            bounds.append(f"{'>' if self.min_exclusive else '>='} {self.min:g}")
        if self.max is not None:
            bounds.append(f"<= {self.max:g}")
        return what + (" " + " and ".join(bounds) if bounds else "")


def load_toml(path: str | Path, what: str) -> tuple[dict, str]:
    """Parse a TOML file; return (data, text). Errors name the file (and line, from tomllib)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserFacingError(f"{what} file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserFacingError(f"{what} file {path}: cannot read it ({exc})") from None
    try:
        return tomllib.loads(text), text
    except tomllib.TOMLDecodeError as exc:
        raise UserFacingError(f"{path}: not valid TOML: {exc}") from None


def _check_value(field: Field, value, where: str):
    def bad():
        return UserFacingError(f"{where}: expected {field.describe()}, got {value!r}")

    if field.kind in ("number", "int"):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad()
        if field.kind == "int" and not isinstance(value, int):
            raise bad()
        if not math.isfinite(value):
            raise bad()
        if field.min is not None and (value < field.min or (field.min_exclusive and value == field.min)):
            raise bad()
        if field.max is not None and value > field.max:
            raise bad()
        if field.choices and value not in field.choices:
            raise bad()
        return float(value) if field.kind == "number" else int(value)
    if field.kind == "list_number":
        if not isinstance(value, list) or not value:
            raise bad()
        inner = Field("number", min=field.min, max=field.max, min_exclusive=field.min_exclusive)
        return [_check_value(inner, v, f"{where}[{i}]") for i, v in enumerate(value)]
    if field.kind == "str":
        if not isinstance(value, str) or (field.choices and value not in field.choices):
            raise bad()
        return value
    if field.kind == "bool":
        if not isinstance(value, bool):
            raise bad()
        return value
    raise AssertionError(field.kind)


def validate(data: dict, schema: dict, source: str, table: str = "") -> dict:
    """Return ``data`` checked against ``schema`` with defaults filled in."""
    label = f"[{table}] " if table else ""
    if not isinstance(data, dict):
        raise UserFacingError(f"{source}: {label.strip() or 'top level'} must be a table")
    unknown = [k for k in data if k not in schema]
    if unknown:
        raise UserFacingError(
            f"{source}: {label}unknown field {unknown[0]!r} (known: {', '.join(schema)})"
        )
    out = {}
    for key, spec in schema.items():
        where = f"{source}: {label}{key}"
        sub = f"{table}.{key}" if table else key
        if isinstance(spec, dict):
            out[key] = validate(data.get(key, {}), spec, source, sub)
            continue
        if key not in data or (data[key] is None and spec.default is None):
            if spec.default is REQUIRED:
                raise UserFacingError(f"{where}: missing (expected {spec.describe()})")
            out[key] = spec.default
            continue
        out[key] = _check_value(spec, data[key], where)
    return out


def schema_doc(schema: dict, table: str = "") -> list[tuple[str, str, str]]:
    """(field, expected/default, help) rows for documentation and tests."""
    rows = []
    for key, spec in schema.items():
        name = f"{table}.{key}" if table else key
        if isinstance(spec, dict):
            rows += schema_doc(spec, name)
        else:
            default = ("required" if spec.default is REQUIRED else "optional" if spec.default is None
                       else f"default {spec.default!r}")
            rows.append((name, f"{spec.describe()}; {default}", spec.help))
    return rows

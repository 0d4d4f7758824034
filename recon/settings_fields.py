"""Settings fields that say what they are: a default, a one-line meaning, a unit and a range.

The estimator's (recon.estimator.tuning) and the diagnosis's (recon.diagnosis.settings) tuned
numbers are fields of frozen dataclasses made with :func:`bounded`; :func:`check` refuses a
value outside its range, naming the field, its meaning and unit; :func:`describe` lists them for
docs and reports.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import field

__all__ = ["bounded", "check", "describe"]


def bounded(default, meaning: str, unit: str, lo: float, hi: float, lo_open: bool = False):
    """A field with its meaning, unit and range [lo, hi] (``lo_open``: (lo, hi])."""
    return field(default=default, metadata={"meaning": meaning, "unit": unit, "range": (lo, hi),
                                            "lo_open": lo_open})


def check(obj) -> None:
    """Raise ValueError naming the first field of ``obj`` outside its range (a tuple field: each of
    its values, and at least one)."""
    for f in dataclasses.fields(obj):
        if "range" not in f.metadata:
            continue
        v = getattr(obj, f.name)
        values = v if isinstance(v, tuple) else (v,)
        if not values:
            raise ValueError(f"{type(obj).__name__}.{f.name} needs at least one value ({f.metadata['meaning']})")
        for x in values:
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise ValueError(f"{type(obj).__name__}.{f.name} must be finite numbers ({f.metadata['meaning']}), "
                                 f"not {v!r}")
            lo, hi = f.metadata["range"]
            below = x <= lo if f.metadata["lo_open"] else x < lo
            if below or x > hi:
                left = "(" if f.metadata["lo_open"] else "["
                raise ValueError(f"{type(obj).__name__}.{f.name} = {v!r} is outside {left}{lo:g}, {hi:g}] "
                                 f"({f.metadata['meaning']}, {f.metadata['unit']})")


def describe(obj) -> list[dict]:
    """Each field of a settings object: name, value, meaning, unit, range (for docs and reports)."""
    out = []
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            out += [{**d, "name": f"{f.name}.{d['name']}"} for d in describe(v)]
        elif "range" in f.metadata:
            out.append({"name": f.name, "value": v, "meaning": f.metadata["meaning"], "unit": f.metadata["unit"],
                        "range": list(f.metadata["range"])})
    return out

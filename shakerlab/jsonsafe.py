"""The one JSON cleaner: numpy scalars and arrays, paths and tuples to plain JSON values."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def clean(value, nan_to_none: bool = True):
    """A JSON-safe copy of ``value``: numpy scalars and arrays to Python numbers and lists,
    tuples to lists, paths to strings, dict keys to strings. With ``nan_to_none`` (the
    default) NaN and infinities become ``None`` (strict JSON); without it they stay floats
    (HDF5 attributes take them, JSON ``null`` they do not)."""
    if isinstance(value, dict):
        return {str(k): clean(v, nan_to_none) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v, nan_to_none) for v in value]
    if isinstance(value, np.ndarray):
        return clean(value.tolist(), nan_to_none)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return None if nan_to_none and not math.isfinite(v) else v
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value

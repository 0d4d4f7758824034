"""One channel read from a file, with its time base."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Signal:
    """A channel: ``values`` on ``time`` (an explicit time column) or on ``t0 + i * dt``.

    ``quantum``: the printed precision of each time value (CSV), 0 for binary times.
    ``where``: how to name sample ``i`` in a message (``line 12`` / ``sample 11``)."""

    name: str
    values: np.ndarray
    source: str
    time: np.ndarray | None = None
    t0: float = 0.0
    dt: float | None = None
    quantum: np.ndarray | None = None
    lines: np.ndarray | None = None
    quantity: str | None = None        # declared by the file (UFF ordinate type), if any

    def where(self, i: int) -> str:
        return f"line {int(self.lines[i])}" if self.lines is not None else f"sample {i}"

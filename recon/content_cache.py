"""A memo for pure functions of sampled signals, keyed by the signals' content.

The same stage's channels pass through the spectral noise estimate and the Savitzky-Golay
window choice many times in one run (every polish asks for its stage's noise floor, every
filter for its window). Keying by the bytes of the arrays, not by the array objects, makes the
memo safe whoever owns or changes an array: a changed array has another key. Hashing costs
about a millisecond per megabyte, a small part of what the spectrum or the window choice costs.

Results are shared between callers: a cached value must not be changed in place (its arrays
are made read-only by the functions that store them).
"""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np

# entries kept: enough for every channel of every stage of a run and of its held-out pieces,
# not a tuned choice (a miss only costs the computation)
CAPACITY = 256


def digest(x: np.ndarray) -> tuple:
    """A key for an array's content: (dtype, shape, 128-bit BLAKE2b of its bytes)."""
    a = np.ascontiguousarray(x)
    return a.dtype.str, a.shape, hashlib.blake2b(a.view(np.uint8).reshape(-1), digest_size=16).digest()


class ContentCache:
    """A bounded least-recently-used map, safe under threads."""

    def __init__(self, capacity: int = CAPACITY):
        if not (isinstance(capacity, int) and capacity > 0):
            raise ValueError(f"ContentCache capacity must be a positive integer, got {capacity!r}")
        self.capacity = capacity
        self._data: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def get(self, key):
        with self._lock:
            if key in self._data:
                self._data.move_to_end(key)
                self.hits += 1
                return self._data[key]
            self.misses += 1
            return None

    def put(self, key, value) -> None:
        with self._lock:
            self._data[key] = value
            self._data.move_to_end(key)
            while len(self._data) > self.capacity:
                self._data.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._data.clear()
            self.hits = self.misses = 0

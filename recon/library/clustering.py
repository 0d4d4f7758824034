"""Kernel clustering of the samples by the quadrant of (y, y').

h = sgn(sgn(y) + sgn(y')):  +1 on AB (y >= 0, y' >= 0, not both zero), -1 on CD
(y <= 0, y' <= 0), 0 on BC/DA where y and y' have opposite signs (there z
changes sign and the sign trick of the agent model does not apply).
"""
from __future__ import annotations

import numpy as np


def cluster(y: np.ndarray, dy: np.ndarray) -> np.ndarray:
    return np.sign(np.sign(y) + np.sign(dy)).astype(np.int8)

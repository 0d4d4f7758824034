"""Monomials y^p * y'^r and their names ("y^2", "y*dy", "y^2*dy", "dy^3", ...)."""
from __future__ import annotations

import re
from functools import lru_cache

import numpy as np

from shakerlab.errors import UserFacingError


def name(p: int, r: int) -> str:
    parts = []
    if p:
        parts.append("y" if p == 1 else f"y^{p}")
    if r:
        parts.append("dy" if r == 1 else f"dy^{r}")
    return "*".join(parts) if parts else "1"


_TERM = re.compile(r"^(y|dy)(?:\^(\d+))?$")


def parse(text: str) -> tuple[int, int]:
    """Inverse of :func:`name`: "y^2*dy" -> (2, 1)."""
    return _parse(str(text))


@lru_cache(maxsize=4096)
def _parse(text: str) -> tuple[int, int]:
    """:func:`parse`, read once per name (every simulation of a model reads its term names)."""
    p = r = 0
    for part in text.replace(" ", "").split("*"):
        m = _TERM.match(part)
        if not m:
            raise UserFacingError(f"monomial {text!r}: cannot read factor {part!r} (expected y, y^P, dy, dy^R)")
        e = int(m.group(2) or 1)
        if m.group(1) == "y":
            p += e
        else:
            r += e
    return p, r


def exponents(names) -> tuple:
    """Exponent arrays (p, r) (int64) of the monomials ``names``, for the numba simulators."""
    pr = np.array([parse(str(k)) for k in names], dtype=np.int64).reshape(-1, 2)
    return pr[:, 0].copy(), pr[:, 1].copy()


def of_degree(m: int) -> list[tuple[int, int]]:
    """All (p, r) with p + r = m, pure y first: y^m, y^(m-1) dy, ..., dy^m."""
    return [(m - i, i) for i in range(m + 1)]


def up_to(q: int, low: int = 2) -> list[tuple[int, int]]:
    return [pr for m in range(low, q + 1) for pr in of_degree(m)]

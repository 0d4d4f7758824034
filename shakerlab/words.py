"""One vocabulary for every figure a person reads: the command line, the HTML report, the demo,
the batch table and the operator window all format through these functions, so one figure reads
the same everywhere. Machine-readable outputs (JSON, CSV) keep full precision."""
from __future__ import annotations

import math
import re


def nrmse_text(v) -> str:
    """An NRMSE for a person: percent with 3 significant digits ("0.0467 %", "12.3 %"); "diverged"
    for a simulation that left the record (None, NaN or infinite)."""
    if v is None:
        return "diverged"
    v = float(v)
    if not math.isfinite(v):
        return "diverged"
    return f"{100.0 * v:#.3g} %".replace(". %", " %")


def duration_text(seconds) -> str:
    """Seconds for a person: "0.4 s", "12 s", "2 min 05 s", "1 h 03 min"."""
    s = float(seconds)
    if not math.isfinite(s) or s < 0:
        return "-"
    if s < 10:
        return f"{s:.1f} s"
    if s < 60:
        return f"{s:.0f} s"
    if s < 3600:
        m, r = divmod(int(round(s)), 60)
        return f"{m} min {r:02d} s"
    h, r = divmod(int(round(s)), 3600)
    return f"{h} h {r // 60:02d} min"


# the parameters of a structure's model (per unit mass) and their units; fn terms are named
# fn_m[term] with units from the term's exponents (fn_term_units)
PARAMETER_UNITS = {
    "c_m": "1/s", "k_m": "1/s^2", "alpha_m": "1/s^2", "gamma": "1/m", "delta": "1/m", "inv_m": "1/kg",
    "input_offset": "m/s^2", "drive_u2": "1/(drive unit)", "drive_hp": "rad/s",
}
_FACTOR = re.compile(r"^(y|dy|y'|z)(?:\^(\d+))?$")


def fn_term_units(term: str) -> str:
    """The units of the coefficient of fn term ``term`` (e.g. "y^2*dy") in a per-unit-mass equation:
    the term y^p y'^r has units m^(p+r) s^-r and the equation's units are m/s^2, so its coefficient
    has m^(1-p-r) s^(r-2). "?" for a term not of that form."""
    p = r = 0
    for factor in term.replace(" ", "").split("*"):
        m = _FACTOR.match(factor)
        if not m:
            return "?"
        n = int(m.group(2) or 1)
        if m.group(1) == "y":
            p += n
        elif m.group(1) in ("dy", "y'"):
            r += n
        else:
            return "?"
    return _units(1 - p - r, r - 2)


def _units(m_exp: int, s_exp: int) -> str:
    num, den = [], []
    for sym, e in (("m", m_exp), ("s", s_exp)):
        if e > 0:
            num.append(sym if e == 1 else f"{sym}^{e}")
        elif e < 0:
            den.append(sym if e == -1 else f"{sym}^{-e}")
    top = "*".join(num) or "1"
    return top if not den else f"{top}/{'*'.join(den) if len(den) == 1 else '(' + '*'.join(den) + ')'}"


def parameter_name(key: str, term: str | None = None) -> str:
    """The one spelling of a parameter: ``c_m``, ..., and ``fn_m[y^2]`` for an fn term."""
    return f"{key}[{term}]" if term is not None else key


def parameter_units(key: str, term: str | None = None, excitation: str = "base") -> str:
    """Units of a structure's parameter (per unit mass); ``term`` for an fn_m term."""
    if term is not None:
        return fn_term_units(term)
    if key == "input_offset" and excitation == "force":
        return "N"
    return PARAMETER_UNITS.get(key, "")

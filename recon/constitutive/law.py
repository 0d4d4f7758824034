"""ConstitutiveLaw: the force law of a component under an imposed displacement.

    F = c x' + k x + fn(x, x') + z + f0 [+ m x'']
    z = alpha w,   w' = x' - gamma |x'| w - delta x' |w|

so that z' = alpha x' - gamma |x'| z - delta x' |z|: the library's Bouc-Wen law (n = 1), here
in force units (N), not per unit mass. ``mass`` is a known inertia (0: none).

Command-dependent law (an MR damper; ``eta`` > 0): with the command v and its first-order
lag u, u' = -eta (u - v),

    c -> c + c1 u,   alpha -> alpha + alpha1 u

so the damping, the hysteretic force's initial stiffness and its amplitude alpha/(gamma + delta)
all scale linearly with u. fn monomials use the library's names with y for x and dy for x'.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.library import monomials
from recon.simulation.imposed import hysteretic_state
from recon.steps.bouc_wen import fn_values
from shakerlab.errors import UserFacingError

NAMES = ("c", "k", "alpha", "gamma", "delta", "f0")
COMMAND_NAMES = ("c1", "alpha1", "eta")
UNITS = {"c": "N s/m", "k": "N/m", "alpha": "N/m", "gamma": "1/m", "delta": "1/m", "f0": "N", "mass": "kg",
         "c1": "N s/m per command unit", "alpha1": "N/m per command unit", "eta": "1/s"}
KIND = "constitutive"


@dataclass
class ConstitutiveLaw:
    c: float
    k: float
    alpha: float
    gamma: float
    delta: float
    f0: float = 0.0
    fn: dict = field(default_factory=dict)
    mass: float = 0.0
    c1: float = 0.0
    alpha1: float = 0.0
    eta: float = 0.0
    provenance: dict = field(default_factory=dict)

    @property
    def K(self) -> float:
        """Small-amplitude stiffness k + alpha."""
        return self.k + self.alpha

    @property
    def lam(self) -> float:
        return self.gamma + self.delta

    @property
    def commanded(self) -> bool:
        return self.eta > 0

    def parameters(self) -> dict:
        out = {k: float(getattr(self, k)) for k in NAMES}
        out["fn"] = dict(self.fn)
        if self.mass:
            out["mass"] = float(self.mass)
        if self.commanded:
            out.update({k: float(getattr(self, k)) for k in COMMAND_NAMES})
        return out

    def to_dict(self) -> dict:
        units = {k: UNITS[k] for k in self.parameters() if k in UNITS}
        units["fn"] = {k: "N / (m^p (m/s)^r) for y^p dy^r" for k in self.fn}
        return {"kind": KIND, "parameters": self.parameters(), "units": units,
                "convention": "force law of an imposed displacement x (y) and velocity x' (dy), SI units",
                "equation": self.equation(), "provenance": self.provenance}

    @classmethod
    def from_dict(cls, d: dict) -> "ConstitutiveLaw":
        if d.get("kind") not in (None, KIND):
            raise UserFacingError(f"not a constitutive law (kind {d.get('kind')!r})")
        p = d.get("parameters", d)
        missing = [k for k in NAMES[:5] if k not in p]
        if missing:
            raise UserFacingError(f"constitutive law: missing parameter(s) {', '.join(missing)}")
        for k in p.get("fn", {}):
            monomials.parse(k)
        return cls(**{k: float(p[k]) for k in NAMES if k in p}, fn={k: float(v) for k, v in p.get("fn", {}).items()},
                   mass=float(p.get("mass", 0.0)), **{k: float(p[k]) for k in COMMAND_NAMES if k in p},
                   provenance=dict(d.get("provenance", {})))

    def __str__(self) -> str:
        return self.equation()

    @classmethod
    def load(cls, path) -> "ConstitutiveLaw":
        """A law saved by ``reconstruct --save-model`` of a component test."""
        path = Path(path)
        try:
            d = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise UserFacingError(f"{path}: no such law file") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise UserFacingError(f"{path}: cannot read the law file ({exc})") from None
        if not isinstance(d, dict):
            raise UserFacingError(f"{path}: not a constitutive law (a JSON object with kind 'constitutive')")
        try:
            return cls.from_dict(d)
        except (TypeError, ValueError) as exc:
            raise UserFacingError(f"{path}: bad constitutive law ({exc})") from None
        except UserFacingError as exc:
            raise UserFacingError(f"{path}: {exc}") from None

    def equation(self) -> str:
        fn = " ".join(f"{'+' if v >= 0 else '-'} {abs(v):.6g} {k}" for k, v in self.fn.items())
        c = f"({self.c:.6g} + {self.c1:.6g} u)" if self.commanded else f"{self.c:.6g}"
        a = f"({self.alpha:.6g} + {self.alpha1:.6g} u)" if self.commanded else f"{self.alpha:.6g}"
        m = f" + {self.mass:.6g} ddy" if self.mass else ""
        s = (f"F = {c} dy + {self.k:.6g} y {fn + ' ' if fn else ''}+ z {'+' if self.f0 >= 0 else '-'} "
             f"{abs(self.f0):.6g}{m};  z = {a} w,  w' = dy - {self.gamma:.6g} |dy| w - {self.delta:.6g} dy |w|")
        if self.commanded:
            s += f";  u' = -{self.eta:.6g} (u - cmd)"
        return s

    # ------------------------------------------------------------------ prediction
    def gains(self, u):
        """(c, alpha) at the lagged command u (scalars without a command law)."""
        if not self.commanded or u is None:
            return self.c, self.alpha
        return self.c + self.c1 * u, self.alpha + self.alpha1 * u

    def force(self, y, dy, w, u=None, ddy=None):
        c, a = self.gains(u)
        f = c * dy + self.k * y + fn_values(self.fn, y, dy) + a * w + self.f0
        if self.mass and ddy is not None:
            f = f + self.mass * ddy
        return f

    def start_state(self, F0, y0, dy0, u0=None, ddy0=0.0) -> float:
        """w at a record's first sample from the force law, within the loop's range."""
        c, a = self.gains(u0)
        if not a:
            return 0.0
        z0 = F0 - c * dy0 - self.k * y0 - fn_values(self.fn, np.array([y0]), np.array([dy0]))[0] - self.f0 \
            - self.mass * ddy0
        bound = 1.0 / self.lam if self.lam > 0 else abs(z0 / a)
        return float(np.clip(z0 / a, -bound, bound))

    def simulate(self, dt, y, dy, cmd=None, w0=0.0, ddy=None):
        """(F, w, u) along an imposed motion (y, y' sampled at ``dt``) from the state w0."""
        w, u = hysteretic_state(dy, dt, self.gamma, self.delta, w0, cmd if self.commanded else None, self.eta)
        return self.force(y, dy, w, u, ddy), w, u


def is_law_file(path) -> bool:
    """Does ``path`` hold a constitutive law (JSON with kind 'constitutive')? False for anything else."""
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(d, dict) and d.get("kind") == KIND

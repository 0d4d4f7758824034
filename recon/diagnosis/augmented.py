"""A baseline HystereticModel plus the optional extra physics the diagnosis can add.

Per unit mass (g = 1 and u = -x_base'' under base excitation, g = 1/m and u = F under
force excitation):

    y'' + c y' + k (1 + drift t) y + fn(y, y') + z
        + mu tanh(y'/v0) + c2 y'|y'| + kc max(side*y - gap, 0)*side   = g u
    z'  = alpha y' - gamma |y'| z - delta y' |z|
    q'' + 2 zeta2 w2 q' + w2^2 q = g u - drive2 a       (higher mode, only when w2 > 0)

where a is the measured point's absolute acceleration beyond what the input gives it: y''
under base excitation (so drive2 = 1 drives q with -(x_base'' + y'')), y'' + g u under force
excitation (drive2 = 1 drives q with -y''). drive2 = 0 is a structural mode driven as the
first one is; drive2 = 1 a resonance riding on the measured point (a sensor mount, a local
mass).

What the sensors report (the output the model is compared with):

    base:  y_rec(t) = (1 + tip_scale) x_tip(t - delay) - x_base(t),  x_tip = x_base + y + phi2 q
    force: y_rec(t) = (1 + tip_scale) (y + phi2 q)(t - delay)

in the quantity the response was recorded in: a velocity record (``order`` 1) reads the same
with every motion differentiated once (x_tip' = x_base' + y' + phi2 q', x_base' the base's
velocity as recon.signals.response_target takes it away), so the channel's delay, the sensor's
scale and the higher mode's reading act on the velocity the vibrometer measured.

``t`` in the drift term is the stage's recorded time (session time when the
recording keeps it). Every extra is off when its parameter is 0, so an
``AugmentedModel`` with no extras simulates exactly like its baseline.
The integrator is :func:`recon.simulation.rk4.simulate_states`: the extended RK4 kernel, or
its plain specialisation when no extra acts (the same numbers to the bit; input interpolated
by a 4-point cubic between samples, sub-steps when sampling is coarse).
"""
from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.model import HystereticModel, finite_number
from recon.simulation.rk4 import P_NAMES, kernel_parameters, simulate_states, substeps
from shakerlab.errors import UserFacingError
from shakerlab.output_files import check_output, write_text
from shakerlab.run_data import BASE, Stage

EXTRAS = {
    # name: (default, unit, meaning)
    "mu": (0.0, "m/s^2", "Coulomb friction level per unit mass (mu tanh(y'/v0))"),
    "v0": (0.0, "m/s", "velocity scale of the smoothed sign (0: 1e-4 m/s)"),
    "c2": (0.0, "1/m", "quadratic damping c2 y'|y'|"),
    "kc": (0.0, "1/s^2", "one-sided contact stiffness"),
    "gap": (0.0, "m", "contact gap"),
    "side": (1.0, "-", "+1: contact when y > gap, -1: when y < -gap"),
    "drift": (0.0, "1/s", "relative stiffness drift: k(t) = k (1 + drift t)"),
    "delay": (0.0, "s", "the displacement (tip) channel lags the input (base/force) channel"),
    "tip_scale": (0.0, "-", "relative calibration error of the displacement (tip) sensor"),
    "w2": (0.0, "rad/s", "higher-mode natural frequency (0: off)"),
    "zeta2": (0.02, "-", "higher-mode damping ratio"),
    "phi2": (0.0, "m/m", "higher-mode participation in the displacement reading"),
    "drive2": (0.0, "-", "what drives the higher mode: 0 the input (a structural mode), 1 the measured "
                         "point's absolute acceleration (a resonance riding on it)"),
}
# the extras that are slots of the simulation kernel's parameter vector (recon.simulation.rk4.P_NAMES,
# the same name): they reach it by that name (AugmentedModel.kernel_vector); the others act on the reading
KERNEL_EXTRAS = tuple(name for name in EXTRAS if name in P_NAMES)


def shift(x: np.ndarray, delay: float, dt: float) -> np.ndarray:
    """x(t - delay) by linear interpolation (the first samples hold x[0])."""
    if delay == 0.0:
        return x
    idx = np.arange(x.size) - delay / dt
    return np.interp(idx, np.arange(x.size), x)


@dataclass
class AugmentedModel:
    """``baseline`` (a HystereticModel) plus extra physics ``extras`` (see EXTRAS)."""

    baseline: HystereticModel
    extras: dict = field(default_factory=dict)
    added: list = field(default_factory=list)      # catalog ids this model adds to its baseline

    def __post_init__(self):
        unknown = set(self.extras) - set(EXTRAS)
        if unknown:
            raise UserFacingError(f"augmented model: unknown extra parameter(s) {sorted(unknown)} "
                                  f"(known: {', '.join(EXTRAS)})")
        self.extras = {k: float(v) for k, v in self.extras.items()}

    def get(self, name: str) -> float:
        return self.extras.get(name, EXTRAS[name][0])

    @property
    def excitation(self) -> str:
        return self.baseline.excitation

    def copy(self) -> "AugmentedModel":
        """An independent copy: the baseline's parameters and term dict are its own. The baseline's
        provenance is copied one level deep (what is written to it is whole entries; a deep copy of
        it cost 8 % of a diagnosis, every fit's every trial copies the model)."""
        base = copy.copy(self.baseline)
        base.fn_m = dict(base.fn_m)
        base.provenance = dict(base.provenance)
        return AugmentedModel(base, dict(self.extras), list(self.added))

    def friction_v0(self) -> float:
        """The friction's smoothing velocity as simulated: v0, 1e-4 m/s where friction is on without one."""
        v0 = self.get("v0")
        return 1e-4 if self.get("mu") != 0.0 and v0 <= 0.0 else v0

    def kernel_vector(self) -> np.ndarray:
        """The simulation kernel's parameter vector (recon.simulation.rk4.kernel_parameters), slot
        by name: the baseline's input gain, linear and Bouc-Wen parameters and the extras that are
        kernel slots (KERNEL_EXTRAS), v0 as simulated (1 with friction off), the contact's side
        as a sign and the higher mode's share of the input, gu2 (module docstring)."""
        m = self.baseline
        named = {name: self.get(name) for name in KERNEL_EXTRAS}
        named["v0"] = self.friction_v0() or 1.0
        named["side"] = 1.0 if named["side"] >= 0 else -1.0
        named["gu2"] = 1.0 if m.excitation == BASE else 1.0 - named["drive2"]
        return kernel_parameters(g=m.input_gain, c=m.c_m, k=m.k_m, alpha=m.alpha_m, gamma=m.gamma, delta=m.delta,
                                 **named)

    # --------------------------------------------------------------- simulation
    def substeps(self, dt: float, step_factor: int = 1) -> int:
        """RK4 sub-steps per sample of interval ``dt``: 64 steps per period of the stiffest
        resonance (the model's, with a contact's stiffness added), 20 per period of the higher mode
        (it is linear), h mu / v0 (the friction's local damping) inside RK4's stability; at most 64;
        then ``step_factor`` times that (a stage whose record needs a finer step,
        recon.diagnosis.rank.integration_step_factor)."""
        m = self.baseline
        mu = self.get("mu")
        w2 = self.get("w2")
        stiff = max(abs(m.K_m), abs(m.k_m), 1.0, abs(self.get("kc")) + abs(m.K_m))
        n_sub = max(substeps(dt, stiff), substeps(dt, w2 ** 2, 20))   # the extra mode is linear: 20 steps/period
        if mu != 0.0:   # keep h * mu / v0 (the friction's local damping) inside RK4's stability
            n_sub = max(n_sub, int(math.ceil(dt * abs(mu) / self.friction_v0() / 1.5)))
        return min(n_sub, 64) * int(step_factor)

    def simulate(self, t: np.ndarray, u: np.ndarray, x_in: np.ndarray | None = None, initial=None,
                 dt: float | None = None, order: int = 0, step_factor: int = 1):
        """Recorded-output prediction for input ``u`` on time base ``t`` (from rest, or from
        ``initial`` = (y0, y'0, z0); the higher mode always starts at rest).

        ``order``: the recorded quantity, 0 displacement, 1 velocity (the module docstring).
        ``x_in`` is the base motion in that quantity (base excitation; needed for the tip-scale
        and delay output terms); ``dt`` the sampling interval of ``t`` if the caller has it
        (the median interval); ``step_factor`` as :meth:`substeps` takes it.
        Returns (y_rec, states) with states = (y, y', z, q, q').
        """
        if order not in (0, 1):
            raise ValueError(f"augmented model: output order {order} (0 displacement, 1 velocity)")
        m = self.baseline
        t = np.asarray(t, float)
        if dt is None:
            dt = float(np.median(np.diff(t)))
        u = m.drive(np.asarray(u, float), dt)        # the exciter's force, when the baseline models one
        coef, p, r = m.fn_arrays()
        n_sub = self.substeps(dt, step_factor)
        P = self.kernel_vector()
        y0, dy0, z0 = (0.0, 0.0, 0.0) if initial is None else (float(v) for v in initial)
        st = simulate_states(np.ascontiguousarray(u, float), float(t[0]), dt, int(n_sub), P, coef, p, r, y0, dy0, z0)
        y = st[order] + self.get("phi2") * st[3 + order]
        scale = 1.0 + self.get("tip_scale")
        delay = self.get("delay")
        if m.excitation == BASE and x_in is not None:
            tip = shift(x_in + y, delay, dt)
            y_rec = scale * tip - x_in
        else:
            y_rec = scale * shift(y, delay, dt)
        return y_rec, st

    def simulate_stage(self, stage: Stage, u: np.ndarray | None = None):
        """Recorded-output prediction for the stage, started from its estimated initial state."""
        u = self.baseline.stage_input(stage, band=False) if u is None else u     # as rank.prepare
        x_in = stage.channels["x_base"] if stage.excitation == BASE else None
        return self.simulate(stage.t, u, x_in, initial=self.baseline.stage_start(stage, u))[0]

    # ---------------------------------------------------------------- printing
    def equation(self) -> str:
        eq = self.baseline.equation()
        lhs, _, rest = eq.partition(" + z = ")
        extra = []
        if self.get("mu"):
            extra.append(f"+ {self.get('mu'):.6g} sign(y')")
        if self.get("c2"):
            extra.append(f"+ {self.get('c2'):.6g} y'|y'|")
        if self.get("kc"):
            s = self.get("side")
            extra.append(f"+ {self.get('kc'):.6g} max({'' if s >= 0 else '-'}y - {self.get('gap'):.4g}, 0)"
                         + ("" if s >= 0 else " * (-1)"))
        if self.get("drift"):
            lhs = lhs.replace(" y", " y", 1)
            extra.append(f"+ {self.get('drift'):.4g} t * k y (stiffness drift)")
        out = lhs + (" " + " ".join(extra) if extra else "") + " + z = " + rest
        notes = []
        if self.get("w2"):
            drive = "u" if not self.get("drive2") else (
                f"u - {self.get('drive2'):.4g} y''" if self.excitation == BASE
                else f"{1 - self.get('drive2'):.4g} u - {self.get('drive2'):.4g} y''")
            notes.append(f"q'' + 2*{self.get('zeta2'):.3g}*{self.get('w2'):.6g} q' + {self.get('w2'):.6g}^2 q = {drive}; "
                         f"displacement reading += {self.get('phi2'):.4g} q  (higher mode at "
                         f"{self.get('w2') / 2 / math.pi:.4g} Hz)")
        if self.get("delay"):
            notes.append(f"displacement channel lags the input channel by {self.get('delay') * 1e3:.4g} ms")
        if self.get("tip_scale"):
            notes.append(f"displacement (tip) sensor reads (1 {'+' if self.get('tip_scale') >= 0 else '-'} "
                         f"{abs(self.get('tip_scale')):.4g}) x")
        return "\n".join([out] + notes)

    # ----------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        return {"kind": "shakerlab.recon.AugmentedModel", "baseline": self.baseline.to_dict(),
                "extras": dict(self.extras), "added": list(self.added),
                "extras_units": {k: EXTRAS[k][1] for k in self.extras}, "equation": self.equation()}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, d: dict) -> "AugmentedModel":
        if not isinstance(d, dict):
            raise UserFacingError(f"model JSON must be an object, got {type(d).__name__}")
        if d.get("kind") == "shakerlab.recon.HystereticModel":
            return cls(HystereticModel.from_dict(d))
        if "baseline" not in d:
            raise UserFacingError("augmented model JSON lacks field 'baseline'")
        extras, added = d.get("extras", {}), d.get("added", [])
        if not isinstance(extras, dict):
            raise UserFacingError(f"model JSON: field 'extras' must be an object, got {type(extras).__name__}")
        extras = dict(extras)
        for k, v in extras.items():
            if k not in EXTRAS:
                raise UserFacingError(f"model JSON: field 'extras.{k}' is not a known extra ({', '.join(EXTRAS)})")
            extras[k] = finite_number(v, f"extras.{k}")
        if not isinstance(added, list) or not all(isinstance(a, str) for a in added):
            raise UserFacingError(f"model JSON: field 'added' must be a list of names, got {added!r}")
        return cls(HystereticModel.from_dict(d["baseline"]), dict(extras), list(added))

    @classmethod
    def load(cls, path) -> "AugmentedModel":
        path = Path(path)
        if not path.exists():
            raise UserFacingError(f"{path}: no such model file")
        try:
            return cls.from_dict(json.loads(path.read_text(encoding="utf-8")))
        except (json.JSONDecodeError, RecursionError) as exc:
            raise UserFacingError(f"{path}: model JSON is not valid JSON ({exc})") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise UserFacingError(f"{path}: cannot read the model file ({exc})") from None
        except UserFacingError as exc:
            raise UserFacingError(f"{path}: {exc}") from None

    def save(self, path, overwrite: bool = False) -> None:
        """Written as HystereticModel.save: through a temporary file, never over a run file."""
        check_output(path, overwrite=overwrite, option="model", never_hdf5=True)
        write_text(path, self.to_json(), overwrite=overwrite, never_hdf5=True)

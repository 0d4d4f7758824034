"""The identified SDOF hysteretic model (per unit mass).

    y'' + c_m y' + k_m y + sum_j a_j y^p_j y'^r_j + z = g u
    z'  = alpha_m y' - gamma |y'| z - delta y' |z|

with ``g = 1`` and ``u = -x_base''`` under base excitation (``y = x_tip - x_base``)
and ``g = inv_m = 1/m`` and ``u = force`` under force excitation (``y = x``).
"""
from __future__ import annotations

import json
import math
import numbers
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.exciter import drive_force
from recon.library import monomials
from recon.simulation.rk4 import simulate_sdof, substeps
from recon.simulation.start_state import fit_start
from recon.signals import (at_rest, continuous_velocity_start, response_order, response_target, stage_input,
                           start_derivatives, target_edge)
from shakerlab.errors import UserFacingError
from shakerlab.output_files import check_output, write_text
from shakerlab.run_data import BASE, FORCE, Stage

UNITS = {
    "c_m": "1/s", "k_m": "1/s^2", "alpha_m": "1/s^2", "gamma": "1/m", "delta": "1/m",
    "inv_m": "1/kg", "fn_m": "term y^p*dy^r has coefficient units m^(1-p-r) s^(r-2)",
    "y": "m", "dy": "m/s", "z": "m/s^2 (restoring force per unit mass)",
}
MAX_TERM_DEGREE = 12     # highest p + r of an fn term read from a model JSON
CONVENTION = ("per unit mass: every force term is divided by the mass m; base excitation "
              "y = x_tip - x_base, u = -x_base''; force excitation y = x, u = force [N] with "
              "coefficient inv_m = 1/m")


PARAMETER_NAMES = ("c_m", "k_m", "alpha_m", "gamma", "delta")   # the physical parameters, per unit mass
MAX_SUBSTEPS = 64   # RK4 sub-steps per sample at most (64 steps per period of a resonance at fs)


def signed(value: float, term: str) -> str:
    """`` + 3 y`` or `` - 3 y``: a coefficient and its term with the sign folded into the operator."""
    return f" {'-' if value < 0 else '+'} {abs(value):.6g}{term}"


def finite_number(value, field_name: str) -> float:
    """``value`` as a float if it is a finite JSON number; otherwise a UserFacingError naming the field."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise UserFacingError(f"model JSON: field {field_name!r} is {value!r}, expected a number")
    try:
        out = float(value)
    except OverflowError:
        out = math.inf
    if not math.isfinite(out):
        raise UserFacingError(f"model JSON: field {field_name!r} is {value!r}, expected a finite number")
    return out


def sampling_interval(t: np.ndarray) -> float:
    """The sampling interval of a uniformly sampled time base ``t``: the median of its intervals,
    every interval within 1e-6 of it (else a UserFacingError)."""
    dts = np.diff(t)
    dt = float(np.median(dts))
    if np.any(np.abs(dts - dt) > 1e-6 * dt + 1e-12):
        raise UserFacingError("simulate: t must be uniformly sampled")
    return dt


@dataclass
class HystereticModel:
    excitation: str
    c_m: float
    k_m: float
    alpha_m: float
    gamma: float
    delta: float
    fn_m: dict = field(default_factory=dict)
    inv_m: float | None = None
    provenance: dict = field(default_factory=dict)
    # optional constant offset b of the recorded input (its units: m/s^2 base, N force): the model
    # is driven by g (u - b). None (the default) = no such parameter; every result without it is
    # unchanged (ReconSettings.input_offset)
    input_offset: float | None = None
    # the exciter between a recorded drive and the force (force excitation, recon.exciter): the
    # model is driven by g HP_hp(u + u2 u^2). None (the default): driven by the input as recorded
    drive_u2: float | None = None
    drive_hp: float | None = None

    def __post_init__(self):
        if self.excitation not in (BASE, FORCE):
            raise UserFacingError(f"model excitation must be 'base' or 'force', got {self.excitation!r}")
        if self.excitation == FORCE and self.inv_m is None:
            raise UserFacingError("force-excitation model needs inv_m (1/m)")
        if self.excitation != FORCE and (self.drive_u2 is not None or self.drive_hp is not None):
            raise UserFacingError("an exciter model (drive_u2, drive_hp) needs force excitation: under base "
                                  "excitation the input is the measured base acceleration, not a drive")
        self.fn_m = {k: float(v) for k, v in self.fn_m.items()}
        for k in self.fn_m:
            monomials.parse(k)

    # ------------------------------------------------------------------ basics
    @property
    def K_m(self) -> float:
        return self.k_m + self.alpha_m

    @property
    def lam(self) -> float:
        return self.gamma + self.delta

    @property
    def input_gain(self) -> float:
        return 1.0 if self.excitation == BASE else float(self.inv_m)

    def fn_arrays(self):
        keys = list(self.fn_m)
        p, r = monomials.exponents(keys)
        return np.array([self.fn_m[k] for k in keys], float), p, r

    def fn(self, y, dy):
        out = np.zeros_like(np.asarray(y, float))
        for k, a in self.fn_m.items():
            p, r = monomials.parse(k)
            out = out + a * y ** p * dy ** r
        return out

    # ---------------------------------------------------------------- printing
    def equation(self) -> str:
        """The equation as text, each coefficient printed with its sign folded into the operator
        ("+ -" never appears: ``y' - 3 y`` rather than ``y' + -3 y``)."""
        lhs = f"y''{signed(self.c_m, ' y' + chr(39))}{signed(self.k_m, ' y')}"
        for k, a in self.fn_m.items():
            lhs += signed(a, " " + k.replace("dy", "y`").replace("`", chr(39)))
        rhs = "-x_base''" if self.excitation == BASE else f"{self.inv_m:.6g} F"
        if self.input_offset is not None:
            rhs = (f"-x_base''{signed(-self.input_offset, '')}" if self.excitation == BASE
                   else f"{self.inv_m:.6g} (F{signed(-self.input_offset, '')})")
        zeq = (f"z' = {self.alpha_m:.6g} y'{signed(-self.gamma, ' |y' + chr(39) + '| z')}"
               f"{signed(-self.delta, ' y' + chr(39) + ' |z|')}")
        out = f"{lhs} + z = {rhs}\n{zeq}"
        if self.has_drive:
            out += (f"\nF = HP(u{signed(self.drive_u2 or 0.0, ' u^2')}), high-pass corner "
                    f"{abs(self.drive_hp or 0.0) / (2 * np.pi):.4g} Hz, u the recorded drive (recon.exciter)")
        return out

    @property
    def has_drive(self) -> bool:
        return self.drive_u2 is not None or self.drive_hp is not None

    def drive(self, u: np.ndarray, dt: float) -> np.ndarray:
        """The force the exciter makes of the recorded drive ``u`` (``u`` itself without an exciter model)."""
        if not self.has_drive:
            return u
        return drive_force(u, dt, self.drive_u2 or 0.0, self.drive_hp or 0.0)

    def __str__(self) -> str:
        return self.equation()

    def print(self) -> None:  # noqa: A003 - like PySINDy
        print(self.equation())

    # ----------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        params = {"c_m": self.c_m, "k_m": self.k_m, "alpha_m": self.alpha_m,
                  "gamma": self.gamma, "delta": self.delta, "fn_m": dict(self.fn_m)}
        if self.excitation == FORCE:
            params["inv_m"] = self.inv_m
        units = UNITS
        if self.input_offset is not None:
            params["input_offset"] = self.input_offset
            units = dict(UNITS, input_offset="m/s^2" if self.excitation == BASE else "N")
        if self.has_drive:
            params["drive_u2"] = self.drive_u2 or 0.0
            params["drive_hp"] = self.drive_hp or 0.0
            units = dict(units, drive_u2="1/(drive unit)", drive_hp="rad/s")
        return {"kind": "shakerlab.recon.HystereticModel", "excitation": self.excitation,
                "parameters": params, "units": units, "convention": CONVENTION,
                "equation": self.equation(), "provenance": self.provenance}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, d: dict) -> "HystereticModel":
        """The model of a dict as :meth:`to_dict` writes it; every field is checked (a finite number
        where a number is expected) and a bad one is named in a UserFacingError."""
        if not isinstance(d, dict):
            raise UserFacingError(f"model JSON must be an object, got {type(d).__name__}")
        p = d.get("parameters")
        if "parameters" not in d or "excitation" not in d:
            raise UserFacingError(f"model JSON lacks field {'parameters' if 'parameters' not in d else 'excitation'!r}")
        if not isinstance(p, dict):
            raise UserFacingError(f"model JSON: field 'parameters' must be an object, got {type(p).__name__}")
        if not isinstance(d["excitation"], str):
            raise UserFacingError(f"model JSON: field 'excitation' must be 'base' or 'force', got {d['excitation']!r}")
        for key in ("c_m", "k_m", "alpha_m", "gamma", "delta"):
            if key not in p:
                raise UserFacingError(f"model JSON lacks field 'parameters.{key}'")
        values = {key: finite_number(p[key], f"parameters.{key}") for key in ("c_m", "k_m", "alpha_m", "gamma", "delta")}
        fn = p.get("fn_m", {})
        if not isinstance(fn, dict):
            raise UserFacingError(f"model JSON: field 'parameters.fn_m' must be an object of term: coefficient, "
                                  f"got {type(fn).__name__}")
        fn_m = {}
        for term, a in fn.items():
            where = f"parameters.fn_m[{term!r}]"
            try:
                deg = sum(monomials.parse(term))
            except UserFacingError as exc:
                raise UserFacingError(f"model JSON: field {where}: {exc}") from None
            if deg > MAX_TERM_DEGREE:
                raise UserFacingError(f"model JSON: field {where}: degree {deg} above {MAX_TERM_DEGREE}")
            fn_m[term] = finite_number(a, where)
        inv_m = p.get("inv_m")
        if inv_m is not None or d["excitation"] == FORCE:
            inv_m = finite_number(inv_m, "parameters.inv_m")
        offset = p.get("input_offset")
        if offset is not None:
            offset = finite_number(offset, "parameters.input_offset")
        drive = {k: finite_number(p[k], f"parameters.{k}") if p.get(k) is not None else None
                 for k in ("drive_u2", "drive_hp")}
        provenance = d.get("provenance", {})
        return cls(excitation=d["excitation"], fn_m=fn_m, inv_m=inv_m, input_offset=offset, **drive,
                   provenance=provenance if isinstance(provenance, dict) else {}, **values)

    @classmethod
    def from_json(cls, text: str) -> "HystereticModel":
        try:
            d = json.loads(text)
        except (json.JSONDecodeError, RecursionError) as exc:
            raise UserFacingError(f"model JSON is not valid JSON ({exc})") from None
        return cls.from_dict(d)

    def save(self, path, overwrite: bool = False) -> None:
        """Write the model JSON through a temporary file: an existing file is replaced only with
        ``overwrite``, and never when it is an HDF5 file (a run file)."""
        check_output(path, overwrite=overwrite, option="model", never_hdf5=True)
        write_text(path, self.to_json(), overwrite=overwrite, never_hdf5=True)

    @classmethod
    def load(cls, path) -> "HystereticModel":
        path = Path(path)
        if not path.exists():
            raise UserFacingError(f"{path}: no such model file")
        try:
            return cls.from_json(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError) as exc:
            raise UserFacingError(f"{path}: cannot read the model file ({exc})") from None
        except UserFacingError as exc:
            raise UserFacingError(f"{path}: {exc}") from None

    # -------------------------------------------------------------- simulation
    def simulate(self, t, u, n_sub: int | None = None, initial=None, dt: float | None = None):
        """Response to the per-unit-mass input (base) or force (force), from rest.

        Returns (y, dy, z) sampled at ``t`` (uniform sampling required).
        ``initial=(y0, dy0, z0)`` starts from that state instead of rest. ``dt``: ``t``'s
        :func:`sampling_interval`, when the caller has it (a fit simulating one record many times).
        """

        t = np.asarray(t, float)
        u = np.asarray(u, float)
        if self.input_offset is not None:
            u = u - self.input_offset
        if t.shape != u.shape or t.size < 2:
            raise UserFacingError(f"simulate: t and u must be 1-D arrays of equal length (got {t.shape}, {u.shape})")
        dt = sampling_interval(t) if dt is None else dt
        u = self.drive(u, dt)
        coef, p, r = self.fn_arrays()
        if n_sub is None:   # capped: a trial stiffer than that (resonance above ~fs) is far from any record;
            # uncapped, one such output-error trial can take minutes; capped it diverges and is rejected
            n_sub = min(substeps(dt, max(abs(self.K_m), abs(self.k_m), 1.0)), MAX_SUBSTEPS)
        y0, v0, z0 = (0.0, 0.0, 0.0) if initial is None else (float(v) for v in initial)
        return simulate_sdof(u, dt, int(n_sub), self.input_gain, self.c_m, self.k_m, self.alpha_m,
                             self.gamma, self.delta, coef, p, r, y0, v0, z0)

    # ``tuning`` of the stage methods below (recon.estimator.tuning): the numbers the input's band
    # (band_*) and a start state fitted to the stage's first seconds (start_fit_*) are decided with;
    # the estimator passes its ReconSettings.tuning, every other reader of a recorded stage the default

    def stage_input(self, stage: Stage, band: bool = True, tuning: EstimatorTuning = DEFAULT_TUNING) -> np.ndarray:
        """The input u the model is driven by, built from the stage's channels (recon.signals;
        ``band``: taken in the channel's own band, recon.input_band)."""
        if stage.excitation != self.excitation:
            raise UserFacingError(f"stage {stage.name!r} is {stage.excitation} excitation, model is {self.excitation}")
        return stage_input(stage, band, tuning)

    def stage_start(self, stage: Stage, u=None, fit: bool = True, tuning: EstimatorTuning = DEFAULT_TUNING):
        """The stage's state at its first sample (y, y', z), estimated from the recording.
        A response recorded as velocity or acceleration: :meth:`measured_start`.

        y, y', y'' by a Savitzky-Golay fit at the start; z from the equation of motion,
        z = g u - y'' - c y' - k y - fn(y, y'). A stage recorded from rest gives ~0. A stage that
        starts in motion gets its start fitted to its first seconds (``fit``; else the edge
        estimate itself, recon.simulation.start_state)."""

        u = self.stage_input(stage, tuning=tuning) if u is None else u
        measured = continuous_velocity_start(stage)     # velocity recorded by the rig: its own rule
        if measured is not None:
            y0, v0, a0, at_rest = measured
            return y0, v0, float(self.start_z(0.0 if at_rest else u[0], y0, v0, a0))
        if response_target(stage) is not None:
            return self.measured_start(stage, u, fit, tuning)
        y0, v0, a0, sigma, sig_v, v_rms = start_derivatives(stage)
        # recorded from rest: y0 within the noise and y'0 small against the stage's rms
        # velocity (a zero crossing mid-motion has y'0 near its peak) or within the noise of
        # the edge estimate (at 40 dB its y' noise alone exceeds 5 % of the rms velocity). Then
        # start from rest exactly: an edge estimate of y'' (hence z0) is noisy.
        if abs(y0) < 5 * sigma and (abs(v0) < 0.05 * v_rms or abs(v0) < 4 * sig_v):
            return 0.0, 0.0, 0.0
        edge = (float(y0), float(v0), float(self.start_z(u[0], y0, v0, a0)))
        if not fit:
            return edge
        # the edge estimate's z0 comes from the noisy edge y'': the start is fitted to the
        # stage's first seconds instead, with rest as the other candidate (recon.simulation.start_state)
        t = stage.t - stage.t[0]
        return self._fitted_start(stage, edge, v_rms, lambda init, n: self.simulate(t[:n], u[:n], initial=init)[0],
                                  stage.y, tuning)

    def _fitted_start(self, stage: Stage, edge: tuple, v_rms: float, simulate, target: np.ndarray,
                      tuning: EstimatorTuning, offset: bool = False) -> tuple:
        """The start (y, y', z) fitted to the stage's first seconds of ``target`` (what ``simulate``
        gives), from the edge estimate, each on the scale of its motion (recon.simulation.start_state;
        ``offset``: a constant offset of the target is a nuisance of the fit)."""
        y_rms = float(np.std(stage.y)) or 1.0
        scales = (max(abs(edge[0]), 0.05 * y_rms), max(abs(edge[1]), 0.05 * v_rms),
                  max(abs(edge[2]), 0.05 * abs(self.alpha_m) * y_rms, 1e-12))
        start, _ = fit_start(simulate, target, stage.dt, edge, scales, tuning.start_fit_seconds,
                             tuning.start_fit_nfev, n_free=2 if self.alpha_m == 0.0 else 3, offset=offset)
        return start

    def measured_start(self, stage: Stage, u: np.ndarray, fit: bool = True, tuning: EstimatorTuning = DEFAULT_TUNING):
        """:meth:`stage_start` of a stage whose response was recorded as velocity or acceleration,
        judged in that quantity (recon.signals.response_target), never on the integrated
        displacement, whose drift (the integrated sensor noise) is no motion of the structure.

        The edge of the target says whether the stage starts at rest.
        - A velocity as recorded: its value within 5 times its edge noise and its derivative small,
          as the displacement rule judges y0 and y'0 (recon.signals.at_rest). The start is then
          fitted with a constant velocity offset as a nuisance, as every fit in velocity takes it,
          so a sensor's offset is no start in motion.
        - A velocity integrated from an acceleration record: its value within 5 % of its rms or 4
          times its edge noise, since its edge value carries the integration's constant (the line
          removed), an error the white floor does not measure: held to the noise alone, a rest is
          taken for motion and the start is fitted to that error.
        At rest the start is the model's rest (0, 0, 0): a record in velocity cannot see a static
        offset, and the rest is the state a stage recorded from rest is in. Otherwise the start is
        fitted to the stage's first seconds in the target's quantity (recon.simulation.start_state),
        from the edge estimate."""
        order, x = response_target(stage)
        x0, x1, sig, x_rms, sig1, x1_rms = target_edge(stage)
        y0 = start_derivatives(stage)[0]
        if response_order(stage) == order:          # measured as the target's quantity
            rest = at_rest(x0, sig, x1, sig1, x1_rms)
        else:                                       # integrated to it
            rest = abs(x0) < 0.05 * x_rms or abs(x0) < 4 * sig
        v0, a0, v_rms = x0, x1, x_rms
        if rest:
            return 0.0, 0.0, 0.0
        edge = (float(y0), float(v0), float(self.start_z(u[0], y0, v0, a0)))
        if not fit:
            return edge
        t = stage.t - stage.t[0]
        start = self._fitted_start(stage, edge, v_rms, lambda init, n: self.simulate_quantity(t[:n], u[:n], init, order),
                                   x, tuning, offset=response_order(stage) == order)
        return start

    def simulate_quantity(self, t, u, initial=None, order: int = 0, dt: float | None = None) -> np.ndarray:
        """The simulated y^(order) (0: y, 1: y', 2: y'' from the equation of motion) from ``initial``
        (``dt``: as :meth:`simulate`)."""
        y, dy, z = self.simulate(t, u, initial=initial, dt=dt)
        if order == 0:
            return y
        if order == 1:
            return dy
        return self.acceleration(t, u, y, dy, z)

    def acceleration(self, t, u, y, dy, z) -> np.ndarray:
        """y'' = g u - c y' - k y - fn(y, y') - z along a simulated (y, y', z) driven by ``u``."""
        u = np.asarray(u, float)
        if self.input_offset is not None:
            u = u - self.input_offset
        u = self.drive(u, float(np.median(np.diff(t))))
        return self.input_gain * u - self.c_m * dy - self.k_m * y - self.fn(y, dy) - z

    def start_z(self, u0: float, y0: float, v0: float, a0: float) -> float:
        """z at a recorded start (y, y', y''): from the equation of motion when the model has
        hysteresis; 0 when it has none (alpha = 0), since such a z would never decay and would act
        as a permanent force offset."""
        if self.alpha_m == 0.0:
            return 0.0
        return self.balance(u0, y0, v0, a0)

    def balance(self, u0: float, y0: float, v0: float, x: float) -> float:
        """g u - x - c y' - k y - fn(y, y') at one instant: the equation of motion gives z from
        y'' (x = y'') or y'' from z (x = z)."""
        if self.input_offset is not None:
            u0 = u0 - self.input_offset
        return self.input_gain * u0 - x - self.c_m * v0 - self.k_m * y0 - float(
            self.fn(np.array([y0]), np.array([v0]))[0])

    def fit_item(self, stage: Stage, u=None, tuning: EstimatorTuning = DEFAULT_TUNING) -> tuple:
        """``stage`` as the output-error fits take it: (t from 0, u, y, (y0, y0', y0'')). The
        start carries y'' rather than z, so that every trial parameter set gets its own z0
        from :meth:`balance`. A response recorded as velocity or acceleration adds its fifth
        element, (order, target) of recon.signals.response_target: the fits compare the simulated
        y' or y'' with it (recon.output_error.problem.item_target)."""
        u = self.stage_input(stage, tuning=tuning) if u is None else u
        y0, v0, z0 = self.stage_start(stage, u, tuning=tuning)
        item = (stage.t - stage.t[0], u, stage.y, (y0, v0, self.balance(u[0], y0, v0, z0)))
        measured = response_target(stage)
        return item if measured is None else item + (measured,)

    def simulate_measured(self, stage: Stage,
                          tuning: EstimatorTuning = DEFAULT_TUNING) -> tuple[np.ndarray, np.ndarray]:
        """(simulated, recorded) response of the stage in the quantity it was recorded in: y and the
        stage's y for a displacement record, y' or y'' and recon.signals.response_target otherwise.
        What a fit is judged on (validation, the simpler models' scores, adequacy)."""
        measured = response_target(stage)
        if measured is None:
            return self.simulate_stage(stage, tuning)[1], stage.y
        u = self.stage_input(stage, tuning=tuning)
        sim = self.simulate_quantity(stage.t - stage.t[0], u, self.stage_start(stage, u, tuning=tuning), measured[0])
        # a constant velocity offset is a nuisance of the comparison, as in the fits
        # (recon.output_error.problem.measured_error)
        return sim + np.mean(measured[1] - sim), measured[1]

    def simulate_stage(self, stage: Stage, tuning: EstimatorTuning = DEFAULT_TUNING):
        """(t, y_sim) for the stage's recorded input, started from the stage's initial state."""
        u = self.stage_input(stage, tuning=tuning)
        y, _, _ = self.simulate(stage.t - stage.t[0], u, initial=self.stage_start(stage, u, tuning=tuning))
        return stage.t, y

"""In-memory form of a recorded run, shared by the rig (writer) and recon (reader).

A *run* is a set of *stages* (the protocol's steps: ``linear``, ``nonlinear``,
``validation``, ...).  Each stage holds sampled channels on one time base:

- base excitation (the shaker rig): ``x_base`` and ``x_tip`` [m]; the
  relative coordinate is ``y = x_tip - x_base`` and the input per unit mass is
  ``u = -x_base''``.
- force excitation (other labs, the Bouc-Wen benchmark): ``force`` [N] and
  ``x`` [m]; ``y = x`` and ``u = force`` (so ``1/m`` is identified).

Motion channels may be recorded as velocity or acceleration instead of displacement
(``v_tip``, ``a_base``, ``v`` ...; :mod:`shakerlab.quantities`). A stage then keeps the
recorded channels in ``measured`` and their quantities in ``quantities`` (role -> quantity),
and ``channels`` holds the displacement of every role, integrated from the recorded quantity
where it was not recorded as displacement: code that works in displacement reads
``channels`` as before, the signal stage (``recon.signals``) reads ``measured``.

File formats (``.h5`` run files, ``.npz``) are read by :func:`load_run`.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from shakerlab.errors import UserFacingError
from shakerlab.quantities import CONTINUOUS, DISPLACEMENT, PREFIX, channel_name, integrate, parse_channel

BASE = "base"
FORCE = "force"
CHANNELS = {BASE: ("x_base", "x_tip"), FORCE: ("force", "x")}

# a stage name read from a file: a plain name (letters, digits, _ . -), never a path
STAGE_NAME = re.compile(r"[^\W][\w.-]{0,99}")


def check_stage_name(name: str, source) -> str:
    """Refuse a stage name from a file that is not a plain name: no path separators, no ``..``, no
    control characters, at most 100 characters (stage names become output file names)."""
    if not isinstance(name, str) or not STAGE_NAME.fullmatch(name) or ".." in name:
        raise UserFacingError(f"{source}: stage name {name!r} is not a plain name (letters, digits, '_', '.', "
                              f"'-'; no path separators or '..'); the file is refused")
    return name


@dataclass
class Stage:
    """One stage of a run: channels sampled on a common time base ``t`` [s].

    ``channels`` may name a motion channel in any quantity (``x_tip``, ``v_tip``, ``a_tip``);
    after construction ``channels`` holds the displacement of every role, ``measured`` the
    channels recorded as velocity or acceleration and ``quantities`` the recorded quantity of
    every motion role (module docstring)."""

    name: str
    t: np.ndarray
    channels: dict[str, np.ndarray]
    excitation: str = BASE
    settings: dict = field(default_factory=dict)
    measured: dict = field(default_factory=dict)
    quantities: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.excitation not in CHANNELS:
            raise UserFacingError(
                f"stage {self.name!r}: excitation must be 'base' or 'force', got {self.excitation!r}"
            )
        self.t = np.asarray(self.t, dtype=float)
        self._split_quantities()
        missing = [c for c in CHANNELS[self.excitation] if c not in self.channels and c not in self.quantities]
        if missing:
            raise UserFacingError(
                f"stage {self.name!r} ({self.excitation} excitation) lacks channel(s) {', '.join(missing)}"
            )
        for name, values in list(self.channels.items()):
            values = np.asarray(values, dtype=float)
            if values.shape != self.t.shape:
                raise UserFacingError(
                    f"stage {self.name!r}: channel {name!r} has {values.size} samples, t has {self.t.size}"
                )
            if not np.all(np.isfinite(values)):
                bad = int(np.flatnonzero(~np.isfinite(values))[0])
                raise UserFacingError(
                    f"stage {self.name!r}: channel {name!r} has a non-finite value at sample {bad}"
                )
            self.channels[name] = values
        if self.t.size < 2 or np.any(np.diff(self.t) <= 0):
            raise UserFacingError(f"stage {self.name!r}: time must increase strictly")
        for role, quantity in self.quantities.items():
            if quantity != DISPLACEMENT:
                self.measured[channel_name(role, quantity)] = self.channels.pop(channel_name(role, quantity))
                name = channel_name(role, quantity)
                start = (self.settings.get("integration_start_m", {}).get(name)
                         if self.settings.get("integration") == CONTINUOUS else None)
                self.channels[role] = integrate(self.measured[name], self.dt, quantity, start)[0]

    def _split_quantities(self) -> None:
        """Fill ``quantities`` from the channel names; one quantity per role."""
        self.channels = dict(self.channels)
        self.channels.update(self.measured)        # a Stage rebuilt from another's recorded channels
        self.measured = {}
        found: dict[str, list[str]] = {}
        for name in self.channels:
            parsed = parse_channel(name)
            if parsed is not None:
                found.setdefault(parsed[0], []).append(name)
        roles = [r for r in CHANNELS[self.excitation] if r != "force"]
        for role in roles:
            names = found.get(role, [])
            if len(names) > 1:
                raise UserFacingError(
                    f"stage {self.name!r}: {' and '.join(sorted(names))} measure the same point; give one of them"
                )
            if names:
                self.quantities[role] = parse_channel(names[0])[1]
        missing = [r for r in roles if r not in self.quantities]
        if missing:
            # the displacement names first (the message of a displacement-only stage is unchanged)
            names = [channel_name(r, DISPLACEMENT) for r in CHANNELS[self.excitation]
                     if r not in self.quantities and r not in self.channels]
            others = ", ".join("|".join(channel_name(r, q) for q in PREFIX) for r in missing)
            raise UserFacingError(f"stage {self.name!r} ({self.excitation} excitation) lacks channel(s) "
                                  f"{', '.join(names)} (a motion channel may be {others})")

    def recorded(self) -> dict[str, np.ndarray]:
        """The channels as recorded (displacement roles as they are, the others in their quantity)."""
        out = {}
        for name, values in self.channels.items():
            q = self.quantities.get(name, DISPLACEMENT)
            out[channel_name(name, q) if q != DISPLACEMENT else name] = (
                values if q == DISPLACEMENT else self.measured[channel_name(name, q)])
        return out

    def derived(self, what, make):
        """``make()``, a quantity derived from this stage's recorded samples alone (a filter, an
        input, a start estimate), made once and kept while ``t`` and every channel are the same
        arrays. A stage's samples are not changed in place after it is made; an array that is
        replaced (a new ``t`` or channel) makes the quantity again. Arrays kept are read-only."""
        arrays = (self.t, *self.channels.values(), *self.measured.values())
        cache = self.__dict__.setdefault("_derived", {})
        hit = cache.get(what)
        if hit is not None and len(hit[0]) == len(arrays) and all(a is b for a, b in zip(hit[0], arrays)):
            return hit[1]
        value = make()
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
        cache[what] = (arrays, value)
        return value

    @property
    def dt(self) -> float:
        return self.derived("dt", lambda: float(np.median(np.diff(self.t))))

    @property
    def fs(self) -> float:
        return 1.0 / self.dt

    @property
    def y(self) -> np.ndarray:
        """The relative displacement the model is written in [m]."""
        if self.excitation == BASE:
            return self.channels["x_tip"] - self.channels["x_base"]
        return self.channels["x"]


@dataclass
class Run:
    """A recorded run: ordered stages plus run-level metadata."""

    stages: dict[str, Stage]
    attrs: dict = field(default_factory=dict)
    source: str = ""

    def stage(self, name: str) -> Stage:
        try:
            return self.stages[name]
        except KeyError:
            raise UserFacingError(
                f"{self.source or 'run'}: no stage {name!r} (stages: {', '.join(self.stages) or 'none'})"
            ) from None

    @property
    def excitation(self) -> str:
        kinds = {s.excitation for s in self.stages.values()}
        if len(kinds) != 1:
            raise UserFacingError(f"{self.source or 'run'}: stages mix excitation kinds {sorted(kinds)}")
        return kinds.pop()

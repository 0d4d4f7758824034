"""In-memory form of a recorded run, shared by the rig (writer) and recon (reader).

A *run* is a set of *stages* (the protocol's steps: ``linear``, ``nonlinear``,
``validation``, ...).  Each stage holds sampled channels on one time base:

- base excitation (the shaker rig): ``x_base`` and ``x_tip`` [m]; the
  relative coordinate is ``y = x_tip - x_base`` and the input per unit mass is
  ``u = -x_base''``.
- force excitation (other labs, the Bouc-Wen benchmark): ``force`` [N] and
  ``x`` [m]; ``y = x`` and ``u = force`` (so ``1/m`` is identified).

File formats (``.h5`` run files, ``.npz``) are read by :func:`load_run`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from shakerlab.errors import UserFacingError

BASE = "base"
FORCE = "force"
CHANNELS = {BASE: ("x_base", "x_tip"), FORCE: ("force", "x")}


@dataclass
class Stage:
    """One stage of a run: channels sampled on a common time base ``t`` [s]."""

    name: str
    t: np.ndarray
    channels: dict[str, np.ndarray]
    excitation: str = BASE
    settings: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.excitation not in CHANNELS:
            raise UserFacingError(
                f"stage {self.name!r}: excitation must be 'base' or 'force', got {self.excitation!r}"
            )
        self.t = np.asarray(self.t, dtype=float)
        missing = [c for c in CHANNELS[self.excitation] if c not in self.channels]
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

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.t)))

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

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
from pathlib import Path

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


def load_npz(path: str | Path) -> Run:
    """Read an ``.npz`` run: arrays named ``<stage>/<channel>`` or ``<stage>_<channel>``.

    Channels per stage: ``t`` plus ``x_base, x_tip`` (base excitation) or
    ``force, x`` (force excitation).
    """
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's problem
        raise UserFacingError(f"{path}: not a readable .npz file ({exc})") from None
    grouped: dict[str, dict[str, np.ndarray]] = {}
    for key in data.files:
        for sep in ("/", "_"):
            stage, _, channel = key.partition(sep)
            if channel in ("t", "x_base", "x_tip", "force", "x"):
                grouped.setdefault(stage, {})[channel] = data[key]
                break
    if not grouped:
        raise UserFacingError(f"{path}: no stage arrays (expected names like 'linear/t', 'linear/x_tip')")
    stages = {}
    for name, ch in grouped.items():
        if "t" not in ch:
            raise UserFacingError(f"{path}: stage {name!r} has no time array 't'")
        excitation = FORCE if "force" in ch else BASE
        t = ch.pop("t")
        stages[name] = Stage(name=name, t=t, channels=ch, excitation=excitation)
    return Run(stages=stages, source=str(path))


def save_npz(run: Run, path: str | Path) -> None:
    arrays = {}
    for name, st in run.stages.items():
        arrays[f"{name}/t"] = st.t
        for ch, v in st.channels.items():
            arrays[f"{name}/{ch}"] = v
    np.savez(path, **arrays)


def load_run(path: str | Path) -> Run:
    """Load a run from ``.h5`` (shakerlab run file) or ``.npz``."""
    path = Path(path)
    if not path.exists():
        raise UserFacingError(f"{path}: no such file")
    if path.suffix == ".npz":
        return load_npz(path)
    if path.suffix in (".h5", ".hdf5", ".nxs"):
        from shakerlab import recording  # the HDF5 run-file format

        return recording.read_run(path)
    raise UserFacingError(f"{path}: unknown run file type {path.suffix!r} (expected .h5 or .npz)")

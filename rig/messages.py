"""The messages a plan yields and the runner executes (the bluesky idea, kept small).

A plan is a generator: ``result = yield Message(...)``. The runner executes
each message against the instruments and sends back its result (only
:class:`Acquire` returns something: the samples of its window). A plan never
touches an instrument itself, so the same plan runs headless, in the GUI and
in tests, and the runner can pause, abort and supervise it anywhere.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


# the protocol's default pre-trigger (``[run] pre_trigger_s``): recorded rest at the start of every stage
PRE_TRIGGER_S = 0.1


@dataclass(frozen=True)
class BeginStage:
    """Start recording a stage; ``settings`` go into the run file with it.

    ``pre_trigger_s`` > 0: the runner first records that long at the current state (at least
    that long, in whole acquisition blocks) before it executes the plan's next message, so a
    stage that a plan begins after a :class:`Rest` opens with the specimen at rest and the drive
    switched on inside the record (the stage's first setpoint in its ``steps``), never before
    its first sample. 0: the stage's first sample is the next one acquired.
    """

    name: str
    settings: dict = field(default_factory=dict)
    pre_trigger_s: float = 0.0


@dataclass(frozen=True)
class EndStage:
    """Ramp the output to zero, switch it off, and close the stage with a summary."""

    summary: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SetFrequency:
    """Change the drive frequency (the amplitude is unchanged)."""

    hz: float


@dataclass(frozen=True)
class CheckSetpoint:
    """Refuse (the run stops, ramped down, with the reason) unless the rig's limits allow this drive.

    Plans yield it as soon as they derive a setpoint from measured data (the
    resonance found, the nonlinear stage's final level), before the stage that
    uses it begins. ``origin`` says how the setpoint was derived.
    """

    vpp: float | None
    hz: float | None
    origin: str


@dataclass(frozen=True)
class Ramp:
    """Ramp the generator amplitude to ``vpp`` at the configured rate, acquiring meanwhile.

    Switches the output on first (at the lowest amplitude) when it is off.
    """

    vpp: float
    label: str = ""


@dataclass(frozen=True)
class Acquire:
    """Hold the current setpoint for ``duration_s`` and return the window's samples (:class:`Window`).

    A pause inside the window restarts it after resuming, so the window is
    always uninterrupted steady excitation.
    """

    duration_s: float


@dataclass(frozen=True)
class Rest:
    """Output off (ramped down first) for ``duration_s``; samples are not recorded outside a stage."""

    duration_s: float


@dataclass(frozen=True)
class Log:
    level: str
    message: str


@dataclass(frozen=True)
class Checkpoint:
    """A safe place to pause between steps."""


@dataclass(frozen=True)
class ControlSine:
    """Closed-loop sine (:mod:`rig.sine_control`): hold the base motion's fundamental at
    ``target_m`` (peak, metres) at the current frequency, correcting the generator amplitude once
    per analysis window; ``duration_s`` counts from the moment it is on target (within the
    tolerance). Returns a :class:`rig.sine_control.ControlResult` whose ``window`` is the last
    ``analysis_s`` (all of ``duration_s`` when 0).

    ``max_tip_m`` / ``max_relative_m``: response ceilings (notching: the base target is lowered).
    A correction beyond ``limits.max_generator_vpp`` is refused: ``on_refusal="stop"`` ends the
    run safely (status tripped, the stage records why); ``"return"`` leaves the output at its
    current (allowed) level and returns the result with ``refused`` set.
    """

    target_m: float
    duration_s: float
    analysis_s: float = 0.0
    label: str = ""
    max_tip_m: float | None = None
    max_relative_m: float | None = None
    on_refusal: str = "stop"
    settle_timeout_s: float | None = None


@dataclass
class Window:
    """The samples an :class:`Acquire` returns."""

    index0: int
    fs: float
    x_base: np.ndarray
    x_tip: np.ndarray
    amplitude_vpp: float
    frequency_hz: float

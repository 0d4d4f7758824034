"""What a candidate of the catalog is: one kind of missing physics, everything about it in one place.

A candidate module (one per id in this folder) defines ``CANDIDATE``, a :class:`Candidate` with:

- its words: ``explanation`` (what it is, for the user), ``adds`` (the term or model change),
  ``simulated`` (how the augmented model simulates it);
- ``parameters``: the keys reported for it (``fn:<term>``, ``x:<extra>`` of
  recon.diagnosis.augmented.EXTRAS, or a baseline key such as ``alpha_m``), the first one being
  its size;
- ``kernel``: the slots of the simulation kernel's parameter vector (recon.simulation.rk4.P_NAMES)
  its parameters set, by name (an extra that is a slot reaches it under its own name, augmented.py
  KERNEL_EXTRAS); none for a library term (the kernel's fn coefficients) or a reading change;
- ``starts(baseline, ctx)``: where its fit starts, a list of (AugmentedModel, new free keys,
  scales, bounds), several when the fit is multimodal (ctx: locate.py's context of the record);
- ``applies(baseline, ctx)``: whether it can be added to this baseline;
- ``check(model, data)``: why a fitted model is not physical for this candidate ([] if it is);
- ``signature``: the kinds of located findings (locate.py) that are evidence for it;
- ``amplitude_dependent``: whether its effect changes with amplitude at one frequency (how two
  candidates are told apart: recon.diagnosis.ambiguity);
- ``conceal(truth, baseline, strength)``: how to hide it in a synthetic truth (the contract test
  and recon.testing.concealed): changes ``truth`` and ``baseline`` in place and returns the
  truth's extras; the size ``strength`` 1 raises the baseline's error by a few per cent;
- the fit's options (``screen_keys``, ``column``, ``screen_output``, ``admissible_starts``,
  ``fit_each``, ``hysteresis_absorbs``, ``even_stiffness_absorbs``), described on the fields.

docs/diagnosis.md ("Adding a candidate") says how to add one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from recon.diagnosis.augmented import AugmentedModel
from recon.model import HystereticModel


def never(model, data) -> list[str]:
    """A candidate with no physical range of its own beyond the common checks."""
    return []


@dataclass(frozen=True)
class Candidate:
    id: str
    explanation: str
    adds: str
    simulated: str
    parameters: tuple           # the keys reported for it; the first is its size
    starts: Callable
    applies: Callable = lambda base, ctx: True
    check: Callable = never     # (fitted AugmentedModel, stage data) -> reasons it is not physical
    signature: tuple = ()       # located finding kinds that are evidence for it (locate.py)
    amplitude_dependent: bool = False   # its effect changes with amplitude at one frequency
    conceal: Callable | None = None     # (truth, baseline, strength) -> truth's extras (module doc)
    screen_keys: int = 99       # with several starts: how many of the new keys the screening frees
    column: Callable | None = None   # col(am, t, y, dy): the term's regressor when linear in its first key
    screen_output: bool = False      # with a column and several starts: pick the start by a short output-error fit
    admissible_starts: Callable | None = None   # starts inside the physical range, tried when a fit ends implausible
    fit_each: str | None = None      # an extra the fit cannot move (discrete): fitted once per value, the best kept
    # an effect a reconstructed Bouc-Wen law can take up (a dissipation: its |y'| z terms dissipate more
    # at larger amplitude; or a reading error: a law the record does not hold fits part of it): also
    # fitted from the baseline without its hysteresis (diagnose.hysteresis_free_core)
    hysteresis_absorbs: bool = False
    # a one-sided stiffness the reconstruction may have made even-powered stiffness terms of (y^2, y^4:
    # the asymmetric part of the force): also fitted from the baseline without them
    # (diagnose.even_stiffness_free_core)
    even_stiffness_absorbs: bool = False
    # the kernel slots (recon.simulation.rk4.P_NAMES) its parameters set: its contribution to the
    # simulation kernel, by name (module doc)
    kernel: tuple = ()


def start_model(base: HystereticModel, extras: dict, cid: str) -> AugmentedModel:
    """The baseline (copied) with ``extras``, marked as augmented by ``cid``."""
    return AugmentedModel(HystereticModel.from_dict(base.to_dict()), dict(extras), [cid])


def fn_term_starts(term: str, cid: str, scale_of: Callable):
    """Starts of a candidate that is one fn term: the term at 0, on the scale ``scale_of(ctx)``."""
    def starts(base, ctx):
        m = start_model(base, {}, cid)
        m.baseline.fn_m[term] = 0.0
        return [(m, [f"fn:{term}"], {f"fn:{term}": scale_of(ctx)}, {})]
    return starts

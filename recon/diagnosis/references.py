"""What every candidate is measured against, and where candidate fits start.

The *null model* is the baseline with every parameter refitted by output error; the *reference*
is the better, on the held-out samples, of the null model and the baseline as given. A candidate
gets credit only for what it predicts better than the reference, and than every other null model
(a fit of the baseline alone from some other start, :class:`Origins`.nulls).

Candidate fits start from several *origins* (:class:`Origin`): the reference, the other of the
two, and cores of the baseline with a part the reconstruction may have made of the missing
physics taken out (its fn terms, its Bouc-Wen law, its even stiffness terms). Each core is also a
null model, so a candidate gets no credit for what taking that part out does alone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.candidate_fit import CANDIDATE_FAILURES
from recon.diagnosis.catalog import CATALOG
from recon.diagnosis.settings import DEFAULTS, DiagnosisSettings
from recon.library import monomials
from shakerlab.errors import UserFacingError
from shakerlab.run_data import Run

# the baseline's parameters a candidate fit frees when it starts from the baseline as given
GIVEN_FREE = ("c_m", "k_m")
HYSTERESIS_KEYS = ("alpha_m", "gamma", "delta")


@dataclass(frozen=True)
class References:
    """The baseline and the fits every candidate is compared with."""
    base: AugmentedModel             # the baseline as given
    kind: str                        # "paper", "linear", "model" or the model file
    data: list                       # rank.prepare's stage data
    null: rank.FitResult             # every baseline parameter refitted
    given: rank.FitResult            # the baseline as given, scored the same way
    refit_better: bool               # the null model predicts the held-out samples better than given

    @property
    def ref(self) -> rank.FitResult:
        """The reference: the better of the null model and the baseline as given."""
        return self.null if self.refit_better else self.given

    @property
    def ref_name(self) -> str:
        return "refit" if self.refit_better else "as_given"

    @property
    def bkeys(self) -> list:
        """The baseline's own parameters (rank.baseline_keys)."""
        return rank.baseline_keys(self.base.baseline)

    @property
    def full_free(self) -> list:
        """Every free parameter of the baseline, its extras' included (:func:`every_parameter`)."""
        return every_parameter(self.base)


@dataclass(frozen=True)
class Origin:
    """A start for candidate fits: a fit of the baseline, the baseline keys freed beside the
    candidate's, those an equation-error step may move, and its name (an entry's started_from)."""
    fit: rank.FitResult
    free: list
    step_keys: list
    name: str


@dataclass
class Origins:
    """Where candidate fits start, and the null models found on the way."""
    common: list                                     # every candidate starts from these
    without_hysteresis: list = field(default_factory=list)       # catalog: hysteresis_absorbs
    without_even_stiffness: list = field(default_factory=list)   # catalog: even_stiffness_absorbs
    even_terms: tuple = ()                           # the baseline's even stiffness terms
    core: rank.FitResult | None = None               # the linear core, when fitted
    nulls: list = field(default_factory=list)        # null models a candidate must beat too

    def for_candidate(self, cand) -> list:
        return (self.common + (self.without_hysteresis if cand.hysteresis_absorbs else [])
                + (self.without_even_stiffness if cand.even_stiffness_absorbs else []))


def every_parameter(base: AugmentedModel) -> list[str]:
    """Every free parameter of the baseline: its own (rank.baseline_keys) and its extras' (but v0 and
    side, which a candidate's fit sets)."""
    return rank.baseline_keys(base.baseline) + [f"x:{k}" for k in base.extras if k not in ("v0", "side")]


def without_terms(am: AugmentedModel, drop: tuple) -> AugmentedModel:
    """A copy of ``am`` without the baseline fn terms ``drop``."""
    m = am.copy()
    for t in drop:
        m.baseline.fn_m.pop(t, None)
    return m


def reference_fits(run: Run, base: AugmentedModel, max_nfev: int, settings: DiagnosisSettings = DEFAULTS):
    """(stage data, the null model: every baseline parameter refitted, the baseline as given scored
    the same way with no parameter moved)."""
    data = rank.prepare(run, base.baseline, settings)
    null = rank.fit(base, every_parameter(base), data, max_nfev=max_nfev)
    given = rank.fit(base, [], data)
    return data, null, given


def check_null(null, data, run) -> None:
    """The null model (the baseline refitted) must simulate every stage and leave held-out samples."""
    if null.n_held == 0:
        raise UserFacingError(f"{run.source or 'run'}: no held-out samples to compare models on (stages "
                              f"{', '.join(d.name for d in data)}); record a validation stage or longer stages")
    if not math.isfinite(null.mse_held):
        bad = [d for d in data if not np.isfinite(null.nrmse.get(d.name, np.nan))]
        where = ", ".join(d.name for d in bad) or ", ".join(d.name for d in data)
        raise UserFacingError(f"{run.source or 'run'}: the baseline refitted by output error does not simulate "
                              f"stage(s) {where} (the simulation diverged); try --baseline linear or a saved model")


def references_of(base: AugmentedModel, kind: str, data: list, null: rank.FitResult,
                  given: rank.FitResult) -> References:
    """The references of a baseline whose null model simulates. When the refit predicts the
    held-out samples worse than the baseline as given (it absorbed the effect, or one tone per
    stage leaves it poorly determined), the baseline as given is the reference and its own
    parameters stay as given in candidate fits, so a candidate gets no credit for undoing a refit."""
    refit_better = (math.isfinite(null.mse_held)
                    and not (math.isfinite(given.mse_held) and given.mse_held <= null.mse_held))
    return References(base=base, kind=kind, data=data, null=null, given=given, refit_better=refit_better)


def candidate_origins(refs: References, ids: list, max_nfev: int,
                      settings: DiagnosisSettings = DEFAULTS) -> Origins:
    """Where the candidates ``ids`` start (module docstring). From the reference, candidate fits
    free every baseline parameter when it is the null model, else only c and k (where a baseline
    reconstructed from the same data absorbs an effect, friction as extra viscous damping); then
    the other of the two; the baseline as given with only the term free when the refit is worse;
    and the cores of the baseline the candidates' catalog entries ask for."""
    base, data, ref, null, given = refs.base, refs.data, refs.ref, refs.null, refs.given
    bkeys, full_free = refs.bkeys, refs.full_free
    base_free = full_free if refs.refit_better else list(GIVEN_FREE)
    common = [Origin(ref, base_free, bkeys if refs.refit_better else list(GIVEN_FREE), refs.ref_name)]
    if not refs.refit_better and math.isfinite(null.mse_held):
        # a refit that is worse alone may be right with the missing term
        common.append(Origin(null, full_free, bkeys, "refit"))
    elif refs.refit_better and math.isfinite(given.mse_held):
        # a refit that is better alone can lead a candidate's fit astray (c and k can run far from
        # their true values beside an offset and the held-out simulation diverge)
        common.append(Origin(given, list(GIVEN_FREE), list(GIVEN_FREE), "as_given"))
    if not refs.refit_better:
        # where refitting the baseline hurts the held-out samples, c and k moved beside the term can
        # too (a stage every model misfits holds the fitting cost, and c and k trade the other
        # stages for it): the term alone
        common.append(Origin(given, [], [], "term_alone"))
    out = Origins(common=common)
    if ref.nrmse_held > settings.linear_core_nrmse:
        # a reference that misses most of the response is no place for a local fit to start from
        # (a baseline whose opposite-signed fn terms stand in for a friction its library lacks holds
        # the friction's term at 0); from the linear core the term can reach its value
        out.core = linear_core(base, data, bkeys, max_nfev)
    if out.core is not None:
        common.append(Origin(out.core, full_free, bkeys, "linear_core"))
        out.nulls.append(out.core)
    out.even_terms = tuple(even_stiffness_terms(base))
    if any(CATALOG[c].hysteresis_absorbs for c in ids if c in CATALOG):
        # a Bouc-Wen law the reconstruction may have made of a missing dissipation, or of part of a
        # reading error: the dissipative candidates and the sensor scale start without it too
        loopless_free = [k for k in full_free if k not in HYSTERESIS_KEYS]
        unlooped = hysteresis_free_core(base, data, loopless_free, max_nfev)
        if unlooped is not None:
            out.nulls.append(unlooped)
            out.without_hysteresis.append(Origin(unlooped, loopless_free,
                                                 [k for k in bkeys if k not in HYSTERESIS_KEYS],
                                                 "without_hysteresis"))
    if any(CATALOG[c].even_stiffness_absorbs for c in ids if c in CATALOG):
        # even stiffness terms the reconstruction may have made of a one-sided stiffness
        even = {f"fn:{t}" for t in out.even_terms}
        evenless_free = [k for k in full_free if k not in even]
        evenless = even_stiffness_free_core(base, out.even_terms, data, evenless_free, max_nfev)
        if evenless is not None:
            out.nulls.append(evenless)
            out.without_even_stiffness = [Origin(evenless, evenless_free, [k for k in bkeys if k not in even],
                                                 "without_even_stiffness")]
    return out


def linear_core(base: AugmentedModel, data, bkeys: list, max_nfev: int) -> rank.FitResult | None:
    """The baseline with its fn terms at 0 (kept in the model, so a fit frees them) and its linear
    terms refitted by output error; None without fn terms or when the fit fails."""
    if not base.baseline.fn_m:
        return None
    m = base.copy()
    for k in m.baseline.fn_m:
        m.baseline.fn_m[k] = 0.0
    return core_fit(m, [k for k in bkeys if k in GIVEN_FREE + ("inv_m",)], data, max_nfev)


def core_fit(m: AugmentedModel, free: list, data, max_nfev: int) -> rank.FitResult | None:
    """``m`` with ``free`` refitted by output error; None when the fit fails or predicts no held-out
    sample (a core: a null model and a place for candidate fits to start from)."""
    try:
        fr = rank.fit(m, free, data, max_nfev=max_nfev)
    except CANDIDATE_FAILURES:
        return None
    return fr if math.isfinite(fr.mse_held) and fr.n_held > 0 else None


def hysteresis_free_core(base: AugmentedModel, data, free: list, max_nfev: int) -> rank.FitResult | None:
    """The baseline without its Bouc-Wen law: alpha folded into k (the loop's small-amplitude
    stiffness is k + alpha), alpha, gamma and delta at 0 and held there, ``free`` (keys without
    HYSTERESIS_KEYS) refitted by output error. None for a baseline without hysteresis or when the
    fit fails.

    A reconstructed Bouc-Wen law can take up a dissipation it does not hold: its |y'| z terms
    dissipate more at larger amplitude, as quadratic damping or friction does. From such a
    baseline, and from its refit, the candidate's own term stays at 0; from this core it can reach
    its true value."""
    if base.baseline.alpha_m == 0.0:
        return None
    m = base.copy()
    b = m.baseline
    b.k_m += b.alpha_m
    b.alpha_m = b.gamma = b.delta = 0.0
    return core_fit(m, free, data, max_nfev)


def even_stiffness_terms(base: AugmentedModel) -> list[str]:
    """The baseline's fn terms even in y and free of y' (y^2, y^4, ...): the asymmetric part of its
    restoring force."""
    out = []
    for t in base.baseline.fn_m:
        p, r = monomials.parse(t)
        if r == 0 and p >= 2 and p % 2 == 0:
            out.append(t)
    return out


def even_stiffness_free_core(base: AugmentedModel, drop: tuple, data, free: list,
                             max_nfev: int) -> rank.FitResult | None:
    """The baseline without its even stiffness terms ``drop`` (even_stiffness_terms), ``free`` (keys
    without theirs) refitted by output error. None for a baseline without them or when the fit fails.

    A reconstructed y^2 or y^4 can take up a one-sided contact (the even part of its force); a
    contact fitted on top of it then has nothing left to explain (the even terms can fit the
    fitting stages better than the true contact while predicting the held-out stage worse, and the
    contact fitted beside them stays far below its true stiffness)."""
    if not drop:
        return None
    return core_fit(without_terms(base, drop), free, data, max_nfev)

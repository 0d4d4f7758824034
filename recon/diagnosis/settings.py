"""The diagnosis's settings: the significance rule and how a record is split, weighted and fitted.

Every number the diagnosis decides with lives here, in two frozen objects, each field with its
meaning, unit and allowed range (checked when the object is made):

- :class:`SignificanceRule`: when a candidate's held-out improvement over its reference counts
  (recon.diagnosis.rank's module doc gives the figures it reads);
- :class:`DiagnosisSettings`: the rule, how a record is split into fitting and held-out
  samples, how its stages are weighted, how a stage recorded in motion starts, the search's
  own numbers (where candidate fits start, which refits are tried, how long a screening fit runs),
  how the mismatch is located, and when the answer calls two candidates ambiguous or a loop a
  friction law.

``recon.diagnose(run, settings=DiagnosisSettings(...))`` uses them; the defaults are the
calibrated ones (docs/diagnosis.md, "How the rule was set"). A test or a study that asks another
value makes another object (``dataclasses.replace``); no module holds a tuned number of its own.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from recon.settings_fields import bounded as _f, check as _check, describe

__all__ = ["SignificanceRule", "DiagnosisSettings", "DEFAULT_RULE", "DEFAULTS", "describe"]


@dataclass(frozen=True)
class SignificanceRule:
    """When a candidate's held-out improvement over its reference is significant (rank.score's
    figures: dBIC, explained, gain over the noise, relative cut of the NRMSE, share of pieces
    improved). Every candidate needs the BIC margin and the explained share; it then passes by the
    large-gain, the steady or the unanimous route (:meth:`passes`)."""
    bic_margin: float = _f(10.0, "held-out BIC improvement every candidate needs (dBIC < -margin)",
                           "BIC units (n_eff ln MSE ratio + k ln n_eff)", 0.0, 1e3)
    min_explained: float = _f(0.15, "share of the reference's excess over the noise floor the candidate "
                              "must remove", "fraction", 0.0, 1.0)
    min_gain_noise: float = _f(1.5, "large-gain route: mean-square cut of the held-out error",
                               "noise variances", 0.0, 1e6)
    min_rel_gain: float = _f(0.1, "large-gain route: relative cut of the held-out NRMSE", "fraction", 0.0, 1.0)
    held_blocks: int = _f(10, "equal consecutive pieces the held-out samples are cut into for the "
                          "steady and unanimous routes", "pieces", 1, 1000)
    consistent_blocks: float = _f(0.9, "steady route: share of the pieces the candidate must improve",
                                  "fraction", 0.0, 1.0)
    steady_gain: float = _f(0.1, "steady route: mean-square cut of the held-out error", "noise variances",
                            0.0, 1e6)
    steady_rel_gain: float = _f(0.04, "steady route: relative cut of the held-out NRMSE", "fraction", 0.0, 1.0)
    complete_blocks: float = _f(1.0, "unanimous route: share of the pieces the candidate must improve",
                                "fraction", 0.0, 1.0)
    complete_explained: float = _f(0.4, "unanimous route: share of the excess over the noise removed "
                                   "(at most all of it)", "fraction", 0.0, 1.0)
    complete_gain: float = _f(0.04, "unanimous route: mean-square cut of the held-out error",
                              "noise variances", 0.0, 1e6)
    complete_rel_gain: float = _f(0.02, "unanimous route: relative cut of the held-out NRMSE", "fraction",
                                  0.0, 1.0)
    stage_level: float = _f(0.01, "never worse on a held-out stage: the chance, shared among the held-out "
                            "stages, that noise alone makes a model no worse than the baseline look worse "
                            "on one (recon.diagnosis.stagewise)", "probability", 0.0, 1.0, lo_open=True)

    def __post_init__(self):
        _check(self)
        if int(self.held_blocks) != self.held_blocks:
            raise ValueError(f"SignificanceRule.held_blocks must be a whole number of pieces, not {self.held_blocks!r}")

    def smallest_gain(self) -> float:
        """The least mean-square cut of the held-out error, in noise variances, that any route
        counts: a mismatch whose mean square is below it cannot make a candidate significant."""
        return min(self.min_gain_noise, self.steady_gain, self.complete_gain)

    def passes(self, dbic: float, explained: float, gain: float, rel: float, blocks: float | None = None) -> bool:
        """The rule on a candidate's held-out figures: the BIC margin and the share of the excess
        explained, then either the large gain with its relative cut, or, for a candidate that
        helps on ``consistent_blocks`` of the pieces (``blocks``; None closes the two block
        routes), the steady gain and cut, or, for one that helps on every piece and removes at
        least ``complete_explained`` of the excess without going below the noise floor, the
        unanimous gain and cut."""
        if not (dbic < -self.bic_margin and explained >= self.min_explained):
            return False
        steady = blocks is not None and blocks >= self.consistent_blocks
        complete = (blocks is not None and blocks >= self.complete_blocks
                    and self.complete_explained <= explained <= 1.0)
        return bool((rel >= self.min_rel_gain and gain >= self.min_gain_noise)
                    or (steady and gain >= self.steady_gain and rel >= self.steady_rel_gain)
                    or (complete and gain >= self.complete_gain and rel >= self.complete_rel_gain))

    def smallest_relative_cut(self) -> float:
        """The smallest relative cut of the held-out NRMSE that any route accepts."""
        return min(self.min_rel_gain, self.steady_rel_gain, self.complete_rel_gain)


@dataclass(frozen=True)
class DiagnosisSettings:
    """The significance rule, how the diagnosis splits, weights and starts a record's stages, and
    the numbers its search for candidate fits is tuned with."""
    rule: SignificanceRule = field(default_factory=SignificanceRule)
    hold_fraction: float = _f(0.3, "share at the end of a stage held out when the run has no validation "
                              "stage reaching it", "fraction", 0.0, 1.0, lo_open=True)
    cover_share: float = _f(0.4, "a validation stage whose peak is below this share of a fitting stage's "
                            "peak leaves that stage's top untested (its end is held out too)", "fraction",
                            0.0, 1.0)
    top_reach: float = _f(0.9, "a partly held-out stage whose fitting part stays below this share of its "
                          "peak fits the first half of its top level too", "fraction", 0.0, 1.0)
    burn_in_decays: float = _f(3.0, "decay times of the mode (2 / c each) a fitting stage recorded in "
                               "motion leaves out of the fit (0: none)", "decay times", 0.0, 100.0)
    burn_in_keep: float = _f(0.3, "the burn-in applies only if at least this share of the stage's "
                             "fitting samples remains", "fraction", 0.0, 1.0)
    fit_model_share: float = _f(1e-3, "each stage's fitting error is divided by hypot(noise floor, this "
                                "share of its rms): an allowance for model error beside the noise",
                                "fraction of rms", 0.0, 1.0)
    fit_rate: float = _f(2000.0, "the fits' iterations simulate a stage sampled faster than twice this rate "
                         "on every q-th sample (rate >= this); the start choice and every held-out figure "
                         "use every sample (0: never thin)", "Hz", 0.0, 1e7)
    stop_chi2: float = _f(0.01, "a fit stops after an iteration that lowers its cost by less than this many "
                          "chi-square units of its own likelihood (recon.output_error.stopping)",
                          "chi-square units", 0.0, 1e3, lo_open=True)
    # where candidate fits start and what they are refitted without (recon.diagnosis.references,
    # candidate_fit, refits)
    linear_core_nrmse: float = _f(0.7, "a reference whose held-out NRMSE is above this explains less than half "
                                  "of the held-out variance: candidate fits also start from the baseline's "
                                  "linear core (fn terms at 0, c and k refitted)", "NRMSE", 0.0, 1e3)
    follow_on_share: float = _f(0.5, "a candidate fitted from the baseline as given (c and k free) that leaves "
                                "at most this share of its start's fitting cost is fitted again with every "
                                "baseline parameter free", "fraction", 0.0, 1.0)
    prune_fit_share: float = _f(0.9, "a candidate whose fit leaves at most this share of the reference's "
                                "fitting cost is refitted without the baseline fn terms that may have "
                                "absorbed it", "fraction", 0.0, 1.0)
    prune_pairs_up_to: int = _f(5, "baseline fn terms up to which a candidate is also refitted without each "
                                "pair of them", "terms", 0, 100)
    revision_steps: int = _f(4, "moves at most of the baseline's fn terms chosen again under a candidate "
                             "(term_revision.py)", "moves", 0, 50)
    revision_tries: int = _f(2, "moves a revision step tries by actual refit, best predicted first, before it "
                             "stops", "refits", 1, 50)
    start_screen_nfev: int = _f(5, "short output-error fit of a candidate's new terms that ranks its starts",
                                "function evaluations", 1, 1000)
    output_screen_nfev: int = _f(8, "short output-error fit that ranks starts differing in a fixed shape "
                                 "parameter, or a start moved inside its term's physical bound",
                                 "function evaluations", 1, 1000)
    shape_screen_nfev: int = _f(6, "short output-error fit of the new terms that ranks equation-stepped "
                                "starts differing in a fitted shape parameter", "function evaluations", 1, 1000)
    step_min_finite: float = _f(0.9, "an equation-error step (a candidate's linear start) is taken only where the "
                                "equation residual is finite on at least this share of the fitting samples",
                                "fraction", 0.0, 1.0)
    # how a held-out stage recorded in motion starts (recon.diagnosis.rank.held_start)
    start_fit_share: float = _f(0.3, "a held-out stage recorded in motion: each model's start state is fitted "
                                "on this first share of the stage (at least 10 samples)", "fraction", 0.0, 1.0,
                                lo_open=True)
    start_fit_nfev: int = _f(10, "the output-error fit of that start state", "function evaluations", 1, 1000)
    # where the reference misses (recon.diagnosis.locate)
    time_segments: int = _f(8, "equal consecutive pieces a stage's simulation residual is cut into to find "
                            "where in time it misses and whether it trends", "pieces", 1, 1000)
    band_power: float = _f(0.999, "the top of an input's band is the frequency below which this share of its "
                           "power lies (a mode start is placed twice above it)", "fraction", 0.0, 1.0,
                           lo_open=True)
    # how the answer is worded (recon.diagnosis.ambiguity, wording)
    model_error_share: float = _f(0.2, "two named candidates are ambiguous when the first's held-out MSE is below the "
                                  "runner-up's by less than this share of its own excess over the noise floor",
                                  "fraction of excess MSE", 0.0, 1.0)
    sliding_share: float = _f(0.95, "a Bouc-Wen loop reads as a friction law when the record travels far enough "
                              "for z to reach this share of its sliding force (below 1)", "fraction", 0.0, 1.0,
                              lo_open=True)

    def __post_init__(self):
        if not isinstance(self.rule, SignificanceRule):
            raise ValueError(f"DiagnosisSettings.rule must be a SignificanceRule, not {type(self.rule).__name__}")
        _check(self)
        for name in ("prune_pairs_up_to", "revision_steps", "revision_tries", "start_screen_nfev",
                     "output_screen_nfev", "shape_screen_nfev", "start_fit_nfev", "time_segments"):
            v = getattr(self, name)
            if int(v) != v:
                raise ValueError(f"DiagnosisSettings.{name} must be a whole number, not {v!r}")
        if not self.sliding_share < 1.0:
            raise ValueError(f"DiagnosisSettings.sliding_share must be below 1 (the sliding force is reached "
                             f"only asymptotically), not {self.sliding_share!r}")


DEFAULT_RULE = SignificanceRule()
DEFAULTS = DiagnosisSettings(rule=DEFAULT_RULE)

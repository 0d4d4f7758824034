"""The estimator's tuned numbers, each with its meaning, unit and range: ``ReconSettings.tuning``.

``reconstruct(run, ReconSettings(tuning=EstimatorTuning(simpler_gain=0.3)))`` runs the estimator
with another value; the defaults are the calibrated ones (docs/method.md). In a settings file
(a batch job's ``[recon]`` table, a saved result's settings) ``tuning`` is a table of these
fields; an unknown field or a value out of range is refused, naming it.

What each group decides:

- adequacy (recon.estimator.adequacy): ``noise_factor``, ``nrmse_floor``, ``max_fn_terms``;
- restarts of the nonlinear stage's polish (recon.estimator.finish): ``start_nrmse_limit``,
  ``floor_factor``, the generic Bouc-Wen starts ``alpha_shares`` x ``knees`` screened with
  ``screen_nfev`` evaluations, ``continue_rounds``, ``start_rounds``;
- the input offset's automatic switch (recon.estimator.input_offset): ``dc_share``;
- the two stages fitted together (recon.estimator.two_stage): ``joint_false_alarm``,
  ``floor_ratio``, ``floor_draws``;
- the simpler models beside an inadequate full model (recon.estimator.pipeline):
  ``simpler_gain``, ``simpler_fit_slack``.
"""
from __future__ import annotations

from dataclasses import dataclass

from recon.settings_fields import bounded as _f, check, describe

__all__ = ["EstimatorTuning", "DEFAULT_TUNING", "describe"]


@dataclass(frozen=True)
class EstimatorTuning:
    """The estimator's tuned numbers (module doc)."""
    noise_factor: float = _f(5.0, "a validation NRMSE up to this many times the record's noise floor is "
                             "adequate (noise and filter error explain it)", "x noise floor", 1.0, 1e3)
    nrmse_floor: float = _f(0.01, "below this validation NRMSE a model is adequate whatever the noise floor",
                            "NRMSE", 0.0, 1.0)
    max_fn_terms: int = _f(4, "most fn terms an adequate model may have (a TMP-like law: y^2, y^3 and two "
                           "damping terms)", "terms", 0, 100)
    start_nrmse_limit: float = _f(1.0, "an estimate that simulates the nonlinear stage worse than this NRMSE "
                                  "(1: worse than predicting zero) is polished from restarted fn terms",
                                  "NRMSE", 0.0, 1e3, lo_open=True)
    floor_factor: float = _f(1.5, "a polish that ends above this many times the stage's noise floor is "
                             "restarted from the generic Bouc-Wen starts", "x noise floor", 1.0, 1e3)
    alpha_shares: tuple = _f((0.25, 0.5, 0.75), "generic starts: shares of the small-amplitude stiffness "
                             "put into the hysteresis", "fraction", 0.0, 1.0, lo_open=True)
    knees: tuple = _f((1.0, 3.0), "generic starts: the nonlinear stage's amplitude over the loop's knee "
                      "(lambda Y)", "lambda Y", 0.0, 1e3, lo_open=True)
    screen_nfev: int = _f(20, "evaluations each generic start is polished with before the best is polished "
                          "to the end", "evaluations", 1, 10000)
    continue_rounds: int = _f(3, "more polish rounds, while the cost falls, after a polish stopped at its "
                              "evaluation budget", "rounds", 0, 100)
    start_rounds: int = _f(2, "times the start state of a stage recorded in motion is re-estimated with the "
                           "polished model", "rounds", 0, 100)
    dc_share: float = _f(0.5, "the input offset is fitted ('auto') when the linear stage's mean motion "
                         "exceeds this share of its rms motion", "fraction of rms", 0.0, 1e3)
    joint_false_alarm: float = _f(0.01, "the joint fit of the two stages is kept when the nonlinear stage's "
                                  "sum of squares rises by less than the chi-square quantile at this level",
                                  "probability", 0.0, 1.0, lo_open=True)
    floor_ratio: float = _f(1.1, "a joint fit whose mean square is within this ratio of its floor, either "
                            "way, is at its floor (no restart)", "ratio", 1.0, 100.0)
    floor_draws: int = _f(2, "noise draws per stage of the floor's estimate (one simulation each)",
                          "draws", 1, 100)
    simpler_gain: float = _f(0.5, "a simpler model replaces an inadequate full model when its held-out NRMSE "
                             "is at most this share of the full model's", "fraction", 0.0, 1.0)
    simpler_fit_slack: float = _f(2.0, "... and when it fits the nonlinear stage at most this many times "
                                  "worse than the full model", "ratio", 1.0, 1e3)

    def __post_init__(self):
        check(self)
        for name in ("max_fn_terms", "screen_nfev", "continue_rounds", "start_rounds", "floor_draws"):
            if int(getattr(self, name)) != getattr(self, name):
                raise ValueError(f"EstimatorTuning.{name} must be a whole number, not {getattr(self, name)!r}")

    @classmethod
    def of(cls, value) -> "EstimatorTuning":
        """``value`` as EstimatorTuning: itself, or a mapping of its fields (lists become tuples)."""
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            known = set(cls.__dataclass_fields__)
            unknown = sorted(set(value) - known)
            if unknown:
                raise ValueError(f"unknown tuning field(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
            return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in value.items()})
        raise ValueError(f"tuning must be an EstimatorTuning or a table of its fields, not {type(value).__name__}")


DEFAULT_TUNING = EstimatorTuning()

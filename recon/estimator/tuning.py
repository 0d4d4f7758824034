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
  ``simpler_gain``, ``simpler_fit_slack``;
- what is admissible (recon.estimator.fallback.admissible): ``split_limit``; which fn terms
  (and which Bouc-Wen law) are negligible after the polish (recon.estimator.pipeline): ``negligible``;
- the output-error fits (recon.output_error.polish; the simpler models decimate and stop alike):
  ``polish_fs``, ``polish_nfev``, ``stop_chi2``; the exciter refit (recon.estimator.drive):
  ``drive_nfev``;
- a stage recorded in motion (recon.simulation.start_state, through HystereticModel's stage
  methods): ``start_fit_seconds``, ``start_fit_nfev``;
- the model input's own band (recon.input_band, through recon.signals): ``band_slope_sigmas``,
  ``band_smooth``, ``band_false_alarm``, ``band_grow``;
- the displacement column integrated twice from an acceleration record (recon.signals):
  ``drift_band_share``, ``drift_keep_sigmas``;
- the weak form (recon.weak, also the chain's path form): ``weak_bump_power``,
  ``weak_min_segment``, ``weak_tile_overlap``, ``weak_support_periods``, ``weak_gate_sigmas``,
  ``weak_enter_bic``, ``weak_leave_bic``.
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
    floor_factor: float = _f(1.5, "a polish that ends above this many times the stage's noise floor, past "
                             "the start's transient (start_decays), is restarted from the generic Bouc-Wen "
                             "starts", "x noise floor", 1.0, 1e3)
    start_decays: float = _f(3.0, "decay times of the mode (2 / c each) at the start of the nonlinear stage "
                             "that the restart's floor test leaves out (the transient of a start state no fit "
                             "observes whole; the diagnosis's burn_in_decays)", "decay times", 0.0, 100.0)
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
    split_limit: float = _f(10.0, "a model whose post-yield stiffness |k| exceeds this many times K = k + alpha "
                            "is not admissible (k and alpha cancel: a split the data did not determine)",
                            "x K", 1.0, 1e6)
    negligible: float = _f(0.002, "fn terms whose rms force on the nonlinear stage is below this share of the "
                           "elastic force are dropped after the polish, and a Bouc-Wen law whose z is below it "
                           "has vanished", "fraction of the elastic force", 0.0, 1.0)
    polish_fs: float = _f(2000.0, "the output-error fits simulate a stage recorded faster than twice this rate "
                          "on every q-th sample (its rate stays at least this)", "Hz", 0.0, 1e7, lo_open=True)
    polish_nfev: int = _f(60, "evaluations of an estimate's output-error polish (one that stops at this budget "
                          "is continued: continue_rounds)", "evaluations", 1, 100000)
    stop_chi2: float = _f(0.01, "an output-error fit stops after an iteration that lowers its cost by less "
                          "than this many chi-square units (recon.output_error.stopping)", "chi-square units",
                          0.0, 1e3, lo_open=True)
    drive_nfev: int = _f(60, "evaluations of the exciter refit (ReconSettings(drive=True))", "evaluations",
                         1, 100000)
    start_fit_seconds: float = _f(4.0, "a stage recorded in motion has its start state fitted to this many "
                                  "first seconds of its response", "s", 0.0, 1e4, lo_open=True)
    start_fit_nfev: int = _f(30, "evaluations of that start state's fit", "evaluations", 1, 10000)
    band_slope_sigmas: float = _f(4.0, "model input: an end's first or third derivative within this many of "
                                  "its noise std counts as zero (the end is at rest)", "noise std", 0.0, 1e3)
    band_smooth: int = _f(5, "model input: cosine-series coefficients averaged for the band decision",
                          "coefficients", 1, 1000)
    band_false_alarm: float = _f(0.01, "model input: a coefficient seeds the band when that average exceeds "
                                 "the chi-square level of this false-alarm probability over the whole series",
                                 "probability", 0.0, 1.0, lo_open=True)
    band_grow: float = _f(3.0, "model input: the band grows into neighbouring coefficients above this many "
                          "times the noise floor", "x noise floor", 0.0, 1e3)
    drift_band_share: float = _f(0.5, "a displacement integrated twice from an acceleration record keeps its "
                                 "cosine series from this share of the lowest frequency of the record's band up: "
                                 "below it the column holds the integrated noise (its drift), not motion "
                                 "(0: nothing dropped)", "fraction of the band's lowest frequency", 0.0, 1.0)
    drift_keep_sigmas: float = _f(20.0, "... except a coefficient that stands more than this many times above the "
                                  "integrated noise's expected level there: motion (a stage that starts or ends "
                                  "in motion)", "noise std", 0.0, 1e3)
    weak_bump_power: int = _f(3, "weak form: the test functions are (1 - x^2)^P over their support, this P",
                              "power", 1, 100)
    weak_min_segment: int = _f(12, "weak form: AB/CD runs shorter than this are skipped (noise flicker near "
                               "zero)", "samples", 1, 100000)
    weak_tile_overlap: float = _f(4.0, "weak form: tiled test functions advance by 1/this of their width, so "
                                  "each sample lies in this many rows (the path form's BIC counts them)",
                                  "rows per sample", 1.0, 1000.0)
    weak_support_periods: float = _f(0.5, "weak form along the path: a test function's support in periods of "
                                     "the dominant line", "periods", 0.0, 100.0, lo_open=True)
    weak_gate_sigmas: float = _f(4.0, "weak form along the path: reversals of the smoothed path smaller than "
                                 "this many noise std are not reversals", "noise std", 0.0, 1e3)
    weak_enter_bic: float = _f(6.0, "weak form along the path: an fn term enters when the BIC drops by more "
                               "than this (strong evidence on Kass and Raftery's scale)", "BIC units", 0.0, 1e3)
    weak_leave_bic: float = _f(2.0, "... and leaves when dropping it raises the BIC by less than this (evidence "
                               "not worth a mention)", "BIC units", 0.0, 1e3)

    def __post_init__(self):
        check(self)
        for name in ("max_fn_terms", "screen_nfev", "continue_rounds", "start_rounds", "floor_draws", "polish_nfev",
                     "drive_nfev", "start_fit_nfev", "band_smooth", "weak_bump_power", "weak_min_segment"):
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

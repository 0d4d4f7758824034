"""What the estimator takes and gives: ReconSettings and ReconResult."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from recon.estimator.adequacy import verdict_text
from recon.estimator.tuning import EstimatorTuning
from recon.model import HystereticModel
from recon.steps.linear import LinearFit
from shakerlab import __version__
from shakerlab.errors import UserFacingError


@dataclass
class ReconSettings:
    library_order: int = 5
    form: str = "joint"            # "joint" (AB and CD together), "ab" (the paper's AB-only form) or
    #                                "weak" (joint form integrated against test functions, recon/weak.py)
    refit: bool = True              # structured refit of (a_j, lambda, alpha) on the fixed pattern
    refit_linear: bool = True       # ... and of (c_m, K_m[, inv_m]) on the nonlinear stage too
    polish: bool = True             # output-error refinement of all parameters by simulation
    # library columns that absorb the linear step's c/K error (joint form): "auto" tries without
    # first and falls back to them when the result is not physically admissible
    linear_correction: bool | str = "auto"
    # revise the fn terms by output error on held-out blocks of the nonlinear stage after the
    # polish (recon/term_selection.py); needs polish
    term_selection: bool = True
    # at the end, polish the linear and nonlinear stages together, each weighted by its noise, and keep
    # the joint fit when the nonlinear stage's fit stays within its noise; it also decides the fn terms
    # (recon.estimator.two_stage)
    two_stage_polish: bool = True
    # when the equation-error estimate is not physically admissible (lambda, alpha or K <= 0),
    # also run this form and keep whichever simulates the nonlinear stage better (None: never)
    fallback_form: str | None = "weak"
    linear_stage: str = "linear"
    nonlinear_stage: str = "nonlinear"
    n_folds: int = 5
    window: int | None = None       # Savitzky-Golay window for the nonlinear stage (None: chosen from the data)
    sg_order: int | None = None
    # fit a constant offset b of the recorded input with the output-error polish (the model is driven
    # by g (u - b); for records whose input is not zero-mean, e.g. a force sensor's offset, or a
    # constant force on the specimen). "auto": on when the data show a DC the excitation cannot make
    # (recon.estimator.input_offset); reconstruct stores the decision (True/False) in its settings
    input_offset: bool | str = "auto"
    # the force channel is the exciter's drive (an amplifier voltage), not a measured force: fit the
    # exciter's distortion and roll-off at the end (recon.exciter, recon.estimator.drive); force only
    drive: bool = False
    # the estimator's tuned numbers (recon.estimator.tuning); a table of its fields is accepted
    tuning: EstimatorTuning = field(default_factory=EstimatorTuning)

    FORMS = ("joint", "ab", "weak")

    def __post_init__(self):
        try:
            self.tuning = EstimatorTuning.of(self.tuning)
        except (ValueError, TypeError) as exc:
            raise UserFacingError(f"ReconSettings.tuning: {exc}") from None
        if self.form not in self.FORMS:
            raise UserFacingError(f"ReconSettings.form must be one of {self.FORMS}, got {self.form!r}")
        if self.input_offset not in (True, False, "auto"):
            raise UserFacingError(f"ReconSettings.input_offset must be True, False or 'auto', got {self.input_offset!r}")
        if self.drive not in (True, False):
            raise UserFacingError(f"ReconSettings.drive must be True or False, got {self.drive!r}")
        if self.fallback_form is not None and self.fallback_form not in self.FORMS:
            raise UserFacingError(f"ReconSettings.fallback_form must be None or one of {self.FORMS}, "
                                  f"got {self.fallback_form!r}")

    def to_dict(self):
        return asdict(self)


@dataclass
class ReconResult:
    model: HystereticModel
    linear: LinearFit
    sparse: dict
    library_names: list
    library_coef: list
    hysteresis_info: dict
    differentiation: dict
    validation: dict
    settings: ReconSettings
    timings: dict = field(default_factory=dict)
    signals: dict = field(default_factory=dict, repr=False)
    # the agent-model regression the sparse selector solved (pointwise forms): regression
    # matrix "A", target "b", column "groups" and "core", selector "options", library "lib",
    # the "terms" it selected; None for the weak form. recon.output_error.uncertainty.term_inclusion
    # resamples it.
    selection_problem: dict | None = field(default=None, repr=False)
    # the verdict on the model (recon.estimator.adequacy.assess): admissible, adequate, and why
    adequacy: dict = field(default_factory=dict)

    @classmethod
    def of_model(cls, model: HystereticModel, validation: dict, settings: ReconSettings) -> "ReconResult":
        """A result that holds ``model`` alone, with no estimation steps behind it (a simpler model
        fitted by output error): its linear part is the model's c and k, nothing was selected."""
        nan = float("nan")
        return cls(model=model, linear=LinearFit(model.c_m, model.K_m, model.inv_m, nan, [], nan, nan),
                   sparse={"threshold": None, "n_terms": 0}, library_names=[], library_coef=[],
                   hysteresis_info={}, differentiation={}, validation=validation, settings=settings)

    def to_dict(self) -> dict:
        params = self.model.to_dict()["parameters"]
        return {
            "excitation": self.model.excitation,
            "parameters": params,
            "units": self.model.to_dict()["units"],
            "convention": self.model.to_dict()["convention"],
            "equation": self.model.equation(),
            "validation": self.validation,
            "linear_step": self.linear.to_dict(),
            "nonlinear_step": {"library": dict(zip(self.library_names, self.library_coef)),
                               "hysteresis": self.hysteresis_info, "sparse_regression": self.sparse},
            "settings": {"differentiation": self.differentiation, "threshold": self.sparse["threshold"],
                         "library_order": self.settings.library_order, "form": self.settings.form,
                         "refit": self.settings.refit,
                         **({"drive": True, "drive_fit": self.model.provenance.get("drive_fit")}
                            if getattr(self.settings, "drive", False) else {}),
                         **({"simpler_model": self.adequacy["fallback"]["kind"]}
                            if (self.adequacy.get("fallback") or {}).get("used") else {})},
            "adequacy": self.adequacy,
            "verdict_text": verdict_text(self.adequacy) if self.adequacy else None,
            "timings_s": self.timings,
            "software": {"shakerlab": __version__},
        }

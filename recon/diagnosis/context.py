"""What every step of a diagnosis reads: the record, its prepared stages, where the reference
misses, the settings, the fits' budget and the held-out noise floor.

One :class:`DiagnosisContext` is made once the reference is known (recon.diagnosis.diagnose) and
passed to every step that fits or scores, so that no step reaches for a number of its own.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from recon.diagnosis.settings import DEFAULTS, DiagnosisSettings, SignificanceRule
from shakerlab.run_data import Run


@dataclass(frozen=True)
class DiagnosisContext:
    """The fixed inputs of a diagnosis's fitting and scoring steps."""
    run: Run
    data: list                          # rank.prepare's stage data (fitting and held-out samples)
    derivs: list                        # locate.stage_derivatives: the equation-error steps' derivatives
    located: dict                       # locate's context (the candidates' starts read it)
    noise_mse: float                    # the held-out noise floor (rank.held_noise_mse)
    max_nfev: int = 30                  # function evaluations of a full output-error fit
    settings: DiagnosisSettings = field(default=DEFAULTS)

    @property
    def rule(self) -> SignificanceRule:
        return self.settings.rule

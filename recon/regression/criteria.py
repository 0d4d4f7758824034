"""Model-selection criteria shared by the estimators: correlation lengths, effective sample counts, BIC."""
from __future__ import annotations

import numpy as np

from recon.differentiation import filter_coefficients


def filter_correlation_length(choice: dict) -> float:
    """Correlation length (in samples) of white noise after the stage's highest-derivative
    filter: sum of the squared normalised autocorrelation (Bartlett), which sets the
    effective number of independent residuals N/corr_len."""
    c = filter_coefficients(choice["window"], choice["order"], choice["deriv"], 1.0)
    r = np.correlate(c, c, "full")
    return float(np.sum((r / r.max()) ** 2))

"""Never an improvement that is worse on one held-out stage (issue 76).

A candidate is significant on the held-out samples taken together (rank.score). Taken together,
a model can trade one stage for another: better on a validation stage by much, worse on the
held-out end of the nonlinear stage by more than its noise can account for. Such a model does not
explain the record; it is reported as *partly explained*, with the stage where it fails.

The noise band of a stage is the record's own noise, not a tuned constant. With the recorded
output y = s + e (e white, variance sigma^2: the stage's noise floor), the baseline as given
simulating g and the candidate c, the rise of the stage's held-out sum of squares is

    rise = |y - c|^2 - |y - g|^2 = |d|^2 - 2 (y - g) . d,    d = c - g (noise-free: two simulations),

of which the noise contributes -2 e . d, a Gaussian of standard deviation 2 sigma |d|. (In
likelihood terms: the log-likelihood ratio of the two models on the stage, -rise / (2 sigma^2),
has a standard deviation |d| / sigma where the two fit the stage equally well.) The candidate is
worse on the stage beyond its noise band when

    rise > 2 z sigma |d|,    z = the one-sided normal quantile at level / (number of held-out stages),

the level (SignificanceRule.stage_level) shared among the held-out stages (Bonferroni), so that a
candidate no worse than the baseline anywhere is called worse somewhere with probability at most
that level. Both models' residuals are the stage's held-out samples, each model started as the
diagnosis starts it.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtri

from recon.diagnosis.settings import DEFAULT_RULE
# ``level`` below: the chance, over every held-out stage of a record, that the noise alone makes a
# model that is no worse than the baseline as given look worse on some stage (a test's level, not a
# fitted margin): SignificanceRule.stage_level, the default rule's when not given


def stage_band_z(n_stages: int, level: float = DEFAULT_RULE.stage_level) -> float:
    """The one-sided normal quantile of ``level`` shared among ``n_stages`` stages."""
    return float(-ndtri(level / max(int(n_stages), 1)))   # the normal's upper quantile


def held_stage_figures(given, cand, data, level: float = DEFAULT_RULE.stage_level) -> dict:
    """Per held-out stage of ``data`` (rank.StageData), the candidate fit ``cand`` against the
    baseline as given ``given`` (rank.FitResult, with their simulations ``sims``):
    {stage: {nrmse_before, nrmse_after, rise_noise_variances, band_noise_variances, worse}}.

    nrmse_*: the stage's held-out NRMSE (over the stage's held-out rms); rise: the rise of the
    held-out sum of squares in noise variances; band: 2 z |d| / sigma in the same unit (module
    docstring). A stage the baseline does not simulate (not finite) cannot be made worse; one the
    candidate does not simulate is worse."""
    held = [(i, d) for i, d in enumerate(data) if d.held.any()]
    z = stage_band_z(len(held), level)
    out = {}
    for i, d in held:
        yh = d.y[d.held]
        scale = float(np.sqrt(np.mean((yh - yh.mean()) ** 2))) or 1.0
        g = np.asarray(given.sims[i], float)[d.held]
        c = np.asarray(cand.sims[i], float)[d.held]
        sigma = max(float(d.noise), 1e-300)
        ok_g, ok_c = bool(np.all(np.isfinite(g))), bool(np.all(np.isfinite(c)))
        if not ok_c or not ok_g:
            out[d.name] = {"nrmse_before": float(np.sqrt(np.mean((g - yh) ** 2)) / scale) if ok_g else math.inf,
                           "nrmse_after": float(np.sqrt(np.mean((c - yh) ** 2)) / scale) if ok_c else math.inf,
                           "rise_noise_variances": math.inf if ok_g else -math.inf,
                           "band_noise_variances": 0.0, "worse": bool(ok_g and not ok_c)}
            continue
        ss_g = float(np.sum((yh - g) ** 2))
        ss_c = float(np.sum((yh - c) ** 2))
        band = 2.0 * z * sigma * float(np.linalg.norm(c - g))
        out[d.name] = {"nrmse_before": math.sqrt(ss_g / yh.size) / scale,
                       "nrmse_after": math.sqrt(ss_c / yh.size) / scale,
                       "rise_noise_variances": (ss_c - ss_g) / sigma ** 2,
                       "band_noise_variances": band / sigma ** 2,
                       "worse": bool(ss_c - ss_g > band)}
    return out


def worse_stages(figures: dict) -> list[str]:
    """The stages of :func:`held_stage_figures` where the candidate is worse beyond the noise band."""
    return [s for s, f in figures.items() if f["worse"]]

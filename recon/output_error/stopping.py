"""When an output-error fit has converged as far as the record can tell: a stop in chi-square units.

A least-squares fit of a simulated response minimises a sum of squares of errors. Divided by the
variance of one error, that sum is -2 log likelihood up to a constant, and a change of 1 is one
chi-square unit: the size of the change that moves a well-determined parameter by one standard
error. The variance of one error is the larger of the two the fit can know: the output noise
(the record's floor), and the residual's own mean square, where the model misses more than the
noise (a model without an effect the record holds: its parameters' standard errors are then set
by that mean square, as the fits' reported intervals are). An iteration that lowers the sum by
0.01 units (the default ``stop_chi2``: EstimatorTuning.stop_chi2 for reconstruct's fits,
DiagnosisSettings.stop_chi2 for the diagnosis's) moves the parameters by about 0.1 standard
error, and what the fit could
still gain after such a step is of the same order (the trust region's steps shrink geometrically
near a minimum): no decision downstream (a held-out comparison, a significance test, a term's
price of log n units) can turn on it. The fit stops there instead of running to the solver's
relative tolerance (1e-10 of the cost or less), where it spent a third of its simulations on
changes a thousand times smaller than one unit.

:class:`ChiSquareStop` is the ``callback`` of ``scipy.optimize.least_squares`` (method
"trf"): it is told, once per fit, how many chi-square units one unit of the solver's cost
``F = 0.5 * sum(r**2)`` is worth under the output noise (``units_per_cost``) and how many rows
the residual has, and raises ``StopIteration`` after an accepted iteration that lowered the cost
by less than ``stop_chi2`` units. The solver then
returns its last accepted point with the Jacobian taken there (status -2).
"""
from __future__ import annotations

import math


class ChiSquareStop:
    """A least_squares ``callback`` (module doc). ``units_per_cost``: chi-square units per unit of
    the solver's cost F under the output noise, i.e. 2 / (the noise variance of one residual row)
    for rows that share one scale; with rows of several scales, the largest (the conservative
    stop). ``rows``: the residual's length; the residual's own variance per row, 2 F / rows, is
    the unit instead where it is the larger. ``stop_chi2``: the smallest improvement, in chi-square
    units of the fit's own likelihood, for which another iteration is worth making (module doc)."""

    def __init__(self, units_per_cost: float, rows: int, stop_chi2: float):
        if not (math.isfinite(units_per_cost) and units_per_cost > 0):
            raise ValueError(f"units_per_cost must be finite and positive, not {units_per_cost!r}")
        if not (math.isfinite(stop_chi2) and stop_chi2 > 0):
            raise ValueError(f"stop_chi2 must be finite and positive, not {stop_chi2!r}")
        self.units_per_cost = float(units_per_cost)
        self.rows = max(int(rows), 1)
        self.stop_chi2 = float(stop_chi2)
        self.last = None
        self.stopped = False

    def __call__(self, intermediate_result):
        cost = float(intermediate_result.cost)
        last, self.last = self.last, cost
        if last is None or not math.isfinite(cost):
            return
        drop = last - cost
        units = min(self.units_per_cost, self.rows / cost) if cost > 0 else self.units_per_cost
        if 0.0 <= drop * units < self.stop_chi2:
            self.stopped = True
            raise StopIteration


def stop_for_stages(sample_counts, stop_chi2: float, scale_ratios=None) -> ChiSquareStop | None:
    """The stop (at ``stop_chi2`` units) for a residual whose stage ``i`` rows are
    ``error / (scale_i * sqrt(n_i))``: its sum of squares times ``n_i * ratio_i**2`` is that stage's
    chi-square, where ``ratio_i`` is the fit's scale over the noise it assumes (1: the fit's own scale
    is its likelihood's). None when there is nothing to fit."""
    counts = [int(n) for n in sample_counts]
    if not counts or max(counts) <= 0:
        return None
    ratios = list(scale_ratios) if scale_ratios is not None else [1.0] * len(counts)
    per_ss = max(n * r * r for n, r in zip(counts, ratios))
    return ChiSquareStop(2.0 * per_ss, sum(counts), stop_chi2)

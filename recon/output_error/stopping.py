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

A small gain is evidence of a minimum only where the fit's own local model agrees. On a ridge (a new
term and a baseline term that can trade, as a friction and the viscous damping that held it) or
across a sharp switch, the Gauss-Newton model at the accepted point can promise many units while the
trust region, still shrinking to where that model holds, gains almost nothing per step. Given the
Jacobian at the point (:meth:`ChiSquareStop.record`, a wrapper of the fit's ``jac``), the stop
computes the gain a full Gauss-Newton step promises there (the parameters held at a bound they are
pushed against kept fixed) and does not stop while that promise is one chi-square unit or more: the
size of change a held-out comparison or a significance test can turn on.
"""
from __future__ import annotations

import math

import numpy as np


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
        self._jacobian = None          # (x, J) of the last Jacobian the fit took (record)
        self._bounds = None

    def record(self, jac, bounds=None):
        """``jac`` wrapped to keep its last (x, J), so that the stop can ask the local model what a
        full step would still gain (module doc); ``bounds`` (lo, hi): the fit's, in its variables."""
        self._bounds = bounds

        def recorded(x, *args):
            J = jac(x, *args)
            self._jacobian = (np.array(x, float), J)
            return J
        return recorded

    def model_gain(self, x, f) -> float:
        """The decrease of the cost F a full Gauss-Newton step from ``x`` promises (nan without the
        Jacobian at ``x``), with every parameter at a bound it is pushed against held there."""
        if self._jacobian is None or not np.array_equal(self._jacobian[0], x):
            return float("nan")
        J = np.asarray(self._jacobian[1], float)
        free = np.ones(J.shape[1], bool)
        lo, hi = self._bounds if self._bounds is not None else (None, None)
        for _ in range(J.shape[1] + 1):      # each pass holds at least one more, or ends
            if not free.any():
                return 0.0
            step = np.zeros(J.shape[1])
            step[free] = np.linalg.lstsq(J[:, free], -f, rcond=None)[0]
            pushed = np.zeros_like(free)
            if lo is not None:
                at_lo = np.isfinite(lo) & (x - lo <= 1e-10 * np.maximum(1.0, np.abs(lo)))
                at_hi = np.isfinite(hi) & (hi - x <= 1e-10 * np.maximum(1.0, np.abs(hi)))
                pushed = free & (at_lo & (step < 0) | at_hi & (step > 0))
            if not pushed.any():
                break
            free &= ~pushed
        Js = J @ step
        return float(-(f @ Js) - 0.5 * (Js @ Js))

    def __call__(self, intermediate_result):
        cost = float(intermediate_result.cost)
        last, self.last = self.last, cost
        if last is None or not math.isfinite(cost):
            return
        drop = last - cost
        units = min(self.units_per_cost, self.rows / cost) if cost > 0 else self.units_per_cost
        if 0.0 <= drop * units < self.stop_chi2:
            promise = self.model_gain(np.asarray(intermediate_result.x, float),
                                      np.asarray(intermediate_result.fun, float))
            if promise * units >= 1.0:      # the local model still promises a unit (module doc)
                return
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


def watched(jac, stop: ChiSquareStop | None, bounds=None):
    """``jac`` as the fit passes it to least_squares, recorded for ``stop`` (ChiSquareStop.record)
    when both are there; scipy's own differences ("2-point") and a fit without a stop unchanged."""
    return stop.record(jac, bounds) if stop is not None and callable(jac) else jac


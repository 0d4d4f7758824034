"""The linear and nonlinear stages fitted together, each weighted by its own noise, at the end of
reconstruct.

Every earlier step fits the nonlinear stage alone. With one tone per stage (the paper's protocol)
that stage leaves the Bouc-Wen shape (gamma, delta), the damping and the fn terms poorly
determined: they trade against each other along the one loop the stage draws. The linear stage,
at another amplitude and frequency, holds the small-amplitude stiffness and damping they trade
against. Fitted together, each stage's residual divided by its own noise (the maximum-likelihood
fit under white output noise), the record's two stages decide what one could not.

Three steps, each kept only on the evidence of the joint fit:

1. :func:`two_stage_polish`: the joint polish from the nonlinear stage's model. Kept when the two
   stages agree: the nonlinear stage's sum of squares rises by at most the chi-square(p) quantile
   at ``joint_false_alarm`` (recon.estimator.tuning), in noise variances. A larger rise is model
   error, not noise, and the nonlinear stage's own fit stays. When the joint polish lowers the joint
   sum of squares by less than one noise variance (one chi-square unit: no parameter moves by a
   standard error), the linear stage does not contradict the model: the joint fit is kept, and
   steps 2 and 3, which look for what the linear stage contradicts, are not taken.
2. :func:`drop_terms`: each fn term is dropped in turn and the joint fit repeated; the term whose
   loss costs least goes when that cost is below log(n) noise variances (the BIC price of one
   parameter), and again until every term pays for itself. The cost is the rise of the joint sum
   of squares, each stage's share divided by the residual's :func:`colour` where the loss changes
   the fit: the white-noise price is too low for a residual coloured by the input's noise at
   resonance.
3. :func:`restart`: when the joint fit is not at its floor, or step 1 finds the stages in
   disagreement, the fit may be in another basin: it restarts from the stiffness terms alone
   (y^2, y^3), and from the generic Bouc-Wen starts of the nonlinear stage's polish when that is
   not at its floor either, and keeps the restart when it fits the two stages better (and, after a
   disagreement, agrees with the nonlinear stage).

The floor (:meth:`TwoStages.floor`) is the mean square per sample, in output noise variances, that
the record's noise leaves in the residual of a model if that model is right: the output's white
noise (1) plus the input sensor's noise carried through the model (the input u is made from a
measured channel, so its noise drives the simulation; near a resonance that is a coloured residual
well above the white level). It is measured, not assumed: the stage's own input filter applied to
white noise at the input channel's noise level (the draws the uncertainty ensemble uses), simulated
through the model from the stage's start state as the fit holds it, and compared with the same
simulation without it. A fit is at its floor when
its mean square is within ``floor_ratio`` of that floor either way (:func:`at_floor`): above it the
residual holds model error; below it the model carries the record's noise in a way the record
does not show (its dynamics amplify the input noise more than the residual allows), which a right
model cannot do either.

Measured on the independent generator (bench/recon_accuracy.py --stress, docs/method.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import chdtri

from recon.estimator.fallback import NUMERICAL_ERRORS, admissible, with_term_scales
from recon.estimator.finish import generic_starts
from recon.estimator.result import ReconSettings
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.model import HystereticModel
from recon.output_error.polish import decimate, item_cost, polish
from recon.output_error.problem import OutputError, item_start, item_target, measured_error
from recon.signals import base_noise_in_target, input_filter, target_noise_std
from recon.welch import welch
from shakerlab.run_data import BASE, Run, Stage


# how far (tuning.floor_ratio, either way) the joint fit's mean square per sample may be from its
# floor (TwoStages.floor) for the fit to be taken as at its floor: the mean square's sampling spread
# is sqrt(2/n), under 0.01 for n > 20000, and the floor's own estimate is good to a few per cent, so
# 10 % off it is model error. The floor's noise draws (tuning.floor_draws) are fixed:
FLOOR_SEED = 20261205    # the draws are fixed: the same record gives the same floor
STIFFNESS_TERMS = ("y^2", "y^3")


@dataclass
class TwoStages:
    """The linear and the nonlinear stage of a run and the white-noise std of each one's output."""
    stages: list[Stage]
    noise: list[float]
    tuning: EstimatorTuning = DEFAULT_TUNING
    _draws: list | None = field(default=None, init=False, repr=False)    # _floor_draws, made once

    @classmethod
    def of(cls, run: Run, s: ReconSettings) -> "TwoStages | None":
        """None when the run has no separate linear stage or a stage shows no noise floor."""
        if s.linear_stage not in run.stages or s.linear_stage == s.nonlinear_stage:
            return None
        stages = [run.stage(s.linear_stage), run.stage(s.nonlinear_stage)]
        # in the quantity each response was recorded in, as the fits compare it (problem.item_target)
        noise = [target_noise_std(st) for st in stages]
        if not all(v > 0 and np.isfinite(v) for v in noise):
            return None
        return cls(stages, noise, s.tuning)

    @property
    def names(self) -> list[str]:
        return [st.name for st in self.stages]

    def items(self, model: HystereticModel) -> list[tuple]:
        return [model.fit_item(st, tuning=self.tuning) for st in self.stages]

    def fit(self, model: HystereticModel, items: list | None = None):
        """The joint polish from ``model``: (model, info, items)."""
        items = self.items(model) if items is None else items
        new, info = polish(model, items, noise=self.noise, tuning=self.tuning)
        return new, info, items

    def residuals(self, model: HystereticModel, items: list) -> list[tuple[np.ndarray, float]]:
        """Each stage's residual in units of its noise over the item as the polish fits it
        (decimated), with its sample interval."""
        out = []
        for item, sd in zip(items, self.noise):
            d, _ = decimate(item, self.tuning.polish_fs)
            ys = OutputError.item_response(model, d)
            out.append((measured_error(ys, item_target(d)) / sd, float(d[0][1] - d[0][0])))
        return out

    def floor(self, model: HystereticModel, items: list) -> float:
        """The mean square per sample, in noise variances, of the joint residual that the record's
        noise leaves under ``model`` if ``model`` is right (module doc): 1 for the output's white
        noise plus the input noise carried through the model, over the items as the polish fits
        them. Under base excitation the base sensor's noise enters y = x_tip - x_base as well as
        u; its own share of the output noise is replaced by the pair's joint effect.

        The noise enters the input, not the start: each draw keeps the item's start state
        (y0, y0', z0) as the fit holds it, so the draw's y'' at the start moves with its input
        (balance: z0 = g u0 - y0'' - ...). Left to move z0 instead, a draw's first input sample
        (a Savitzky-Golay second derivative's edge, the noisiest sample it has) set a hysteretic
        offset that decays only as |y'| z does, and the floor came out several times too high
        at random."""
        total, count = 0.0, 0
        for item, sd, draws in zip(items, self.noise, self._floor_draws()):
            d, q = decimate(item, self.tuning.polish_fs)
            base = OutputError.item_response(model, d)
            start = item_start(d)
            share = []
            for un, carried, own in draws:
                noisy = d if start is None else (
                    (*d[:3], (start[0], start[1], start[2] + model.input_gain * un[0]), *d[4:]))
                ys = OutputError.item_response(model, noisy, d[1] + un)
                if not np.all(np.isfinite(ys)):
                    return float("inf")
                share.append((float(np.mean((ys - base - carried) ** 2)) - own) / sd ** 2)
            total += d[2].size * (1.0 + max(float(np.mean(share)), 0.0))
            count += d[2].size
        return total / max(count, 1)

    def _floor_draws(self) -> list[list[tuple[np.ndarray, np.ndarray, float]]]:
        """Per stage, the floor's noise draws as the decimated items take them: (the input's noise,
        the noise the base channel puts into the target (0 for a force input), the variance of
        the part that is the target's own white noise). They depend on the stage and the fixed
        seed only, not on the model: made once per TwoStages."""
        if self._draws is None:
            rng = np.random.default_rng(FLOOR_SEED)
            out = []
            for st in self.stages:
                f = input_filter(st, tuning=self.tuning)
                q = decimate((st.t, st.t, st.t), self.tuning.polish_fs)[1]   # as the items' own
                draws = []
                for _ in range(self.tuning.floor_draws):
                    nb = rng.normal(0.0, f.noise_std, st.t.size)
                    un = f(nb)[::q]
                    if st.excitation == BASE:     # y_meas carries -n_base: the residual gets +n_base
                        carried, own = base_noise_in_target(st, nb)
                        draws.append((un, carried[::q], f.noise_std ** 2 if own else 0.0))
                    else:
                        draws.append((un, np.zeros_like(un), 0.0))
                out.append(draws)
            self._draws = out
        return self._draws

    def sse(self, model: HystereticModel, items: list) -> tuple[float, int]:
        """The joint sum of squares in noise variances over the items as the polish fits them
        (decimated), and the number of samples."""
        res = self.residuals(model, items)
        return float(sum(e @ e for e, _ in res)), int(sum(e.size for e, _ in res))


def colour(residual: np.ndarray, change: np.ndarray, dt: float) -> float:
    """How much more than white noise the residual holds where ``change`` lives: the residual's
    spectral density (Welch, in units of its white noise, so white noise gives 1) averaged over
    frequency with the weights |FFT(change)|^2.

    A sum of squares rise of R noise variances from a change whose spectrum sits where the residual
    is ``colour`` times the white level is worth R / colour under that residual: near a resonance,
    the input's noise passed through the structure colours the output error, and a term that fits
    that colour would otherwise pass for a term that fits the physics.
    """
    nper = int(min(1024, residual.size // 8))
    if nper < 16 or not np.any(change):
        return 1.0
    f, p = welch(residual, fs=1.0 / dt, nperseg=nper)
    density = p / (2.0 * dt)                 # white unit-variance noise: 1
    weight = np.abs(np.fft.rfft(change)) ** 2
    total = float(np.sum(weight))
    if not total > 0:
        return 1.0
    return float(np.sum(weight * np.interp(np.fft.rfftfreq(change.size, dt), f, density)) / total)


def two_stage_polish(model: HystereticModel, run: Run, s: ReconSettings) -> HystereticModel:
    """Step 1 of the module doc. Returns the model (``model`` itself when not kept); its provenance's
    ``output_error_polish["two_stage"]`` records the figures either way."""
    two = TwoStages.of(run, s)
    if two is None:
        return model
    polish_info = dict(model.provenance.get("output_error_polish") or {})
    record = {"stages": two.names, "noise_std": two.noise}

    def with_record(m, **info):
        m.provenance = {**model.provenance, "output_error_polish": {**polish_info, **info, "two_stage": record}}
        return m

    try:
        new, info, items = two.fit(model)
        before, n = item_cost(model, items[1], s.tuning)
        gain = two.sse(model, items)[0] - two.sse(new, items)[0] if info["applied"] else 0.0
    except NUMERICAL_ERRORS as exc:
        record.update(applied=False, reason=f"{type(exc).__name__}: {exc}")
        return with_record(model)
    rms = float(np.std(item_target(items[1])[1])) or 1.0
    p = len(OutputError(model, [items[1]]).keys)
    limit = float(chdtri(p, s.tuning.joint_false_alarm))   # the chi-square's upper quantile

    last = {}     # the nonlinear stage's cost under the model rise() saw last, for the record at the end

    def cost(m) -> float:
        if last.get("model") is not m:
            last.update(model=m, cost=item_cost(m, m.fit_item(two.stages[1], tuning=s.tuning), s.tuning)[0])
        return last["cost"]

    def rise(m) -> float:
        """The nonlinear stage's sum of squares under ``m`` less under ``model``, in noise variances."""
        return n * (cost(m) ** 2 - before ** 2) / (two.noise[1] / rms) ** 2

    try:
        r = rise(new)
    except NUMERICAL_ERRORS as exc:
        record.update(applied=False, reason=f"{type(exc).__name__}: {exc}")
        return with_record(model)
    record.update(nonlinear_cost_before=before, rise_noise_variances=float(r), rise_limit=limit,
                  nfev=info.get("nfev"), joint_gain_noise_variances=float(gain))
    if not info["applied"]:
        # the joint polish found nothing better than the nonlinear stage's model: the stages do not
        # disagree under it, and there is nothing to decide
        record.update(applied=False, reason="the joint polish did not lower the joint cost")
        return with_record(model)
    if admissible(new, s.tuning) and r <= limit:
        if gain >= 1.0:
            new, record["terms"] = drop_terms(new, two)
            new, record["restart"] = restart(new, two, known=record["terms"])
        else:
            # the joint polish lowered the joint sum of squares by less than one noise variance (one
            # chi-square unit: no parameter moved by a standard error): the linear stage does not
            # contradict the nonlinear stage's model, and there is nothing for a term drop or a
            # restart to decide. The joint fit, the likelihood of both stages, is kept
            record["decided"] = ("the joint polish lowered the joint sum of squares by less than one noise "
                                 "variance: no term drop or restart")
    else:
        # the stages disagree under this model: its basin may be the nonlinear stage's alone (terms
        # that fit one loop and not the other stage); restarted from the stiffness terms, the joint fit
        # is kept when it agrees with the nonlinear stage after all
        new, record["restart"] = restart(model, two, force=True)
        if record["restart"]["applied"]:
            r = rise(new)
            record["restart"]["rise_noise_variances"] = float(r)
        if not (record["restart"]["applied"] and r <= limit):
            record["applied"] = False
            return with_record(model)
    record["applied"] = True
    after = cost(new)
    record["nonlinear_cost_after"] = after
    return with_record(new, applied=True, nrmse_after=after, stages=two.names, noise_std=two.noise)


def _joint_fit(model: HystereticModel, two: TwoStages):
    """(model, sse, n) of the joint polish from ``model``; None when it fails or is inadmissible."""
    try:
        new, _, items = two.fit(model)
        total, n = two.sse(new, items)
    except NUMERICAL_ERRORS:
        return None
    if not (admissible(new, two.tuning) and np.isfinite(total)):
        return None
    return new, total, n


def drop_terms(model: HystereticModel, two: TwoStages):
    """Step 2 of the module doc: (model, record). A term's cost is the rise of each stage's sum of
    squares divided by that stage's :func:`colour` where the loss changes the fit (never by less
    than 1: a residual quieter than its white floor does not make a term dearer)."""
    try:
        items = two.items(model)
        base = two.residuals(model, items)
    except NUMERICAL_ERRORS as exc:
        return model, {"failed": f"{type(exc).__name__}: {exc}"}
    sse, n = float(sum(e @ e for e, _ in base)), int(sum(e.size for e, _ in base))
    price = float(np.log(n))
    record = {"sse_noise_variances": sse, "samples": n, "price": price, "dropped": [], "rises": [],
              "costs": []}
    while model.fn_m:
        trials = []
        for k in sorted(model.fn_m):
            trial = HystereticModel.from_dict(model.to_dict())
            trial.provenance = model.provenance
            del trial.fn_m[k]
            fit = _joint_fit(trial, two)
            if fit is None:
                continue
            try:
                res = two.residuals(fit[0], two.items(fit[0]))
            except NUMERICAL_ERRORS:
                continue
            cost = 0.0
            for (e0, dt), (e1, _) in zip(base, res):
                cost += float(e1 @ e1 - e0 @ e0) / max(colour(e0, e1 - e0, dt), 1.0)
            trials.append((cost, float(sum(e @ e for e, _ in res)), k, fit[0], res))
        record["rises"].append({k: total - sse for _, total, k, _, _ in trials})
        record["costs"].append({k: c for c, _, k, _, _ in trials})
        if not trials:
            break
        cost, total, k, new, res = min(trials, key=lambda t: t[0])
        if not cost < price:
            break
        model, sse, base = new, total, res
        record["dropped"].append(k)
    record["sse_after"] = sse
    return model, record


def restart(model: HystereticModel, two: TwoStages, force: bool = False, known: dict | None = None):
    """Step 3 of the module doc (``force``: whatever the joint fit's level): (model, record).
    ``known``: :func:`drop_terms`'s record for ``model``, whose joint sum of squares is reused."""
    if known and "sse_after" in known:
        sse, n = known["sse_after"], known["samples"]
    else:
        try:
            sse, n = two.sse(model, two.items(model))
        except NUMERICAL_ERRORS as exc:
            return model, {"failed": f"{type(exc).__name__}: {exc}"}
    at, floor = at_floor(model, two, sse / n)
    record = {"mean_square_noise_variances": sse / n, "floor_noise_variances": floor,
              "limit": [floor / two.tuning.floor_ratio, two.tuning.floor_ratio * floor], "applied": False}
    if at and not force:
        return model, record
    trial = HystereticModel.from_dict(model.to_dict())
    trial.provenance = model.provenance
    trial.fn_m = {k: model.fn_m.get(k, 0.0) for k in STIFFNESS_TERMS}
    trial = with_term_scales(trial, two.items(trial))
    fit = _joint_fit(trial, two)
    record["start"] = "stiffness_terms"
    if fit is None or not at_floor(fit[0], two, fit[1] / n)[0]:
        # not at the floor from the model's own Bouc-Wen law either: the generic starts, screened
        fit = _generic_fit(model, two, record) or fit
    if fit is None:
        record["failed"] = "no restart's joint fit is finite and admissible"
        return model, record
    new, total, _ = fit
    new, record["terms"] = drop_terms(new, two)
    total = record["terms"].get("sse_after", total)
    record["restart_mean_square"] = total / n
    if total < sse:
        record["applied"] = True
        return new, record
    return model, record


def at_floor(model: HystereticModel, two: TwoStages, mean_square: float) -> tuple[bool, float]:
    """(whether ``model``'s joint mean square per sample is within tuning.floor_ratio of its floor either
    way, the floor): the module doc's test of a fit's basin. A floor that cannot be simulated
    (the model diverges under the input's noise) is no floor: the fit is not at it."""
    try:
        floor = two.floor(model, two.items(model))
    except NUMERICAL_ERRORS:
        return False, float("inf")
    if not np.isfinite(floor):
        return False, float("inf")
    ratio = two.tuning.floor_ratio
    return floor / ratio <= mean_square <= ratio * floor, floor


def _generic_fit(model: HystereticModel, two: TwoStages, record: dict):
    """The joint fit from the best of the generic Bouc-Wen starts (finish.generic_starts), each
    screened by a short joint polish; (model, sse, n) or None."""
    screened = []
    items = two.items(model)
    for share, knee, trial in generic_starts(model, items, two.tuning):
        try:
            new, info = polish(trial, [trial.fit_item(st, tuning=two.tuning) for st in two.stages], noise=two.noise,
                               max_nfev=two.tuning.screen_nfev, tuning=two.tuning)
        except NUMERICAL_ERRORS:
            continue
        if np.isfinite(info["nrmse_after"]):
            screened.append((info["nrmse_after"], share, knee, new))
    if not screened:
        return None
    _, share, knee, best = min(screened, key=lambda r: r[0])
    record["start"] = {"alpha_share": share, "knee": knee}
    return _joint_fit(best, two)

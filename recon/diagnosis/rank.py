"""Fit each candidate's augmented model by simulation and rank them on held-out data.

Output-error fit: the free parameters (the baseline's own ones, refitted, plus the
candidate's) minimise sum over fitting stages of |y_sim - y_rec|^2 / (N s^2), with
s^2 = noise^2 + (fit_model_share rms(y))^2 per stage (:func:`fit_scale`).
The held-out data are the validation stage(s); without one, the last 30 % of
every stage (the simulation runs through the whole stage, only the score is split).
A fitting stage whose response the validation stages do not reach (below cover_share
of its peak: the rig protocol's nonlinear stage) has its last 30 % held out as well,
so that the held-out data span the amplitudes the fit saw (:func:`uncovered_stages`); where
that stage reaches its top level only inside those 30 %, the fit keeps the level's first
half and the second half is held out (:func:`hold_cut`), so that the fit also sees the
amplitudes it is judged at.

Every candidate is compared with the *null* model: the baseline refitted the same
way on the same data, so a candidate only gets credit for what its extra terms add.
The figures of the comparison, all on the held-out samples (:func:`score`):

- dBIC = n_eff ln(MSE_cand / MSE_null) + k_added ln(n_eff), with n_eff the held-out
  residual's effective number of independent samples (from its autocorrelation) and
  k_added the candidate's number of extra parameters;
- explained: the share of the null model's excess over the noise floor,
  (MSE_null - MSE_cand) / (MSE_null - noise^2), that the candidate removes;
- gain: the mean-square reduction MSE_null - MSE_cand in units of the noise variance;
- rel: the relative cut of the held-out NRMSE, 1 - sqrt(MSE_cand / MSE_null);
- blocks: the share of held_blocks equal consecutive pieces of the held-out samples on
  which the candidate's mean-square error is below the null model's (:func:`blocks_improved`).

The significance rule (recon.diagnosis.settings.SignificanceRule; the field names below are
its fields, the figures its defaults). Every candidate needs dBIC < -bic_margin (10) and
explained >= min_explained (0.15): terms fitted to noise
fail both. It then passes by one of three routes:

- **Large gain:** gain >= min_gain_noise (1.5 noise variances) and rel >= min_rel_gain
  (0.10). An improvement smaller than the noise cannot be told from a better fit of the
  input-estimation errors; on clean recordings no candidate passing the other conditions
  reaches a gain of 1.5.
- **Steady:** blocks >= consistent_blocks (0.9, all but one of the ten pieces), gain >=
  steady_gain (0.1) and rel >= steady_rel_gain (0.04). A weak term that is truly missing
  (quadratic damping beside a refitted linear damping, a higher mode far above the band)
  acts throughout the record and lowers the held-out error by a few per cent, often by a
  fraction of the noise variance on a record at 40-80 dB; a fit of a passing error helps on
  some pieces and hurts on others.
- **Unanimous:** blocks >= complete_blocks (1.0, every piece), complete_explained (0.4) <=
  explained <= 1 (a candidate that goes below the noise floor means the floor is
  overestimated and the excess unknown), gain >= complete_gain (0.04) and rel >=
  complete_rel_gain (0.02). Where the reconstructed baseline has taken up most of an effect,
  what is left is small beside the noise; unanimity over the ten pieces is the evidence
  (10 of 10 by chance, were the pieces independent: 1 in 1024), and what the gain over the
  noise guards against, a fit of input-estimation errors, is a passing error.

Calibration: the thresholds were set on the stored candidate scores of the stress bench
(the independent generator's recordings, with and without an effect; bench/results,
docs/diagnosis.md), each placed between the largest figure a clean recording's candidate
reached and the figures of the effects the route is meant to name. They were set on
the same recordings they were first judged on; recordings from fresh generator seeds test them.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.jacobian import fit_jacobian
from recon.diagnosis.locate import equation_residual
from recon.differentiation import estimate_spectrum
from recon.library import monomials
from recon.model import HystereticModel
from recon.output_error.problem import (DIVERGED_RESIDUAL, FD_STEP, finite_or_differences, forward_differences,
                                        get_parameter, parameter_scales, set_parameter)
from recon.output_error.stopping import stop_for_stages, watched
from recon.regression.criteria import effective_samples
from recon.signals import base_motion, measured_velocity, response_target
from recon.simulation.resampling import thinned_input
from recon.diagnosis.settings import DEFAULT_RULE, DEFAULTS, DiagnosisSettings, SignificanceRule
from recon.threads import fd_map
from shakerlab.quantities import VELOCITY, channel_name
from shakerlab.run_data import BASE, Run, Stage

# the significance rule, the held-out split, the burn-in and the stages' weighting are settings
# (recon.diagnosis.settings): every function below that uses one takes ``settings`` (or ``rule``),
# the calibrated defaults when not given. The weighting: each fitting stage's error is divided by
# hypot(noise floor, fit_model_share x rms), the maximum-likelihood weighting where the noise
# dominates, with an allowance for the model's own error so that an averaged (nearly noise-free)
# stage does not outweigh the rest by its resolution alone. Weighting by each stage's rms instead
# lets a small, noisy stage set the cost by its noise, so that a large stage's error hardly counts
# and the fit can trade a true mode for one that fits the small stage's noise.
# Not tuned choices (no settings field): a physical bound and the noise estimate's numerics.
# physical: no displacement reading resolves better than 1e-5 of its peak (a 100 dB dynamic range),
# a property of the sensors, not a choice the diagnosis makes
RESOLUTION_FRACTION = 1e-5
# numerical: the difference orders k of difference_noise's white-noise estimate, which takes the
# smallest over them (the estimator's own search range, no threshold the answer is tuned with)
DIFF_ORDERS = (2, 3, 4, 5, 6)


def difference_noise(x: np.ndarray) -> float:
    """White-noise std of ``x`` from its k-th differences, sigma^2 = mean((D^k x)^2) / C(2k, k),
    the smallest over k = 2..6. Model-free: no fitted model's error can hide in it, and a smooth
    signal's part of D^k x falls as (w dt)^k, so the best order leaves the noise."""
    x = np.asarray(x, float)
    best = float("inf")
    for k in DIFF_ORDERS:
        if x.size <= k + 10:
            continue
        dk = np.diff(x, n=k)
        best = min(best, float(math.sqrt(np.mean(dk ** 2) / math.comb(2 * k, k))))
    return best if math.isfinite(best) else 0.0


def resolution_floor(x: np.ndarray) -> float:
    """The std a reading of ``x`` cannot resolve below: q / sqrt(12) when its values sit on a
    grid of step q (a quantised channel), and never below RESOLUTION_FRACTION of its peak."""
    x = np.asarray(x, float)
    peak = float(np.max(np.abs(x))) if x.size else 0.0
    floor = RESOLUTION_FRACTION * peak
    xs = x[: min(x.size, 20000)]
    steps = np.diff(np.unique(xs))
    steps = steps[steps > 1e-12 * max(peak, 1e-300)]
    if steps.size:
        q = float(np.min(steps))
        grid = (xs - xs.min()) / q
        if np.max(np.abs(grid - np.round(grid))) < 0.01:
            floor = max(floor, q / math.sqrt(12.0))
    return floor


def noise_floor(x: np.ndarray, dt: float) -> dict:
    """The noise std of one channel used by the significance tests, and its parts: the largest of
    the spectral floor, the difference-based floor and the resolution bound (averaged records
    have a spectral floor far below what the sensor resolves)."""
    parts = {"spectral": float(estimate_spectrum(x, dt).noise_std), "differences": difference_noise(x),
             "resolution": resolution_floor(x)}
    return {"std": max(parts.values()), **parts}


@dataclass
class StageData:
    """One stage as the diagnosis compares models with it, in the quantity the response was
    recorded in (``order``: 0 displacement, 1 velocity; recon.signals.response_target): ``y``,
    ``x_in``, ``noise`` and ``rms`` are in that quantity, ``motion`` is the relative displacement
    (for what a displacement decides: a contact's reach, the recorded range)."""
    name: str
    t: np.ndarray
    u: np.ndarray
    x_in: np.ndarray | None  # the base motion in the recorded quantity (base excitation)
    y: np.ndarray            # the recorded relative motion in the recorded quantity
    fit: np.ndarray          # boolean mask of fitting samples
    held: np.ndarray         # boolean mask of held-out samples
    noise: float             # white-noise std of the recorded y
    rms: float
    initial: tuple = (0.0, 0.0, 0.0)   # (y, y', z) at the first sample (0 when recorded from rest)
    start_model: HystereticModel | None = None   # the model whose force balance gave ``initial``'s z
    edge: tuple | None = None          # a fitting stage recorded in motion: its edge estimate (y, y', z)
    edge_model: HystereticModel | None = None    # the model whose force balance gave ``edge``'s z
    noise_parts: dict = field(default_factory=dict)   # per channel: spectral, differences, resolution
    fit_model_share: float = DEFAULTS.fit_model_share  # the model-error allowance of fit_scale (settings)
    order: int = 0                     # the recorded quantity: 0 displacement, 1 velocity
    motion: np.ndarray | None = None   # the relative displacement when y is not it
    fit_step: int = 1                  # a fit's iterations take every fit_step-th sample (settings.fit_rate)
    start_fit_share: float = DEFAULTS.start_fit_share  # held_start fits the start on this first share (settings)
    start_fit_nfev: int = DEFAULTS.start_fit_nfev      # ... with this many function evaluations (settings)
    stop_chi2: float = DEFAULTS.stop_chi2              # a fit over the stage stops at this gain (settings)
    step_factor: int = 1               # the simulator's sub-steps times this (integration_step_factor)

    @functools.cached_property
    def dt(self) -> float:
        """The median sampling interval (taken once: every simulation of the stage needs it)."""
        return float(np.median(np.diff(self.t)))

    def thinned(self) -> "StageData":
        """The stage as a fit's iterations see it: every ``fit_step``-th sample (the whole stage when
        1). The input is low-passed before it is thinned (recon.simulation.resampling.thinned_input,
        made once per input), so taking every q-th sample at no less than settings.fit_rate does not
        fold its noise into the response band; the parameters a fit finds on it differ from the full
        record's by far less than their standard errors, and every figure the rule reads is taken
        again on every sample (:func:`fit`)."""
        q = self.fit_step
        if q <= 1:
            return self
        cut = slice(None, None, q)
        return dataclasses.replace(
            self, t=self.t[cut], u=thinned_input(self.u, q), x_in=None if self.x_in is None else self.x_in[cut],
            y=self.y[cut], fit=self.fit[cut], held=self.held[cut],
            motion=None if self.motion is None else self.motion[cut], fit_step=1)

    @property
    def displacement(self) -> np.ndarray:
        """The stage's relative displacement y (integrated from a velocity record)."""
        return self.y if self.motion is None else self.motion

    @functools.cached_property
    def displacement_rms(self) -> float:
        return self.rms if self.motion is None else float(np.sqrt(np.mean((self.motion - self.motion.mean()) ** 2))) or 1.0


def velocity_offset(ys: np.ndarray, y: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """``ys`` with the constant that best matches it to the recorded velocity ``y`` over ``mask``
    (None: every sample) added: a velocity sensor's constant offset (and the mean of its
    low-frequency noise over the samples) is a nuisance parameter of every comparison in velocity,
    as in reconstruct's fits (recon.output_error.problem.measured_error)."""
    sel = slice(None) if mask is None or not mask.any() else mask
    with np.errstate(all="ignore"):
        offset = float(np.mean(y[sel] - ys[sel]))
    return ys + offset if math.isfinite(offset) else ys


def session_start(st: Stage) -> float:
    """Where stage ``st`` starts on the session's clock, the clock a slow change (a stiffness drift)
    runs on: an imported stage's original start (settings["source_t0"]), else the start the rig's
    run file records for it (settings["t0"], the acquisition's sample clock), else 0 (a stage whose
    own times are already on the session clock)."""
    for key in ("source_t0", "t0"):
        v = st.settings.get(key)
        if v is not None and math.isfinite(float(v)):
            return float(v)
    return 0.0


def stage_output(am: AugmentedModel, d: StageData, initial=None) -> np.ndarray:
    """``am``'s recorded-output prediction of stage ``d`` from ``initial`` (None: from rest), in the
    recorded quantity; in velocity with its constant offset fitted over the stage's fitting samples
    (all of them on a held-out stage)."""
    ys = am.simulate(d.t, d.u, d.x_in, initial, dt=d.dt, order=d.order, step_factor=d.step_factor)[0]
    return ys if d.order == 0 else velocity_offset(ys, d.y, d.fit)


def integration_step_factor(am: AugmentedModel, d: StageData, share: float, most: int = 8) -> int:
    """How many times finer than :meth:`AugmentedModel.substeps` the stage must be integrated for the
    simulator's own error to stay below ``share`` of the record's noise std (:func:`prepare`: the
    square root of the least gain the significance rule counts, so that the simulator's error alone
    can never make a candidate significant). The default step
    resolves the model's resonances; a stage whose input reaches far above them (a sweep, a
    harmonic-rich drive at a low sampling rate) or whose hysteresis turns sharply needs a finer one,
    and a model simulated too coarsely leaves a mismatch that no missing physics made, which a
    flexible candidate (a broad second mode) then fits. Step doubling: RK4's error falls about 16
    times per halved step, so the change from factor f to 2 f is the error at f; the first f whose
    change is below the bound is kept (at most ``most``)."""
    f = 1
    prev = stage_output(am, d)
    while f < most:
        finer = stage_output(am, dataclasses.replace(d, step_factor=2 * f))
        if not (np.all(np.isfinite(prev)) and np.all(np.isfinite(finer))):
            return f
        diff = finer - prev
        if d.order:
            diff = diff - diff.mean()      # a velocity record's offset is fitted (stage_output)
        if float(np.sqrt(np.mean(diff ** 2))) <= share * d.noise:
            return f
        f, prev = 2 * f, finer
    return f


def prepare(run: Run, model: HystereticModel, settings: DiagnosisSettings = DEFAULTS) -> list[StageData]:
    """Per stage: input (computed once), recorded y, fit/held masks, noise level."""
    names = list(run.stages)
    partly = partly_held_stages(run, settings)
    out = []
    for n in names:
        st = run.stage(n)
        # the Savitzky-Golay input, not the band-limited one reconstruct fits with
        # (recon.input_band): band-limiting changes the input near the band's edge, and an output
        # effect fitted on the changed input (a channel delay) can stop short of the truth while
        # another candidate is named in its place (docs/diagnosis.md)
        u = model.stage_input(st, band=False)
        measured = response_target(st)
        # judged in the quantity the response was recorded in: a velocity record in velocity, never
        # on its integrated displacement, whose drift (the integrated sensor noise) is no motion
        order, y = (0, st.y) if measured is None else measured
        fit = np.ones(y.size, bool)
        held = np.zeros(y.size, bool)
        if n not in partly:
            if n.startswith("validation"):
                fit[:] = False
                held[:] = True
        else:
            cut = hold_cut(st.y, settings)      # as fitting_part cuts it
            fit[cut:] = False
            held[cut:] = True
        x_in = None
        if st.excitation == BASE:
            x_in = st.channels["x_base"] if order == 0 else base_motion(st, order)
            tip = channel_name("x_tip", VELOCITY) if order else "x_tip"
            floors = {tip: noise_floor(measured_velocity(st) if order else st.channels[tip], st.dt),
                      ("x_base" if order == 0 else channel_name("x_base", VELOCITY)): noise_floor(x_in, st.dt)}
            noise = math.hypot(*(f["std"] for f in floors.values()))
        else:
            name = "x" if order == 0 else channel_name("x", st.quantities["x"])
            floors = {name: noise_floor(y, st.dt)}
            noise = floors[name]["std"]
        t_session = st.t + session_start(st)
        # (a sampling interval read from the times is 8 kHz to within rounding: 7999.99999 is 8 kHz)
        step = max(1, int(math.floor(1.0 / (st.dt * settings.fit_rate) + 1e-6))) if settings.fit_rate > 0 else 1
        d = StageData(n, t_session, u, x_in, y,
                      fit, held, noise, float(np.sqrt(np.mean((y - y.mean()) ** 2))) or 1.0, noise_parts=floors,
                      fit_model_share=settings.fit_model_share, order=order, motion=None if order == 0 else st.y,
                      fit_step=step, start_fit_share=settings.start_fit_share,
                      start_fit_nfev=settings.start_fit_nfev, stop_chi2=settings.stop_chi2)
        d.step_factor = integration_step_factor(AugmentedModel(model), d, math.sqrt(settings.rule.smallest_gain()))
        # the edge estimate, not a start fitted with the baseline: a fitted start absorbs what an
        # output effect (a channel delay, a tip-scale error) does to the first seconds, and the
        # candidate that models it is then scored from a start made for the model without it
        # (on bench/diagnose.py's recordings at 70 dB this doubled the true candidate's NRMSE for
        # channel_delay and sensor_scale)
        start = model.stage_start(st, u, fit=False)
        if any(start) and not fit.any():
            # a held-out stage recorded in motion: every model fits its own start from this edge
            # estimate (held_start), so whether the baseline simulates the stage well from it must not
            # decide: a baseline that lacks the effect can prefer a start from rest, and then every
            # model, the truth included, is scored from a start far from the stage's true state
            d.initial, d.start_model = start, model
        elif any(start):
            # a stage recorded mid-motion starts from its estimated state, but the estimate is taken
            # at the stage's edge, where a channel skew or scale error also shows: keep it only if
            # the baseline simulates the stage better from it than from rest (and each fit judges
            # it again with its own start model, own_starts)
            d.edge, d.edge_model = start, model
            am = AugmentedModel(model)
            from_rest = stage_output(am, d)
            from_start = stage_output(am, d, start)
            if np.sum((from_start - y) ** 2) < np.sum((from_rest - y) ** 2):
                d.initial, d.start_model = start, model
            d.fit = burn_in(d.t, d.fit, model, settings=settings)
        out.append(d)
    return out


def burn_in(t: np.ndarray, fit: np.ndarray, model: HystereticModel, decays: float | None = None,
            keep: float | None = None, hysteresis_only: bool = True,
            settings: DiagnosisSettings = DEFAULTS) -> np.ndarray:
    """The fitting mask of a stage recorded in motion without its first ``decays`` (default
    ``settings.burn_in_decays``) decay times of ``model``'s mode (2 / c each, c per unit mass), unless
    fewer than ``keep`` (default ``settings.burn_in_keep``) of its fitting samples would remain, the model has no damped
    mode (c <= 0 or k <= 0) or, with ``hysteresis_only``, no hysteresis (alpha = 0): then ``fit``
    as given.

    Such a stage starts with a state no fit knows well: the edge gives y and y' well, but the
    hysteresis state z the previous stage left is not observed (its force balance holds the edge's
    noisy y'' and whatever the model lacks). Its error then
    decays with the mode, and the stage's first seconds can hold most of the fitting cost: even the
    true model, started as the fits start it, then errs far more over the first decay times than
    from the true state, and the fits trade the rest of the record for that transient (naming a
    wrong candidate). Leaving the first decay times out of the fit removes the transient.
    Without hysteresis y and y' are the whole state, and the cut only takes information away (on
    the bolted beam it costs held-out accuracy and a named effect); see docs/diagnosis.md."""
    decays = settings.burn_in_decays if decays is None else decays
    keep = settings.burn_in_keep if keep is None else keep
    if not (model.c_m > 0 and model.k_m > 0) or (hysteresis_only and model.alpha_m == 0.0) \
            or not fit.any() or decays <= 0:
        return fit
    cut = fit & (t >= t[0] + decays / (model.c_m / 2.0))
    return cut if cut.sum() > keep * fit.sum() else fit


def fit_cut(n: int, settings: DiagnosisSettings = DEFAULTS) -> int:
    """Where a stage of ``n`` samples that is partly held out stops being fitted (its last
    ``settings.hold_fraction`` is held out)."""
    return int((1 - settings.hold_fraction) * n)


def hold_cut(y: np.ndarray, settings: DiagnosisSettings = DEFAULTS) -> int:
    """Where a stage with response ``y`` that is partly held out stops being fitted: at
    :func:`fit_cut`, unless the response reaches its top level only after that (its fitting samples
    stay below ``settings.top_reach`` of the stage's peak). Then half of the top level is fitted and
    its second half held out, from the first sample that reaches that share of the peak on.

    The rig protocol's nonlinear stage steps its level up, and where the last level begins in the
    stage's last hold_fraction the fit never sees the amplitudes it is judged at: a contact that
    only the top level engages is then not fitted at all, and a model fitted below the top level
    can diverge when predicting it (a polynomial baseline extrapolated past its fitted range)."""
    y = np.asarray(y, float)
    cut = fit_cut(y.size, settings)
    peak = response_peak(y)
    if not (peak > 0) or response_peak(y[:cut]) >= settings.top_reach * peak:
        return cut
    onset = int(np.argmax(np.abs(y - y.mean()) >= settings.top_reach * peak))
    return max(cut, (onset + y.size) // 2)


def response_peak(y: np.ndarray) -> float:
    """The response's peak about its mean, robust to single outliers (99.9th percentile of |y - mean|)."""
    y = np.asarray(y, float)
    return float(np.percentile(np.abs(y - y.mean()), 99.9)) if y.size else 0.0


def has_validation(run: Run) -> bool:
    """Whether ``run`` has validation stage(s) besides stages to fit on."""
    names = list(run.stages)
    return any(n.startswith("validation") for n in names) and any(not n.startswith("validation") for n in names)


def uncovered_stages(run: Run, settings: DiagnosisSettings = DEFAULTS) -> set[str]:
    """The fitting stages whose response the validation stage(s) do not reach: each one whose peak
    exceeds the largest validation peak by more than 1 / ``settings.cover_share`` (0.4: between the protocols that
    reach less, the rig protocol's 0.13-0.29 on the stress bench, and those that reach more, the paper
    protocol's, sweeps', multisines' 0.53-0.98, recon.testing.concealed's 0.50-0.60). Their last hold_fraction is
    held out too, so that the held-out data span the amplitudes the fit saw. An effect that acts
    only at large amplitude cannot be scored on a validation stage that never gets there: the rig
    protocol's validation tone (0.7 f_res at 0.75 of the final level) moves y to about a third of
    the nonlinear stage's peak, so a contact the nonlinear stage engages and the validation stage
    does not scores the truth no better than the baseline there."""
    if not has_validation(run):
        return set()
    names = list(run.stages)
    val = [response_peak(run.stage(n).y) for n in names if n.startswith("validation")]
    reach = max(val, default=0.0)
    return {n for n in names if not n.startswith("validation")
            and response_peak(run.stage(n).y) * settings.cover_share > reach}


def partly_held_stages(run: Run, settings: DiagnosisSettings = DEFAULTS) -> set[str]:
    """The stages of ``run`` whose end (from :func:`hold_cut` on) is held out: every stage of a run
    without validation stages, else the :func:`uncovered_stages`."""
    return uncovered_stages(run, settings) if has_validation(run) else set(run.stages)


def fitting_part(run: Run, settings: DiagnosisSettings = DEFAULTS) -> Run:
    """``run`` with each of its :func:`uncovered_stages` cut to its fitting samples (before
    :func:`hold_cut`): all a baseline reconstructed for the diagnosis may see, so that its
    held-out score stays out of sample. ``run`` itself when no stage is cut."""
    cut_stages = uncovered_stages(run, settings)
    if not cut_stages:
        return run
    stages = {}
    for n, st in run.stages.items():
        if n in cut_stages:
            cut = hold_cut(st.y, settings)
            st = Stage(n, st.t[:cut], {c: v[:cut] for c, v in st.recorded().items()}, st.excitation,
                       dict(st.settings))
        stages[n] = st
    return Run(stages, dict(run.attrs), run.source)


def initial_for(am: AugmentedModel, d: StageData) -> tuple:
    """``d``'s start state for ``am``: (y0, y'0) as recorded, and z0 from ``am``'s own force balance
    at the first sample (HystereticModel.start_z), not the baseline's. z0 = g u - y'' - c y' - k y -
    fn(y, y') takes whatever the model leaves out of the balance: a constant force the baseline
    lacks sits in the baseline's z0, and a candidate that models it (offset) would count it twice
    (the true model with its offset then fits far worse from the baseline's z0 than from its
    own). The recorded y'' cancels: only the
    change of the model's terms between the two models enters."""
    s0 = d.initial
    base = d.start_model
    if am.baseline.alpha_m == 0.0 and s0[2] != 0.0:
        # a model without hysteresis keeps z constant: a z0 taken from a hysteretic baseline's
        # balance would act on it as a permanent force
        return (float(s0[0]), float(s0[1]), 0.0)
    if base is None or base.alpha_m == 0.0 or am.baseline.alpha_m == 0.0 or am.baseline is base:
        return s0
    y0, v0, z0 = (float(v) for v in s0)
    u0 = float(d.u[0])
    with np.errstate(all="ignore"):
        dz = am.baseline.balance(u0, y0, v0, 0.0) - base.balance(u0, y0, v0, 0.0)
    return (y0, v0, z0 + dz) if math.isfinite(dz) else s0


def held_start(am: AugmentedModel, d: StageData) -> tuple:
    """The start state ``am`` simulates the held-out stage ``d`` from. A stage recorded in motion
    starts from its edge estimate (y, y', z), which a noisy edge derivative makes poor: at 50 dB
    the edge start alone can put the validation NRMSE of every model, the true one included, an
    order of magnitude above its value from a fitted start. Each model's start (y0, y'0, and z0
    when it has hysteresis) is therefore fitted to the first ``d.start_fit_share`` of the stage
    (settings.start_fit_share, with settings.start_fit_nfev evaluations) by output error: every
    model gets the same treatment, so a candidate that changes the output (a delay, a scale error)
    fits its own start. With hysteresis
    the fit also starts from the best of z0 across the law's reach (:func:`z_reach`) on that first
    part, and that start is kept where it simulates the whole stage better."""
    return _held_start(am, d)[0]


def z_reach(b: HystereticModel, y: np.ndarray) -> float:
    """The largest |z| the law ``b`` reaches on the motion ``y``: alpha times half the peak-to-peak
    motion (z's elastic rise from one turning point to the next), at most the law's saturation
    alpha / (gamma + delta) when that is positive."""
    z = abs(b.alpha_m) * 0.5 * float(np.ptp(y)) if y.size else 0.0
    if b.gamma + b.delta > 0.0:
        z = min(z, abs(b.alpha_m) / (b.gamma + b.delta))
    return z if math.isfinite(z) else 0.0


def _held_start(am: AugmentedModel, d: StageData) -> tuple:
    """(:func:`held_start`'s state, the whole stage simulated from it, or None when the state is
    the stage's own ``initial``)."""
    initial = initial_for(am, d)
    s0 = np.asarray(initial, float)
    if d.fit.any() or not np.any(s0):
        return initial, None
    free = 3 if am.baseline.alpha_m != 0.0 else 2
    b = am.baseline
    # the start is fitted on the stage's thinned samples (StageData.thinned), judged on all of them
    th = d.thinned()
    first = slice(0, max(int(d.start_fit_share * th.y.size), 10))

    def first_error(state):
        ys = am.simulate(th.t[first], th.u[first], None if th.x_in is None else th.x_in[first], tuple(state),
                         order=th.order, step_factor=th.step_factor)[0]
        r = ys - th.y[first]
        if d.order:
            r = r - r.mean()       # the velocity offset (stage_output)
        return r if np.all(np.isfinite(r)) else np.full(r.size, DIVERGED_RESIDUAL * d.rms)

    def sq(r):
        return float(r @ r)

    best = None
    if free == 3 and s0[2] != 0.0:
        # z0 from the force balance at the edge carries the edge's y'' noise, and a law whose z is
        # small (alpha near 0) cannot hold it: also start from z0 = 0 and keep the better start on
        # the first part (a start fit from a z0 the law cannot hold may run off to a worse one)
        with np.errstate(all="ignore"):
            tries = [(sq(first_error(st)), i, st) for i, st in enumerate((s0, np.array([s0[0], s0[1], 0.0])))]
        best, _, s0 = min(tries)
    out = _start_fit(am, d, s0, initial, first_error, free)
    if free == 3:
        # z0 across the range the law can hold: the start fit moves z0 only locally, so a stage
        # that starts with z0 far from the edge's estimate and from 0 is not reached by it. A
        # start better on the first part is fitted too, and kept only if it also simulates the
        # whole stage better: a model that lacks an effect could fit the first part from a z0 the
        # rest of the stage refutes
        with np.errstate(all="ignore"):
            best = sq(first_error(s0)) if best is None else best
            scan = min((sq(first_error(st)), i, st) for i, st in enumerate(
                np.array([s0[0], s0[1], zc]) for zc in
                z_reach(b, th.displacement[first]) * np.array([-1.0, -0.5, -0.25, 0.25, 0.5, 1.0])))
        if scan[0] < best:
            other = _start_fit(am, d, scan[2], initial, first_error, free)
            if _stage_error(am, d, other) < _stage_error(am, d, out):
                out = other
    return out


def _stage_error(am: AugmentedModel, d: StageData, start: tuple) -> float:
    """The squared error over the whole stage ``d`` of ``am`` simulated from ``start`` (a
    :func:`_start_fit` answer: (state, the simulation or None)); inf where it does not simulate."""
    state, ys = start
    if ys is None:
        with np.errstate(all="ignore"):
            ys = stage_output(am, d, tuple(state))
    with np.errstate(all="ignore"):
        e = float(np.sum((ys - d.y) ** 2))
    return e if math.isfinite(e) else math.inf


def _start_fit(am: AugmentedModel, d: StageData, s0: np.ndarray, initial: tuple, first_error, free: int) -> tuple:
    """The start state fitted from ``s0`` to the first part of the held-out stage ``d``
    (``first_error``: the residual there of a state), with the whole stage simulated from it; or
    (``s0``, None) where the fit does not improve on it or the state does not carry the stage."""
    b = am.baseline
    base_state = tuple(float(v) for v in s0)
    w = math.sqrt(max(b.K_m, 1e-12))
    scale = np.maximum(np.abs(s0[:free]),
                       0.01 * d.displacement_rms * np.array([1.0, w, max(abs(b.alpha_m), 1e-12)])[:free])

    def state(p):
        out = s0.copy()
        out[:free] = s0[:free] + p * scale
        return tuple(out)

    def resid(p):
        return first_error(state(p))

    base = (initial, None) if base_state == tuple(float(v) for v in initial) else (base_state, None)
    try:
        with np.errstate(all="ignore"):
            sol = least_squares(resid, np.zeros(free), method="trf", x_scale=1.0, max_nfev=int(d.start_fit_nfev),
                                workers=fd_map())
    except (ArithmeticError, ValueError, np.linalg.LinAlgError):
        return base
    r0 = resid(np.zeros(free))
    if not float(sol.fun @ sol.fun) < float(r0 @ r0):
        return base
    # a state fitted on the first part must also carry the simulation through the whole stage
    with np.errstate(all="ignore"):
        ys = stage_output(am, d, state(sol.x))
    return (state(sol.x), ys) if np.all(np.isfinite(ys)) else base


def own_starts(am: AugmentedModel, data: list[StageData]) -> list[StageData]:
    """``data`` with each fitting stage recorded in motion started from rest or from its edge
    estimate, whichever ``am`` simulates that stage better from. :func:`prepare` lets the baseline
    judge it, and a baseline without the effect may judge it wrong: with a constant force, a
    stage that starts at rest at the force's static displacement looks no better from the edge to
    a baseline without the force, and every model would start from rest, the truth included,
    which then fits far worse than from the edge."""
    out = []
    for d in data:
        if d.edge is None or not d.fit.any():
            out.append(d)
            continue
        tries = [dataclasses.replace(d, initial=(0.0, 0.0, 0.0), start_model=None),
                 dataclasses.replace(d, initial=d.edge, start_model=d.edge_model)]
        if am.baseline.alpha_m != 0.0:
            # and from the edge's (y, y') with the law at rest (z = 0): the edge's z0 comes from the
            # force balance, which holds whatever the model leaves out (a constant force beside a
            # Bouc-Wen law puts the force into the balance's z0 where the true z0 is 0).
            # A fixed z0, not a fitted one: a z0 free per stage acts as a constant force itself
            tries.append(dataclasses.replace(d, initial=(float(d.edge[0]), float(d.edge[1]), 0.0), start_model=None))
        err = []
        for x in tries:
            with np.errstate(all="ignore"):
                ys = stage_output(am, x, initial_for(am, x))
                e = float(np.sum((ys[x.fit] - x.y[x.fit]) ** 2))
            err.append(e if math.isfinite(e) else math.inf)
        out.append(tries[int(np.argmin(err))] if math.isfinite(min(err)) else d)
    return out


def simulate_all(am: AugmentedModel, data: list[StageData]) -> list[np.ndarray]:
    return simulate_stages(am, data)[0]


def simulate_stages(am: AugmentedModel, data: list[StageData]) -> tuple[list[np.ndarray], list]:
    """(``am``'s output per stage, the start each stage was simulated from): each output is
    ``stage_output(am, d, start)``, so the starts simulate it again to the bit (FitResult.sims)."""
    out, starts = [], []
    for d in data:
        start, ys = _held_start(am, d)
        out.append(ys if ys is not None else stage_output(am, d, start))
        starts.append(start)
    return out, starts


def nrmse_per_stage(am: AugmentedModel, data: list[StageData], sims=None) -> dict:
    sims = sims if sims is not None else simulate_all(am, data)
    out = {}
    for d, ys in zip(data, sims):
        if not np.all(np.isfinite(ys)):
            out[d.name] = float("inf")
            continue
        out[d.name] = float(np.sqrt(np.mean((ys - d.y) ** 2)) / d.rms)
    return out


# ------------------------------------------------------------------ parameters
def baseline_keys(model: HystereticModel) -> list[str]:
    keys = ["c_m", "k_m"]
    if model.alpha_m != 0.0:
        keys += ["alpha_m", "gamma", "delta"]
    keys += [f"fn:{k}" for k in model.fn_m]
    if model.excitation != BASE:
        keys.append("inv_m")
    return keys


def fit_scale(d: StageData) -> float:
    """The error a stage's fitting samples are divided by: its noise floor, with its
    ``fit_model_share`` (DiagnosisSettings) of its rms added in quadrature."""
    return math.hypot(d.noise, d.fit_model_share * d.rms) or d.rms


def fit_residual(am: AugmentedModel, data: list[StageData]) -> np.ndarray:
    """The weighted residual :func:`fit` minimises: every fitting sample, each stage's error over its
    :func:`fit_scale` and the square root of its sample count (DIVERGED_RESIDUAL throughout if a
    stage diverges)."""
    out = []
    for d in data:
        if not d.fit.any():
            continue
        ys = stage_output(am, d, initial_for(am, d))
        if not np.all(np.isfinite(ys)):
            return np.full(sum(int(x.fit.sum()) for x in data), DIVERGED_RESIDUAL)
        out.append((ys[d.fit] - d.y[d.fit]) * (1.0 / (fit_scale(d) * math.sqrt(max(int(d.fit.sum()), 1)))))
    return np.concatenate(out)


def fit_cost(am: AugmentedModel, data: list[StageData]) -> float:
    """:attr:`FitResult.cost_fit` of ``am`` as it is, from the fitting stages alone (each stage
    started as :func:`fit` starts it: :func:`own_starts`, on the samples it fits, StageData.thinned)."""
    r = fit_residual(am, own_starts(am, [d.thinned() for d in data]))
    return float(r @ r) / max(len([d for d in data if d.fit.any()]), 1)


@dataclass
class FitResult:
    model: AugmentedModel
    cost_fit: float                  # mean-square normalised residual on the fitting samples
    mse_held: float                  # mean-square held-out residual [m^2]
    nrmse: dict                      # per stage (whole stage)
    nrmse_held: float                # held-out NRMSE (all held-out samples together)
    n_held: int
    resid_held: np.ndarray = field(repr=False, default=None)
    stderr: dict = field(default_factory=dict)
    seconds: float = 0.0
    # the stages the fit was scored on and the start each was simulated from: :attr:`sims` again
    sim_stages: list = field(repr=False, default=None)
    sim_starts: list = field(repr=False, default=None)
    _sims: list = field(init=False, repr=False, compare=False, default=None)

    @property
    def sims(self) -> list | None:
        """The model's simulated output per stage (None for a fit not scored). Simulated again when
        first read, from the starts the fit's own simulation took (the same numbers), and kept: a
        diagnosis makes dozens of fits and reads the output of a few, each several MiB at 10 kHz."""
        if self._sims is None and self.sim_stages is not None:
            self._sims = [stage_output(self.model, d, s) for d, s in zip(self.sim_stages, self.sim_starts)]
        return self._sims


def fit(am: AugmentedModel, keys: list[str], data: list[StageData], scales: dict | None = None,
        max_nfev: int = 40, bounds: dict | None = None, scored: bool = True) -> FitResult:
    """Output-error least squares of ``keys`` (start: ``am``'s values).

    ``scored=False``: a screen, which ranks starts by the fitting cost alone: the result holds the
    fitted model and ``cost_fit`` (the same as a scored fit's), without the standard errors and the
    held-out simulation (``mse_held`` nan, no ``sims``)."""
    t0 = time.perf_counter()
    full = data
    scales = scales or {}
    bounds = bounds or {}
    # the iterations, and the choice of each stage's start, on its thinned samples
    # (StageData.thinned); every figure after them on all of them, from the start chosen
    data = own_starts(am, [d.thinned() for d in data])
    full = [dataclasses.replace(f, initial=d.initial, start_model=d.start_model) if d.initial is not f.initial
            or d.start_model is not f.start_model else f for f, d in zip(full, data)]
    x0 = np.array([get_parameter(am, k) for k in keys], float)
    sc = parameter_scales(keys, x0, am.baseline.gamma + am.baseline.delta, scales)
    lo = np.array([(bounds.get(k, (-np.inf, np.inf))[0] - x0[i]) / sc[i] for i, k in enumerate(keys)])
    hi = np.array([(bounds.get(k, (-np.inf, np.inf))[1] - x0[i]) / sc[i] for i, k in enumerate(keys)])
    lo = np.minimum(lo, -1e-12)
    hi = np.maximum(hi, 1e-12)

    def build(p):
        m = am.copy()
        for i, k in enumerate(keys):
            set_parameter(m, k, x0[i] + p[i] * sc[i])
        return m

    def resid(p):
        return fit_residual(build(p), data)

    p0 = np.clip(np.zeros(len(keys)), lo, hi)
    if keys:
        # stopped once an iteration gains less than settings.stop_chi2 (a hundredth) of a chi-square
        # unit of the fit's own likelihood (each stage's error over its fit_scale):
        # recon.output_error.stopping
        stop = stop_for_stages([int(d.fit.sum()) for d in data if d.fit.any()],
                               min((d.stop_chi2 for d in data), default=DEFAULTS.stop_chi2))
        # the Jacobian from forward sensitivities where they reach (recon.diagnosis.jacobian), else
        # forward differences
        jac = fit_jacobian(build, keys, sc, data, initial_for, fit_scale, am)
        jac = watched(finite_or_differences(jac, resid, hi), stop, (lo, hi)) if jac is not None else None
        sol = least_squares(resid, p0, jac=jac or "2-point", method="trf", bounds=(lo, hi), x_scale=1.0,
                            diff_step=FD_STEP, max_nfev=max_nfev, xtol=1e-10, ftol=1e-10,
                            workers=None if jac else fd_map(), callback=stop)
        p = sol.x
        cost = float(sol.fun @ sol.fun)
        stderr = {} if not scored else _standard_errors(sol, keys, sc, cost, resid, p, hi)
    else:
        p = p0
        r = resid(p0)
        cost = float(r @ r)
        stderr = {}
    m = build(p)
    data = full
    if not scored:
        return FitResult(model=m, cost_fit=cost / max(len([d for d in data if d.fit.any()]), 1),
                         mse_held=float("nan"), nrmse={}, nrmse_held=float("nan"), n_held=0,
                         seconds=time.perf_counter() - t0)
    sims, starts = simulate_stages(m, data)
    held = [(ys - d.y)[d.held] for d, ys in zip(data, sims)]
    rh = np.concatenate(held) if held else np.zeros(0)
    yh = np.concatenate([d.y[d.held] - d.y[d.held].mean() for d in data if d.held.any()]) if rh.size else np.zeros(0)
    mse = float(np.mean(rh ** 2)) if rh.size and np.all(np.isfinite(rh)) else float("inf")
    nh = float(math.sqrt(mse / np.mean(yh ** 2))) if rh.size and np.mean(yh ** 2) > 0 else float("nan")
    return FitResult(model=m, cost_fit=cost / max(len([d for d in data if d.fit.any()]), 1), mse_held=mse,
                     nrmse=nrmse_per_stage(m, data, sims), nrmse_held=nh, n_held=int(rh.size), resid_held=rh,
                     stderr=stderr, seconds=time.perf_counter() - t0, sim_stages=data, sim_starts=starts)


def _standard_errors(sol, keys: list[str], sc: np.ndarray, cost: float, resid, p: np.ndarray,
                     hi: np.ndarray) -> dict:
    """Each fitted key's standard error from the solver's last Jacobian ({} where it is singular)."""
    try:
        J = sol.jac
        if not np.all(np.any(J != 0.0, axis=0)):
            # a column of zeros in the solver's last Jacobian (seen with friction's mu and v0
            # after a bounded fit ended on its evaluation limit) would give that parameter a
            # zero standard error: the Jacobian is taken again at the solution
            J = forward_differences(resid, p, hi)
        with np.errstate(all="ignore"):
            jtj = J.T @ J
        if not (np.all(np.isfinite(jtj)) and math.isfinite(cost)):
            # an overflowed Jacobian has no covariance, and LAPACK's SVD of a matrix holding inf or
            # nan can run for minutes before it gives up (seen on a 6 kHz multisine record)
            return {}
        dof = max(sol.fun.size - len(keys), 1)
        cov = np.linalg.pinv(jtj) * (cost / dof)
        return {k: float(math.sqrt(max(cov[i, i], 0.0)) * sc[i]) for i, k in enumerate(keys)}
    except (np.linalg.LinAlgError, ValueError):
        return {}


def held_noise_mse(data: list[StageData]) -> float:
    """The noise floor's mean square over every held-out sample (each stage at its own floor)."""
    return float(np.sum([np.sum(d.held) * d.noise ** 2 for d in data]) / max(sum(int(d.held.sum()) for d in data), 1))


def blocks_improved(ref_resid, cand_resid, blocks: int = DEFAULT_RULE.held_blocks) -> float | None:
    """The share of ``blocks`` equal consecutive pieces of the held-out samples on which the
    candidate's mean-square error is below the reference's (None without both residuals): a term
    that is missing acts throughout the record, a fit of a passing error helps here and hurts there."""
    if ref_resid is None or cand_resid is None or ref_resid.size != cand_resid.size or ref_resid.size < blocks:
        return None
    a = np.array_split(np.asarray(ref_resid, float) ** 2, blocks)
    b = np.array_split(np.asarray(cand_resid, float) ** 2, blocks)
    return float(np.mean([float(np.mean(y)) < float(np.mean(x)) for x, y in zip(a, b)]))


def passes(dbic: float, explained: float, gain: float, rel: float, blocks: float | None = None,
           rule: SignificanceRule = DEFAULT_RULE) -> bool:
    """The significance rule on a candidate's held-out figures (SignificanceRule.passes)."""
    return rule.passes(dbic, explained, gain, rel, blocks)


def smallest_relative_cut(rule: SignificanceRule = DEFAULT_RULE) -> float:
    """The smallest relative cut of the held-out NRMSE that any route of the rule accepts."""
    return rule.smallest_relative_cut()


def score(null: FitResult, cand: FitResult, k_added: int, noise_mse: float,
          rule: SignificanceRule = DEFAULT_RULE) -> dict:
    """Held-out comparison of a candidate with the null model (see the module docstring)."""
    n_eff = effective_samples(null.resid_held)
    if not (math.isfinite(cand.mse_held) and math.isfinite(null.mse_held)) or cand.mse_held <= 0 or null.mse_held <= 0:
        return {"dbic": float("inf"), "explained": 0.0, "n_eff": n_eff, "significant": False}
    dbic = n_eff * math.log(cand.mse_held / null.mse_held) + k_added * math.log(n_eff)
    # a reference at or below the noise floor leaves nothing to explain (and the gain over the noise
    # then fails too): 0, not a ratio over a vanishing excess (it read 8e282 in the JSON)
    excess = null.mse_held - noise_mse
    explained = (null.mse_held - cand.mse_held) / excess if excess > 0 else 0.0
    gain = (null.mse_held - cand.mse_held) / max(noise_mse, 1e-300)
    rel = 1.0 - math.sqrt(cand.mse_held / null.mse_held)
    blocks = blocks_improved(null.resid_held, cand.resid_held, rule.held_blocks)
    return {"dbic": float(dbic), "explained": float(explained), "gain_over_noise": float(gain),
            "n_eff": float(n_eff), "relative_gain": float(rel),
            "blocks_improved": blocks,
            "significant": rule.passes(dbic, explained, gain, rel, blocks)}


def equation_step(am: AugmentedModel, keys: list[str], new_key: str | None, column, derivs: dict,
                  data: list[StageData], settings: DiagnosisSettings = DEFAULTS):
    """Start for a candidate whose term is linear in its parameter: one least-squares step on the
    equation residual of ``am`` over the fitting samples,

        e = du.c y' + du.k y + sum du.a_j phi_j + theta col(y, y', t) - du.g u,

    then ``am`` moved by those increments (the differentiation bias is common to every
    column, so increments are far less biased than a fresh equation-error fit).
    Returns (model, relative residual rms)."""

    names = [k for k in keys if k in ("c_m", "k_m", "inv_m") or k.startswith("fn:")]
    stages = []
    for d in data:
        if not d.fit.any() or d.name not in derivs:
            continue
        t = derivs[d.name][0]
        stages.append((d, t <= d.t[d.fit][-1]))
    # the rows written straight into one matrix, stage after stage (at a 10 kHz stage each rows x
    # columns array is tens of MiB: no per-stage copies beside it); each entry is the same quotient
    # column / frms as a stacked matrix would hold
    A = np.empty((sum(int(np.count_nonzero(sel)) for _, sel in stages), len(names) + (new_key is not None)))
    b = np.empty(A.shape[0])
    row = 0
    for d, sel in stages:
        t, y, dy, ddy, u, dt = derivs[d.name]
        _, _, e, _, frms = equation_residual(am, derivs[d.name])
        block = A[row:row + np.count_nonzero(sel)]
        j = 0
        for k in keys:
            if k == "c_m":
                col = dy
            elif k == "k_m":
                col = y * (1.0 + am.get("drift") * t)
            elif k.startswith("fn:"):
                p, r = monomials.parse(k[3:])
                col = y ** p * dy ** r
            elif k == "inv_m":
                col = -u
            else:
                continue
            np.divide(col[sel], frms, out=block[:, j])
            j += 1
        if new_key is not None:
            np.divide(np.asarray(column(am, t, y, dy), float)[sel], frms, out=block[:, j])
        np.divide(e[sel], frms, out=b[row:row + block.shape[0]])
        row += block.shape[0]
    ok = np.isfinite(b) & np.all(np.isfinite(A), axis=1)
    if ok.sum() < max(settings.step_min_finite * b.size, 10 * A.shape[1]):
        # finite on too few samples (settings.step_min_finite): the baseline's restoring force is
        # not finite along the recorded path (a Bouc-Wen law so stiff that z integrated on the
        # measured y' overflows, or a term of high order): no equation-error step, the candidate
        # starts from ``am`` as it is
        return am.copy(), float("inf")
    if not ok.all():
        A, b = A[ok], b[ok]
    norms = np.linalg.norm(A, axis=0)
    norms[norms == 0] = 1.0
    coef, *_ = np.linalg.lstsq(A / norms, b, rcond=None)
    coef = coef / norms
    resid = float(np.linalg.norm(b - A @ coef) / (np.linalg.norm(b) or 1.0))
    m = am.copy()
    for k, c in zip(names, coef):
        set_parameter(m, k, get_parameter(m, k) + c)
    if new_key is not None:
        set_parameter(m, new_key, get_parameter(m, new_key) + coef[-1])
    return m, resid

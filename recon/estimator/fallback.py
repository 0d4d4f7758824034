"""What reconstruct answers when the full model fails: the best admissible simpler model.

When no pass of the estimator gives a physically admissible model (every estimate has
alpha <= 0, a Bouc-Wen law that does not saturate, a negative stiffness, or a simulation
that diverges), or when every pass failed numerically, the answer is the admissible
model of the simplest kinds below that predicts the held-out stages best:

1. ``bouc_wen_fewer_terms``: the Bouc-Wen law with y^2, y^3 and the estimate's other fn terms
   of degree <= 3 whose force is plausible, started from the estimate folded into the
   admissible region and from a generic start (half the stiffness hysteretic, the loop's knee
   at the nonlinear stage's amplitude);
2. ``bouc_wen``: the Bouc-Wen law without fn terms, from the same starts;
3. ``elastic``: no hysteresis; the TMP law's stiffness terms alone (c y' + k y + a2 y^2 +
   a3 y^3, from the estimate's y^2, y^3 when plausible, and from zero; the better fit is kept):
   a system without hysteresis whose estimate was inadmissible (an estimate can answer a y^2 with
   a Bouc-Wen law so narrow that its z only adds stiffness);
4. ``equivalent_linear``: no hysteresis; stiffness and damping that change with amplitude
   (c y' + k y + k3 y^3 + c3 y^2 y');
5. ``linear``: c y' + k y.

Each is fitted by output error on the linear and nonlinear stages (simulated from their
recorded start states; a Bouc-Wen law that leaves its admissible region is fitted again held
inside it, alpha >= 0 and gamma + delta >= 0: the estimate it replaces has often left it), and
scored on the held-out stages. A hysteretic kind whose fitted Bouc-Wen
force has vanished (rms z below ``tuning.negligible`` of the elastic force) is the elastic kind
with three idle parameters and does not compete. Held-out: the validation stages; the
nonlinear stage when there is none, which the result says. The inadmissible estimate
stays in the result for inspection (``adequacy.inadmissible_estimate``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.library import monomials
from recon.model import HystereticModel
from recon.output_error.polish import decimate, output_noise
from recon.output_error.problem import FD_STEP, OutputError, motion_scales, term_scale
from recon.steps.bouc_wen import hysteretic_share
from recon.threads import fd_map
from recon.validation import nrmse
from shakerlab.run_data import BASE, Run

# what a failing estimator path raises: numerical breakdowns, not programming errors of
# the caller (those raise TypeError/AttributeError/KeyError and are not caught)
NUMERICAL_ERRORS = (np.linalg.LinAlgError, FloatingPointError, OverflowError, ZeroDivisionError, ValueError)

KINDS = ("bouc_wen_fewer_terms", "bouc_wen", "elastic", "equivalent_linear", "linear")
# the kinds that have the law's own form (Bouc-Wen hysteresis): fitted by output error from a
# generic start, they are a full reconstruction, not a simplification of it
HYSTERETIC_KINDS = ("bouc_wen_fewer_terms", "bouc_wen")


def admissible(model: HystereticModel, tuning: EstimatorTuning = DEFAULT_TUNING) -> bool:
    """Physically admissible: finite, positive stiffness, a post-yield stiffness |k| within
    ``tuning.split_limit`` times the initial stiffness K = k + alpha, and either a saturating Bouc-Wen
    law (alpha > 0, gamma + delta > 0) or no hysteresis at all (alpha = gamma = delta = 0) with
    non-negative damping.

    |k| above 10 K (the default): k and alpha nearly cancel (a force that falls after yield ten
    times faster than it rose). Such a split is a numerical artefact, not a law: its model, with K
    far from the truth's, does not predict the validation stage at all."""
    vals = [model.c_m, model.k_m, model.alpha_m, model.gamma, model.delta, *model.fn_m.values()]
    if not np.all(np.isfinite(vals)) or not model.K_m > 0:
        return False
    if abs(model.k_m) > tuning.split_limit * model.K_m:
        return False        # k and alpha cancel: a split the data did not determine
    if model.alpha_m == 0.0 and model.gamma == 0.0 and model.delta == 0.0:
        return bool(model.c_m >= 0.0)
    return bool(model.lam > 0 and model.alpha_m > 0)


@dataclass
class SimplerFit:
    kind: str
    model: HystereticModel | None
    held_out_nrmse: float
    fitted_nrmse: float
    failed: str | None = None
    # the simulation's NRMSE on the nonlinear stage alone (None when it was not fitted)
    nonlinear_stage_nrmse: float | None = None
    # which of its starts the fit came from, where a kind had several named starts (the elastic
    # kind: "estimate", y^2 and y^3 from the inadmissible estimate, or "zero"); None: one start
    start: str | None = None
    # a Bouc-Wen kind made into the answer it would be (terms revised, two stages fitted together:
    # recon.estimator.pipeline._finish_law) before the kinds were compared; its figures are then of that
    finished: bool = False

    def to_dict(self, tuning: EstimatorTuning = DEFAULT_TUNING) -> dict:
        d = {"kind": self.kind, "held_out_nrmse": self.held_out_nrmse, "fitted_nrmse": self.fitted_nrmse,
             "admissible": bool(self.model is not None and admissible(self.model, tuning))}
        if self.nonlinear_stage_nrmse is not None:
            d["nonlinear_stage_nrmse"] = self.nonlinear_stage_nrmse
        if self.model is not None:
            d["equation"] = self.model.equation()
        if self.failed:
            d["failed"] = self.failed
        if self.start is not None:
            d["start"] = self.start
        if self.finished:
            d["finished"] = True
        return d


def fitted_stages(run: Run, settings) -> tuple[str, ...]:
    """The stages a simpler model is fitted on: the linear and nonlinear stages the run has."""
    return tuple(n for n in (settings.linear_stage, settings.nonlinear_stage) if n in run.stages)


def held_out_stages(run: Run, fitted: tuple) -> tuple[list[str], bool]:
    """The stages a model is scored on: the validation stages, else the fitted nonlinear one."""
    names = [n for n in run.stages if n.startswith("validation")]
    if names:
        return names, True
    return [n for n in fitted if n in run.stages][-1:], False


def score(model: HystereticModel, run: Run, names: list[str], tuning: EstimatorTuning = DEFAULT_TUNING) -> float:
    """Mean NRMSE of the model's simulation over ``names`` (inf if it diverges)."""
    out = []
    for n in names:
        try:     # in the recorded quantity, as validation (HystereticModel.simulate_measured)
            ys, measured = model.simulate_measured(run.stage(n), tuning)
        except NUMERICAL_ERRORS:
            return float("inf")
        if not np.all(np.isfinite(ys)):
            return float("inf")
        out.append(nrmse(ys, measured))
    return float(np.mean(out)) if out else float("inf")


def _linear_start(run: Run, linear_stage: str, excitation: str, lin=None) -> tuple[float, float, float | None]:
    """(c_m, k_m, inv_m) to start from: the linear step's values when they are usable, else the
    resonance of the linear stage's response spectrum with 2 % damping."""
    if lin is not None and lin.K_m > 0 and math.isfinite(lin.c_m) and math.isfinite(lin.K_m):
        inv_m = lin.inv_m if excitation != BASE else None
        if excitation == BASE or (inv_m is not None and inv_m > 0):
            return max(lin.c_m, 1e-3 * math.sqrt(lin.K_m)), lin.K_m, inv_m
    st = run.stage(linear_stage)
    y = st.y - np.mean(st.y)
    f = np.fft.rfftfreq(y.size, st.dt)
    spec = np.abs(np.fft.rfft(y * np.hanning(y.size)))
    spec[f < 0.5] = 0.0
    fp = float(f[int(np.argmax(spec))]) or 1.0
    k = (2 * math.pi * fp) ** 2
    inv_m = None
    if excitation != BASE:   # static gain: y ~ inv_m u / k at low frequency; order of magnitude only
        u = st.channels["force"]
        inv_m = k * float(np.std(y)) / max(float(np.std(u)), 1e-300)
    return 0.04 * math.sqrt(k), k, inv_m


def admissible_coordinates(prob: OutputError) -> tuple[np.ndarray, np.ndarray]:
    """(T, lower): the fit's scaled parameters p = T q, with q's lower bounds, such that a Bouc-Wen
    law started admissible (alpha > 0, gamma + delta > 0) stays in the closure of the admissible
    region (alpha >= 0, gamma + delta >= 0): the gamma coordinate of q moves gamma + delta (in
    gamma's scale) with delta held, a change of variables that is linear, so the residual's Jacobian
    is J T. Without a Bouc-Wen law, or from a start outside the region: T = I and no bounds."""
    n = len(prob.keys)
    T, lower = np.eye(n), np.full(n, -np.inf)
    if not all(k in prob.keys for k in ("alpha_m", "gamma", "delta")):
        return T, lower
    ia, ig, idl = (prob.keys.index(k) for k in ("alpha_m", "gamma", "delta"))
    lam0, s = prob.x0[ig] + prob.x0[idl], prob.scale
    if not (lam0 > 0 and prob.x0[ia] > 0):
        return T, lower
    T[ig, idl] = -s[idl] / s[ig]            # p_gamma = q_gamma - p_delta s_delta / s_gamma
    lower[ig] = -lam0 / s[ig]                # gamma + delta = lam0 + q_gamma s_gamma >= 0
    lower[ia] = -prob.x0[ia] / s[ia]         # alpha = alpha0 + q_alpha s_alpha >= 0
    return T, lower


def _fit(model: HystereticModel, data: list, free: list, max_nfev: int, tuning: EstimatorTuning) -> HystereticModel:
    """An output-error fit of ``free`` from ``model``. A Bouc-Wen law that the free fit takes out of its
    admissible region is fitted again from the same start held inside it (:func:`admissible_coordinates`),
    so that a simpler model of the law's form is a law wherever the data allow one, rather than a fit
    that left the region and is set aside. A free fit that stays admissible is the answer as it is."""
    prob = OutputError(model, data, free=free)
    m = _solve(prob, data, max_nfev, tuning)
    if admissible(m, tuning):
        return m
    T, lower = admissible_coordinates(prob)
    if not np.any(np.isfinite(lower)):
        return m
    return _solve(prob, data, max_nfev, tuning, T, lower)


def _solve(prob: OutputError, data: list, max_nfev: int, tuning: EstimatorTuning, T=None, lower=None):
    """``prob`` solved by trust-region least squares from its start; in the coordinates q (p = T q)
    with q >= ``lower`` when they are given."""
    n = len(prob.keys)
    T = np.eye(n) if T is None else T
    jac = prob.jac_option()
    bounded = {} if lower is None else {"bounds": (lower, np.full(n, np.inf))}
    with np.errstate(all="ignore"):
        sol = least_squares(lambda q: prob.residual(T @ q), np.zeros(n),
                            jac=(lambda q: jac(T @ q) @ T) if callable(jac) else jac, method="trf",
                            x_scale=1.0, diff_step=FD_STEP, max_nfev=max_nfev, xtol=1e-10, ftol=1e-12,
                            workers=None if callable(jac) else fd_map(),
                            callback=prob.stop([output_noise(d) for d in data], tuning.stop_chi2), **bounded)
    return prob.build(T @ sol.x)


def figures(model: HystereticModel, run: Run, names: list, fitted, nonlinear_stage: str,
            tuning: EstimatorTuning = DEFAULT_TUNING) -> tuple[float, float, float | None]:
    """A simpler fit's figures: (held-out NRMSE over ``names``, mean NRMSE over the ``fitted`` stages,
    the nonlinear stage's own or None). Each fitted stage is simulated once: their mean is the fit's
    figure, the nonlinear stage's own is what an inadequate full model is compared on
    (pipeline._prefer_simpler)."""
    per_stage = {n: score(model, run, [n], tuning) for n in fitted}
    fit_err = float(np.mean(list(per_stage.values()))) if per_stage else float("inf")
    return score(model, run, names, tuning), fit_err, per_stage.get(nonlinear_stage)


def simpler_models(run: Run, settings, estimate: HystereticModel | None, linear_fit=None,
                   max_nfev: int = 60) -> list[SimplerFit]:
    """Fit every simpler kind (module doc) and score it on the held-out stages (``settings``: the
    ReconSettings, whose tuning the fits and the admissibility read)."""
    t = settings.tuning
    excitation = next(iter(run.stages.values())).excitation
    fitted = fitted_stages(run, settings)
    names, _ = held_out_stages(run, fitted)
    c0, k0, inv0 = _linear_start(run, settings.linear_stage, excitation, linear_fit)
    extra = ["inv_m"] if excitation != BASE else []
    offset = None
    if getattr(settings, "input_offset", False) is True:     # fitted by every kind, as by the estimate
        offset = estimate.input_offset if estimate is not None and estimate.input_offset is not None else 0.0
        offset = offset if math.isfinite(offset) else 0.0
        extra.append("input_offset")
    base = dict(excitation=excitation, c_m=c0, k_m=k0, alpha_m=0.0, gamma=0.0, delta=0.0,
                inv_m=inv0, input_offset=offset, provenance={"simpler_model": True})
    starts = {"linear": (HystereticModel(**base), ["c_m", "k_m"] + extra),
              "equivalent_linear": (HystereticModel(**dict(base, fn_m={"y^3": 0.0, "y^2*dy": 0.0})),
                                    ["c_m", "k_m", "fn:y^3", "fn:y^2*dy"] + extra)}
    keys_h = ["c_m", "k_m", "alpha_m", "gamma", "delta"] + extra
    # a generic Bouc-Wen start: half the stiffness hysteretic, the loop's knee at the nonlinear
    # stage's amplitude (lambda Y = 1)
    y_nl = run.stage(settings.nonlinear_stage).y if settings.nonlinear_stage in run.stages else None
    amp = float(np.sqrt(2.0) * np.std(y_nl)) if y_nl is not None and np.std(y_nl) > 0 else 1.0
    generic = dict(base, alpha_m=0.5 * k0, k_m=0.5 * k0, gamma=0.5 / amp, delta=0.5 / amp)
    bw_starts = [HystereticModel(**generic)]
    plausible = (estimate is not None and estimate.alpha_m != 0.0
                 and np.all(np.isfinite([estimate.alpha_m, estimate.gamma, estimate.delta]))
                 and abs(estimate.alpha_m) < 10 * k0)   # a split of k and alpha that cancels is no start
    if plausible:
        g, d = estimate.gamma, estimate.delta
        if not g + d > 0:
            g, d = abs(g), abs(d)
        if not g + d > 0:
            g = d = 0.5 / amp
        alpha = abs(estimate.alpha_m)
        bw_starts.insert(0, HystereticModel(**dict(base, alpha_m=alpha, gamma=g, delta=d,
                                                   k_m=max(k0 - alpha, 0.05 * k0))))
    # the TMP law's stiffness terms y^2 and y^3 (started at 0, or at the estimate's value when its
    # force at the stage's amplitude is plausible: below 10 times the elastic force). Terms in y'
    # are left out: from an inadmissible estimate they are the least determined (on an independent
    # recording at 50 dB a y'^3 of the wrong sign made this start diverge)
    few = {"y^2": 0.0, "y^3": 0.0}
    if estimate is not None:
        few.update({k: v for k, v in estimate.fn_m.items() if k in few and np.isfinite(v)
                    and abs(v) * amp ** sum(monomials.parse(k)) < 10 * k0 * amp})
    starts["bouc_wen"] = (bw_starts, keys_h)
    fn_keys = [f"fn:{k}" for k in few]
    # the elastic kind also starts from y^2 = y^3 = 0 when the estimate gave them a value: an
    # estimate that is inadmissible has its terms biased by what it failed on, and from there the
    # fit can stop in a local minimum (an effect the model lacks, a second mode for example,
    # biases them; from zero the fit can reach the true values where from the estimate it does not)
    elastic, elastic_starts = [HystereticModel(**dict(base, fn_m=dict(few)))], None
    if any(v != 0.0 for v in few.values()):
        elastic.append(HystereticModel(**dict(base, fn_m={k: 0.0 for k in few})))
        elastic_starts = ["estimate", "zero"]
    starts["elastic"] = (elastic, ["c_m", "k_m"] + extra + fn_keys)
    with_terms = []
    for m in bw_starts:
        mt = HystereticModel.from_dict(m.to_dict())
        mt.fn_m, mt.provenance = dict(few), m.provenance
        with_terms.append(mt)
    starts["bouc_wen_fewer_terms"] = (with_terms, keys_h + fn_keys)
    out = []
    for kind in KINDS:
        if kind not in starts:
            continue
        first, free = starts[kind]
        tried = []
        start_names = elastic_starts if kind == "elastic" else None
        for j, start in enumerate(first if isinstance(first, list) else [first]):
            try:
                data = [decimate(start.fit_item(run.stage(n), tuning=t), t.polish_fs)[0] for n in fitted]
                # fn terms that start at 0 take the scale of 1 % of the elastic force
                m = _fit(with_term_scales(start, data), data, free, max_nfev, t)
            except NUMERICAL_ERRORS as e:
                tried.append(SimplerFit(kind, None, float("inf"), float("inf"), f"{type(e).__name__}: {e}",
                                        start=start_names[j] if start_names else None))
                continue
            if not admissible(m, t):
                tried.append(SimplerFit(kind, m, float("inf"), float("inf"), "the fitted model is not admissible",
                                        start=start_names[j] if start_names else None))
                continue
            if kind in HYSTERETIC_KINDS:
                # a Bouc-Wen law whose force has vanished (rms z below tuning.negligible of the elastic
                # force on the nonlinear stage, as pipeline._without_vanished_hysteresis judges it) is
                # the elastic kind with three idle parameters: it does not compete as a hysteretic one
                share = hysteretic_share(m, data[-1][0], data[-1][1])
                if share < t.negligible:
                    tried.append(SimplerFit(kind, m, float("inf"), float("inf"),
                                            f"its Bouc-Wen force vanished ({share:.2g} of the elastic force): "
                                            "the elastic kind is this model without it",
                                            start=start_names[j] if start_names else None))
                    continue
            held_err, fit_err, nl_err = figures(m, run, names, fitted, settings.nonlinear_stage, t)
            tried.append(SimplerFit(kind, m, held_err, fit_err,
                                    None if math.isfinite(fit_err) else "its simulation diverges",
                                    nl_err, start_names[j] if start_names else None))
        # of several starts, the one that fits the fitted stages best (the held-out stages choose the kind)
        out.append(min(tried, key=lambda f: (f.failed is not None, f.fitted_nrmse)))
    return out


def with_term_scales(model: HystereticModel, data: list) -> HystereticModel:
    """fn terms that start at 0 start at 1 % of the elastic force at the stage's rms motion, so
    the output-error scaling (the start value's size) is meaningful."""
    zero = [k for k, v in model.fn_m.items() if v == 0.0]
    if not zero:
        return model
    y_rms, v_rms = motion_scales(data)
    fn = dict(model.fn_m)
    for k in zero:
        fn[k] = term_scale(k, model.K_m, y_rms, v_rms)
    m = HystereticModel.from_dict(model.to_dict())
    m.fn_m = fn
    m.provenance = model.provenance
    return m

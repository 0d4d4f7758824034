"""Mismatch diagnosis: locate, name the missing physics, model it, show the fit improve.

    from recon.diagnosis.diagnose import diagnose
    d = diagnose(run, baseline="paper")       # or "linear", a model JSON path, a HystereticModel
    d.to_dict()                               # the JSON contract of ``shakerlab diagnose --json``

Steps: the baseline is refitted by output error (the *null* model, so that every
candidate is compared with the best the baseline can do on the same data); the
residuals of the null model are located (:mod:`.locate`); every applicable
catalog candidate (:mod:`.catalog`) is fitted as an augmented model and scored on
held-out data (:mod:`.rank`); the significant ones are ranked by the share of the
held-out mismatch they remove.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.determinism import single_thread_blas
from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.catalog import CATALOG
from recon.diagnosis.locate import locate, stage_derivatives
from recon.differentiation import estimate_spectrum
from recon.estimator.pipeline import reconstruct
from recon.model import HystereticModel
from recon.output_error.problem import get_parameter, set_parameter
from recon.signals import stage_signals
from recon.steps.linear import count_lines, fit_linear
from shakerlab.errors import UserFacingError
from shakerlab.run_data import BASE, Run

# which located findings support which candidate (evidence, not the decision)
SIGNATURES = {
    "coulomb_friction": ("state_near_zero_velocity", "state_cluster"),
    "quadratic_damping": ("state_cluster", "frequency_harmonic", "correlation_tests"),
    "contact_stiffness": ("state_beyond_displacement", "frequency_harmonic"),
    "channel_delay": ("channel",),
    "sensor_scale": ("channel",),
    "parameter_drift": ("time_trend", "time_segment"),
    "higher_mode": ("frequency_resonance", "frequency_band_at_input"),
    "cubic_stiffness": ("state_beyond_displacement", "frequency_harmonic"),
    "quadratic_stiffness": ("state_beyond_displacement", "frequency_harmonic"),
    "hysteresis": ("state_cluster", "correlation_tests"),
}


def linear_baseline(run: Run) -> HystereticModel:
    """y'' + c y' + k y = g u from the linear step of recon (first stage named 'linear', else the first)."""

    name = "linear" if "linear" in run.stages else next(iter(run.stages))
    st = run.stage(name)
    s = stage_signals(st, deriv=2, for_regression=False)
    lines = None
    if st.excitation != BASE:

        lines = count_lines(estimate_spectrum(st.channels["force"], st.dt).freqs, 1.0 / (st.t[-1] - st.t[0]))
    lf = fit_linear(s.y[0], s.y[1], s.y[2], s.u[0], st.excitation, s.column_noise, name, lines)
    return HystereticModel(excitation=st.excitation, c_m=lf.c_m, k_m=lf.K_m, alpha_m=0.0, gamma=0.0, delta=0.0,
                           inv_m=None if st.excitation == BASE else lf.inv_m,
                           provenance={"method": "linear step of recon (diagnosis baseline 'linear')"})


def resolve_baseline(run: Run, baseline) -> tuple[AugmentedModel, str]:
    if isinstance(baseline, AugmentedModel):
        return baseline.copy(), "model"
    if isinstance(baseline, HystereticModel):
        return AugmentedModel(HystereticModel.from_dict(baseline.to_dict())), "model"
    if baseline in (None, "paper"):

        return AugmentedModel(reconstruct(run).model), "paper"
    if baseline == "linear":
        return AugmentedModel(linear_baseline(run)), "linear"
    path = Path(str(baseline))
    if path.suffix != ".json" and not path.exists():
        raise UserFacingError(f"--baseline must be 'paper', 'linear' or a model JSON file, got {baseline!r}")
    return AugmentedModel.load(path), str(path)


@dataclass
class Diagnosis:
    baseline: AugmentedModel
    baseline_kind: str
    fit_before: dict
    null: rank.FitResult
    mismatch: list
    candidates: list                 # every tested candidate with its score
    missing: list                    # significant ones, ranked
    best: AugmentedModel
    best_fit: rank.FitResult
    context: dict = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        def clean_ctx(c):
            return {k: v for k, v in c.items() if k != "billings_voon"}

        return {
            "baseline": self.baseline.equation(),
            "baseline_kind": self.baseline_kind,
            "fit_before": self.fit_before,
            "fit_after": {"nrmse": self.best_fit.nrmse, "held_out_nrmse": self.best_fit.nrmse_held,
                          "model": self.best.equation()},
            "mismatch": self.mismatch,
            "missing_physics": self.missing,
            "result": (f"missing physics: {', '.join(m['id'] for m in self.missing)}" if self.missing
                       else "nothing found: no candidate explains the held-out mismatch beyond noise"),
            "candidates_tested": self.candidates,
            "correlation_tests": self.context.get("billings_voon", {}),
            "context": clean_ctx(self.context),
            "augmented_model": self.best.to_dict(),
            "seconds": self.seconds,
        }


def _params_of(fr: rank.FitResult, keys) -> dict:
    out = {}
    for k in keys:
        v = get_parameter(fr.model, k)
        name = k.split(":", 1)[-1]
        out[name] = {"value": v, "stderr": fr.stderr.get(k)}
    return out


# numerical failures of one candidate's fit or simulation: recorded, never raised
CANDIDATE_FAILURES = (ArithmeticError, ValueError, np.linalg.LinAlgError)


def _check_null(null, data, run) -> None:
    """The null model (the baseline refitted) must simulate every stage and leave held-out samples."""
    if null.n_held == 0:
        raise UserFacingError(f"{run.source or 'run'}: no held-out samples to compare models on (stages "
                              f"{', '.join(d.name for d in data)}); record a validation stage or longer stages")
    if not math.isfinite(null.mse_held):
        bad = [d for d in data if not np.isfinite(null.nrmse.get(d.name, np.nan))]
        where = ", ".join(d.name for d in bad) or ", ".join(d.name for d in data)
        raise UserFacingError(f"{run.source or 'run'}: the baseline refitted by output error does not simulate "
                              f"stage(s) {where} (the simulation diverged); try --baseline linear or a saved model")


@single_thread_blas
def diagnose(run: Run, baseline="paper", candidates=None, max_nfev: int = 30) -> Diagnosis:
    """Diagnose ``run`` against ``baseline`` ("paper", "linear", a model JSON path or a model)."""
    return _diagnose(run, baseline, candidates, max_nfev)


def _diagnose(run: Run, baseline, candidates, max_nfev: int) -> Diagnosis:
    t0 = time.perf_counter()
    base, kind = resolve_baseline(run, baseline)
    if base.excitation != run.excitation:
        raise UserFacingError(f"baseline model is {base.excitation} excitation, {run.source or 'run'} is {run.excitation}")
    data = rank.prepare(run, base.baseline)
    before = rank.nrmse_per_stage(base, data)
    bkeys = rank.baseline_keys(base.baseline)
    extra_keys = [f"x:{k}" for k in base.extras if k not in ("v0", "side")]
    null = rank.fit(base, bkeys + extra_keys, data, max_nfev=max_nfev)
    _check_null(null, data, run)
    sims = rank.simulate_all(null.model, data)

    derivs = stage_derivatives(run, data)
    findings, ctx = locate(null.model, run, data, sims, derivs)
    noise_mse = float(np.sum([np.sum(d.held) * d.noise ** 2 for d in data]) / max(sum(int(d.held.sum()) for d in data), 1))
    tested = []
    fits = {}
    ids = candidates or list(CATALOG)
    for cid in ids:
        if cid not in CATALOG:
            raise UserFacingError(f"unknown candidate {cid!r} (catalog: {', '.join(CATALOG)})")
        cand = CATALOG[cid]
        if cid in null.model.added or not cand.applies(null.model.baseline, ctx):
            continue
        tc = time.perf_counter()
        try:
            starts = cand.starts(null.model.baseline, ctx)
            for m, _, _, _ in starts:       # keep extras already in the baseline
                for k, v in null.model.extras.items():
                    m.extras.setdefault(k, v)
                m.added = list(null.model.added) + [cid]
            if cand.column is not None:     # linear in its first parameter: equation-error step per start
                stepped = [rank.equation_step(m, bkeys, keys[0], cand.column, derivs, data) for m, keys, _, _ in starts]
                i = int(np.argmin([r for _, r in stepped]))
                _, keys, sc, b = starts[i]
                m = stepped[i][0]
                lo = b.get(keys[0], (-np.inf, np.inf))[0]
                if keys[0].startswith("x:") and np.isfinite(lo) and m.extras[keys[0][2:]] < lo:
                    # the equation-error step points across the term's physical bound (input-estimation
                    # errors bias it): also start from two values inside the bound, refit with c and k,
                    # and keep the start that fits best
                    m.extras[keys[0][2:]] = lo
                    tries = [m]
                    for mult in (1.0, 5.0):
                        mm = m.copy()
                        mm.extras[keys[0][2:]] = lo + mult * sc[keys[0]]
                        tries.append(mm)
                    screened = [rank.fit(mm, [keys[0], "c_m", "k_m"], data, sc, max_nfev=8, bounds=b) for mm in tries]
                    m = screened[int(np.argmin([f.cost_fit for f in screened]))].model
            elif len(starts) > 1:           # screen the starts with only the new terms free
                screened = [rank.fit(m, keys[:cand.screen_keys], data, sc, max_nfev=5, bounds=b)
                            for m, keys, sc, b in starts]
                i = int(np.argmin([s.cost_fit for s in screened]))
                m, keys, sc, b = starts[i]
                m = screened[i].model
            else:
                m, keys, sc, b = starts[0]
            fr = rank.fit(m, bkeys + extra_keys + keys, data, sc, max_nfev=max_nfev, bounds=b)
            if not (math.isfinite(fr.mse_held) and fr.n_held > 0):
                raise FloatingPointError(f"held-out mean-square error is {fr.mse_held} on {fr.n_held} samples")
            sc_ = rank.score(null, fr, len(keys), noise_mse)
        except CANDIDATE_FAILURES as exc:
            # a candidate whose fit or simulation fails is recorded with its reason and not ranked
            tested.append({"id": cid, "failed": f"{type(exc).__name__}: {exc}", "significant": False,
                           "seconds": time.perf_counter() - tc})
            continue
        fits[cid] = (fr, keys, sc, b)
        tested.append({"id": cid, **sc_, "held_out_nrmse": fr.nrmse_held, "seconds": time.perf_counter() - tc})
    sig = [t for t in tested if t["significant"]]
    sig.sort(key=lambda t: -t["explained"])
    combined = None
    if len(sig) > 1:
        # forward step: a runner-up is reported only if it still adds on top of the best one
        best_fr, best_keys, best_sc, best_b = fits[sig[0]["id"]]
        kept = [sig[0]]
        for t in sig[1:]:
            cand = CATALOG[t["id"]]
            fr1, keys1, sc1, b1 = fits[t["id"]]
            m = best_fr.model.copy()
            for k in keys1:
                set_parameter(m, k, get_parameter(fr1.model, k))
            if cand.id == "contact_stiffness":
                m.extras["side"] = fr1.model.get("side")
            m.added = list(best_fr.model.added) + [t["id"]]
            try:
                frc = rank.fit(m, bkeys + extra_keys + best_keys + keys1, data, {**best_sc, **sc1},
                               max_nfev=max_nfev, bounds={**best_b, **b1})
                s2 = rank.score(best_fr, frc, len(keys1), noise_mse)
            except CANDIDATE_FAILURES as exc:
                t["on_top_of_best"] = {"failed": f"{type(exc).__name__}: {exc}", "significant": False}
                continue
            t["on_top_of_best"] = s2
            if s2["significant"]:
                kept.append(t)
                fits[t["id"]] = (frc, keys1, sc1, b1)
                combined = frc
                break
        sig = kept
    missing = []
    for t in sig:
        fr, keys = fits[t["id"]][:2]
        cand = CATALOG[t["id"]]
        ev_kinds = SIGNATURES.get(t["id"], ())
        missing.append({
            "id": t["id"], "explanation": cand.explanation, "adds": cand.adds, "simulated": cand.simulated,
            "parameters": _params_of(fr, [k for k in cand.parameters if k in keys or k == "x:side"]),
            "evidence": {"held_out_nrmse_before": null.nrmse_held, "held_out_nrmse_after": fr.nrmse_held,
                         "explained_fraction_of_excess": t["explained"], "delta_bic_held_out": t["dbic"],
                         "effective_samples": t["n_eff"],
                         "located": [f for f in findings if f["kind"] in ev_kinds][:4]},
            "fit_after": {"nrmse": fr.nrmse},
        })
    if combined is not None:
        best_fr = combined
    elif missing:
        best_fr = fits[missing[0]["id"]][0]
    else:
        best_fr = null
    fit_before = {"nrmse": before, "refit_nrmse": null.nrmse, "held_out_nrmse": null.nrmse_held,
                  "noise_nrmse": {d.name: d.noise / d.rms for d in data}}
    return Diagnosis(baseline=base, baseline_kind=kind, fit_before=fit_before, null=null, mismatch=findings,
                     candidates=tested, missing=missing, best=best_fr.model, best_fit=best_fr, context=ctx,
                     seconds=time.perf_counter() - t0)

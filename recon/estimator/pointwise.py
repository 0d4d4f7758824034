"""The pointwise estimator: linear step, agent-model sparse regression, Bouc-Wen parameters."""
from __future__ import annotations

import time

import numpy as np

from recon.estimator.finish import polish_and_validate
from recon.estimator.linear_start import linear_step
from recon.estimator.result import ReconResult, ReconSettings
from recon.library.agent import AgentLibrary
from recon.library.clustering import cluster
from recon.model import HystereticModel
from recon.regression.criteria import filter_correlation_length
from recon.regression.sparse import GroupedSparseSelector
from recon.signals import stage_signals
from recon.steps.bouc_wen import estimate_delta, extract, refit
from shakerlab import __version__
from shakerlab.errors import UserFacingError
from shakerlab.run_data import BASE, Run


def reconstruct_pointwise(run: Run, s: ReconSettings, validate_model: bool = True) -> ReconResult:
    """The pointwise forms (``joint``, ``ab``): the agent model regressed sample by sample."""
    exc = run.excitation
    timings = {}
    t0 = time.perf_counter()
    # the linear step regresses on noisy columns (y', y): errors-in-variables, so the
    # pointwise-optimal filter is used there; the nonlinear step uses the regression criterion.
    # A linear stage too noisy for c and K hands the step to the least noisy fitted stage
    # (recon.estimator.linear_start)
    lf, lin, _ = linear_step(run, s.linear_stage, s.nonlinear_stage, offset=s.input_offset is True,
                             tuning=s.tuning)
    timings["linear"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    nl = stage_signals(run.stage(s.nonlinear_stage), deriv=3, window=s.window, order=s.sg_order, tuning=s.tuning)
    y, dy, ddy, dddy = nl.y
    g = 1.0 if exc == BASE else lf.inv_m
    # a fitted input offset b (a constant force) comes off the input before the nonlinear step: the
    # model is driven by g (u - b), and left in, the constant would take up the even terms
    b_in = lf.offset if lf.offset is not None and np.isfinite(lf.offset) else None
    u0 = nl.u[0] - b_in if b_in is not None else nl.u[0]
    Fn = g * u0 - ddy - lf.c_m * dy - lf.K_m * y
    dFn = g * nl.u[1] - dddy - lf.c_m * ddy - lf.K_m * dy
    # the quadrants of the loop are taken about its centre: a constant force moves the motion's
    # centre off zero while z still swings about zero (clusters about y = 0 put an offset of a few
    # per cent of the amplitude into the wrong quadrant, and the regression misses y^2, y^3)
    h = cluster(y - float(np.mean(y)) if b_in is not None else y, dy)
    lib = AgentLibrary(s.library_order, s.form, linear_correction=bool(s.linear_correction) and s.form == "joint",
                       offset=b_in is not None)
    theta, target = lib.matrix(y, dy, ddy, Fn, dFn, h)     # built a fold of rows at a time by the selector
    if theta.shape[0] < 4 * theta.shape[1]:
        raise UserFacingError(f"stage {s.nonlinear_stage!r}: only {theta.shape[0]} samples in the AB/CD clusters for "
                              f"{theta.shape[1]} library columns; record longer or lower --library-order")
    groups, core = lib.groups()
    selector = GroupedSparseSelector(groups, core, n_folds=s.n_folds, corr_len=filter_correlation_length(nl.choice))
    sp = selector.fit(theta, target)
    del theta
    hp = extract(lib, sp.coef, sp.stderr, sp.support)
    # the regression's inputs, not its matrix: term_inclusion rebuilds the matrix (lib.build, the same
    # numbers) when asked, and the result does not hold a rows x columns copy for the rest of the run
    problem = {"signals": (y, dy, ddy, Fn, dFn, h), "b": target, "groups": groups, "core": core, "lib": lib,
               "terms": sorted(hp.fn),
               "options": {"n_folds": selector.n_folds, "grid": selector.grid, "max_groups": selector.max_groups,
                           "corr_len": selector.corr_len}}
    c_m, K_m = lf.c_m, lf.K_m
    if s.refit:
        mask = lib.rows(h)
        sig = h[mask].astype(float)
        if lib.form == "ab":
            sig = np.ones_like(sig)
        hp, c_m, K_m, g = refit(hp, y[mask], dy[mask], ddy[mask], dddy[mask], u0[mask], nl.u[1][mask], sig,
                                lf.c_m, lf.K_m, g, fit_g=exc != BASE, fit_linear=s.refit_linear)
        Fn = g * u0 - ddy - c_m * dy - K_m * y
        dFn = g * nl.u[1] - dddy - c_m * ddy - K_m * dy
    hp = estimate_delta(hp, y, dy, ddy, Fn, dFn, h)
    # the polish below runs at the reconstruction's peak memory: the refit's Fn, Fn' and the stage's
    # third derivative and u', which nothing after this reads, are let go before it
    t_nl, u_nl, choice_nl = nl.t, nl.u[0], nl.choice
    del Fn, dFn, dddy, nl
    timings["nonlinear"] = time.perf_counter() - t1

    model = HystereticModel(
        excitation=exc, c_m=c_m, k_m=K_m - hp.alpha, alpha_m=hp.alpha, gamma=hp.gamma, delta=hp.delta,
        fn_m=hp.fn, inv_m=None if exc == BASE else g, input_offset=b_in,
        provenance={"method": "agent-model sparse regression (shakerlab recon)", "software": f"shakerlab {__version__}",
                    "settings": s.to_dict(), "threshold": sp.threshold, "source": run.source,
                    "differentiation": {"linear": lin.choice, "nonlinear": choice_nl}},
    )
    model, val = polish_and_validate(model, run, s, hp.info, timings, validate_model)
    return ReconResult(
        model=model, linear=lf, sparse=sp.summary(), library_names=lib.names,
        library_coef=[float(c) for c in sp.coef], hysteresis_info=hp.info,
        differentiation={"linear": lin.choice, "nonlinear": choice_nl,
                         "window": choice_nl["window"], "order": choice_nl["order"],
                         "noise_level": choice_nl["noise_level"]},
        validation=val, settings=s, timings=timings, selection_problem=problem,
        # the smoothed measured motion of the fitted stage; quantities implied by a model
        # (e.g. the hysteretic force) are derived from the final model, see recon.validation
        signals={"t": t_nl, "y": y, "dy": dy, "ddy": ddy, "u": u_nl},
    )

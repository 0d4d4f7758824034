"""Term selection by output error: which fn monomials the model keeps.

The equation-error regression (recon/optimizers.py) picks the fn terms from
third derivatives of noisy displacements. On the simulated rig it misses a
real but weak term (y^2*dy, ~10 % of z at the largest level) and keeps small
spurious ones; the output-error polish then bends alpha and gamma to make up
for them. This module revisits the structure with the simulated response,
which needs no derivative of the output:

1. The stage is split into interleaved blocks; the "fit" blocks are fitted, the
   "held-out" blocks only scored. The simulation always runs through the whole
   stage (from its estimated start state), so a held-out block is a free-run
   prediction of periods the parameters were not fitted on.
2. Around the current (polished) model, one finite-difference Jacobian of the
   simulated output is taken with respect to every parameter and every
   candidate monomial (coefficient 0). Adding a candidate or dropping a present
   term is scored by the linearised refit on the fit blocks and the predicted
   held-out error, with an information criterion
   ``IC = n_eff ln(RSS_held_out) + k ln(n_eff)``; ``n_eff`` is the number of
   held-out samples divided by the residual's correlation length (sum of the
   squared autocorrelation over one block): the output error is dominated by
   slowly varying model error, not by white noise.
3. The best action is applied only if it lowers the IC; the new structure is
   then polished (fit blocks) and must lower the *actual* held-out IC as
   well, else the search stops. Repeat until nothing helps.
4. The caller polishes the selected structure once more on all samples.

Simulations use the stage decimated to about EstimatorTuning.polish_fs (2 kHz by
default; the input is the Savitzky-Golay-smoothed -x_base'' or the force, so
decimating it does not alias).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.library import monomials
from recon.model import HystereticModel
from recon.output_error.polish import decimate, polish
from recon.output_error.problem import OutputError
from recon.regression.criteria import bartlett_correlation_length, bic

# low-order monomials offered for addition (present terms of any order may be dropped)
CANDIDATES = ("y^2", "y*dy", "dy^2", "y^3", "y^2*dy", "y*dy^2", "dy^3")


@dataclass
class SelectionSettings:
    candidates: tuple = CANDIDATES
    block_s: float = 0.5          # length of the interleaved fit / held-out blocks
    max_steps: int = 8
    polish_nfev: int = 10
    fd_step: float = 1e-4         # finite-difference step of the Jacobian (in units of each scale)


def stage_data(model: HystereticModel, stage, tuning: EstimatorTuning = DEFAULT_TUNING):
    """(t, u, y, start) of ``stage`` decimated to about ``tuning.polish_fs`` and the decimation factor
    (the input and the start as ``tuning`` makes them)."""
    u = model.stage_input(stage, tuning=tuning)
    item, q = decimate(model.fit_item(stage, u, tuning), tuning.polish_fs)
    return item, q, u


def _blocks(n: int, block: int) -> np.ndarray:
    """True on the fit blocks (even), False on the held-out blocks (odd)."""
    return (np.arange(n) // max(1, block)) % 2 == 0


def _term_scale(name: str, y: np.ndarray, dy: np.ndarray, model: HystereticModel) -> float:
    """A coefficient whose term is ~1 % of the elastic force K y (rms)."""
    p, r = monomials.parse(name)
    v = np.sqrt(np.mean((y ** p * dy ** r) ** 2))
    f = abs(model.K_m) * np.sqrt(np.mean(y ** 2))
    return float(0.01 * f / v) if v > 0 else 1.0


def select_terms(model: HystereticModel, stage, settings: SelectionSettings | None = None, data=None,
                 tuning: EstimatorTuning = DEFAULT_TUNING):
    """Revise the fn terms of ``model`` on ``stage`` by output error. Returns (model, info);
    the returned model is polished on the decimated fit blocks only (polish it on the whole
    stage afterwards). ``data``: (item, q) from :func:`stage_data` if already computed;
    ``tuning``: the estimator's (its polishes and their decimation)."""
    s = settings or SelectionSettings()
    t_start = time.perf_counter()
    d, q = data if data is not None else stage_data(model, stage, tuning)[:2]
    n = d[0].size
    dt = float(d[0][1] - d[0][0])
    block = max(2, int(round(s.block_s / dt)))
    fit = _blocks(n, block)
    held = ~fit
    data = [d]
    masks = [fit]
    # signals for the candidate scales (simulated y, y' of the current model)
    ysim, dysim, _ = model.simulate(d[0], d[1], initial=None)
    history = []

    current = model
    prob = OutputError(current, data, masks)
    e_cur = prob.simulate(current)
    if e_cur is None:
        return model, {"applied": False, "reason": "the starting model diverges on the stage"}
    e_cur = e_cur[0]
    corr = bartlett_correlation_length(e_cur, block)
    n_eff = max(2.0, held.sum() / corr)
    rss_cur = float(np.mean(e_cur[held] ** 2))
    ic_cur = bic(rss_cur, len(current.fn_m), n_eff)
    history.append({"terms": sorted(current.fn_m), "held_out_rms": float(np.sqrt(rss_cur)), "ic": float(ic_cur)})
    tried = set()
    stale = True
    for _step in range(s.max_steps):
        if stale:   # Jacobian around the current model (kept while trials are rejected)
            extra = {c: _term_scale(c, ysim, dysim, current) for c in s.candidates if c not in current.fn_m}
            prob = OutputError(current, data, masks, extra_terms=extra)
            e0 = prob.simulate(prob.build(np.zeros(len(prob.keys))))[0]
            J = np.empty((n, len(prob.keys)))
            for i in range(len(prob.keys)):
                p = np.zeros(len(prob.keys))
                p[i] = s.fd_step
                ei = prob.simulate(prob.build(p))
                J[:, i] = np.nan if ei is None else (ei[0] - e0) / s.fd_step
            stale = False
        base = [i for i, k in enumerate(prob.keys) if not k.startswith("fn:") or k[3:] in current.fn_m]
        actions = []
        idx = {k[3:]: i for i, k in enumerate(prob.keys) if k.startswith("fn:")}
        present = [t for t in idx if t in current.fn_m]
        # single additions, single drops, and pairs of drops (two spurious terms often
        # compensate each other, so that dropping either alone looks worse)
        moves = [("add", (t,)) for t in idx if t not in current.fn_m]
        moves += [("drop", (t,)) for t in present]
        moves += [("drop", (a, b)) for i_a, a in enumerate(present) for b in present[i_a + 1:]]
        # swaps: a wrong term standing in for a missing one (50 dB ground truth: y^4*dy for y^2*dy)
        moves += [("swap", (a, b)) for a in present for b in idx if b not in current.fn_m]
        for kind, terms in moves:
            ii = [idx[t] for t in terms]
            if kind == "swap":
                cols = [j for j in base if j != ii[0]] + [ii[1]]
                fixed = {ii[0]: -prob.x0[ii[0]] / prob.scale[ii[0]]}
                kk = len(current.fn_m)
            elif kind == "drop":
                cols = [j for j in base if j not in ii]
                fixed = {i: -prob.x0[i] / prob.scale[i] for i in ii}
                kk = len(current.fn_m) - len(terms)
            else:
                cols = base + ii
                fixed = {}
                kk = len(current.fn_m) + len(terms)
            label = (kind, terms)
            if label in tried or not np.all(np.isfinite(J[:, cols])):
                continue
            rhs = -e0.copy()
            p = np.zeros(len(prob.keys))
            for j, v in fixed.items():
                rhs -= J[:, j] * v
                p[j] = v
            sol, *_ = np.linalg.lstsq(J[fit][:, cols], rhs[fit], rcond=None)
            p[cols] = sol
            e_pred = e0 + J @ p
            rss = float(np.mean(e_pred[held] ** 2))
            actions.append((bic(rss, kk, n_eff), label, p, rss))
        if not actions:
            break
        actions.sort(key=lambda a: a[0])
        best_ic, label, p, rss_pred = actions[0]
        what = f"{label[1][0]} -> {label[1][1]}" if label[0] == "swap" else " + ".join(label[1])
        rec = {"action": f"{label[0]} {what}", "predicted_held_out_rms": float(np.sqrt(rss_pred)),
               "predicted_ic": float(best_ic), "ic_before": float(ic_cur)}
        if not best_ic < ic_cur:
            rec["accepted"] = False
            history.append(rec)
            break
        tried.add(label)
        trial = prob.build(p)
        if label[0] == "add":
            keep = set(current.fn_m) | set(label[1])
        elif label[0] == "drop":
            keep = set(current.fn_m) - set(label[1])
        else:
            keep = (set(current.fn_m) - {label[1][0]}) | {label[1][1]}
        trial.fn_m = {k: v for k, v in trial.fn_m.items() if k in keep}
        trial, _ = polish(trial, data, max_nfev=s.polish_nfev, masks=masks, tuning=tuning)
        e_t = OutputError(trial, data, masks).simulate(trial)
        if e_t is None:
            rec["accepted"] = False
            history.append(rec)
            continue
        rss_t = float(np.mean(e_t[0][held] ** 2))
        ic_t = bic(rss_t, len(trial.fn_m), n_eff)
        rec.update({"held_out_rms": float(np.sqrt(rss_t)), "ic": float(ic_t), "accepted": bool(ic_t < ic_cur)})
        history.append(rec)
        if ic_t < ic_cur:
            current, ic_cur, rss_cur = trial, ic_t, rss_t
            tried = set()
            stale = True
            ysim, dysim, _ = current.simulate(d[0], d[1], initial=None)
    info = {"applied": sorted(current.fn_m) != sorted(model.fn_m), "terms_before": sorted(model.fn_m),
            "terms_after": sorted(current.fn_m), "n_eff": float(n_eff), "correlation_length": float(corr),
            "decimation": q, "fs": 1.0 / dt, "block_s": s.block_s, "steps": history,
            "time_s": time.perf_counter() - t_start}
    return current, info

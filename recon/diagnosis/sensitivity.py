"""What a record can show: the size at which each candidate's effect would be named on it.

A candidate is named when, on the held-out samples, it beats the reference (the better of the
baseline as given and the null model) by the margins of :func:`recon.diagnosis.rank.score`. Were
an effect present whose held-out output signature (the difference it makes to the reference's
prediction) has mean square D, the reference would score mse_ref + D and a candidate that captured
it would score mse_ref. :func:`smallest_detectable_mse` is the smallest D that passes the rule then.

The candidate's signature per unit of its size parameter (its first key: mu, c2, kc, the delay, the
scale error, the drift rate, phi2, a library coefficient, alpha) comes from one simulation of the
reference with that parameter at a nominal value (the candidate fit's own scale: about 1 % of the
record's force level) and its shape parameters (friction's v0, the contact's gap and side, the
higher mode's frequency and damping, the Bouc-Wen exponents) where the candidate's fit left them.
A small effect changes the prediction in proportion to its size, so the limit in the parameter's
own unit is nominal x sqrt(D / D_nominal), for that shape.

When the reference is the refitted baseline (the null model), that refit would take up part of an
effect present in the record (a drift the stiffness follows, a quadratic damping that the
baseline's own y^2 y' term mimics at one amplitude): D is then the part of the signature it cannot
take up, the held-out difference left after the reference, with the null model's free parameters,
is refitted to the record the term makes (``absorbed_share`` reports the rest). On a one-tone rig
record with a noisy laser, quadratic damping's limit was 0.32 for the term alone and 11.7 with the
refit's share taken out; c2 = 6 was there and went unnamed.

An estimate of the scale at which an effect starts to show on this record, not a guarantee either
way. An effect already in the record is already in the reference's residual, where it needs less
than an effect added on top of it, which lowers the threshold; a candidate fit that captures only
part of the signature (its own parameters trading with the baseline's) raises it. Measured on the
independent generator's stress recordings (docs/diagnosis.md), effects below their limit are
mostly not named, and effects above it can still be missed.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from recon.diagnosis import rank
from recon.diagnosis.augmented import AugmentedModel
from recon.diagnosis.settings import DEFAULT_RULE, SignificanceRule
from recon.output_error.problem import get_parameter, set_parameter

# numerical, not a tuned choice: the most steps of smallest_detectable_mse's bracket (x4 each) and
# bisection; the bisection stops at its 1e-6 relative tolerance long before, so it is a cap only
SEARCH_STEPS = 80


def smallest_detectable_mse(ref: rank.FitResult, k_added: int, noise_mse: float,
                            rule: SignificanceRule = DEFAULT_RULE) -> float:
    """The smallest held-out mean square D an effect with ``k_added`` parameters must add to the
    reference ``ref`` for a candidate that removes it exactly to pass :func:`rank.score`; inf when
    none does (a reference without held-out samples). The rule's margins all grow with D (the
    BIC, the explained share, the gain over the noise, the relative gain), so a bracket and a
    bisection find it."""
    m = ref.mse_held
    if not (math.isfinite(m) and m > 0 and ref.resid_held is not None and ref.resid_held.size):
        return math.inf

    # the effect's error spread evenly over the held-out samples (a term that acts throughout the
    # record): the reference's residual scaled, so that the rule's routes through the held-out pieces
    # (rank.blocks_improved) count it as helping on every piece
    def passes(d: float) -> bool:
        null = dataclasses.replace(ref, mse_held=m + d, resid_held=ref.resid_held * math.sqrt((m + d) / m))
        cand = dataclasses.replace(ref, mse_held=m)
        return rank.score(null, cand, k_added, noise_mse, rule)["significant"]

    hi = max(m, noise_mse, 1e-300)
    for _ in range(SEARCH_STEPS):
        if passes(hi):
            break
        hi *= 4.0
    else:
        return math.inf
    lo = 0.0
    for _ in range(SEARCH_STEPS):
        mid = 0.5 * (lo + hi)
        if passes(mid):
            hi = mid
        else:
            lo = mid
        if hi - lo <= 1e-6 * hi:
            break
    return hi


def nominal_model(ref: AugmentedModel, fitted: AugmentedModel, keys: list[str], size: float) -> AugmentedModel:
    """The reference with a candidate's term at ``size`` (its first key) and its other keys, and the
    extras the candidate adds, where its fit ``fitted`` left them."""
    m = ref.copy()
    for k, v in fitted.extras.items():
        m.extras.setdefault(k, v)
    for k in keys[1:]:
        set_parameter(m, k, get_parameter(fitted, k))
    set_parameter(m, keys[0], size)
    m.added = list(fitted.added)
    return m


def detection_limits(ref: rank.FitResult, fits: dict, data: list, noise_mse: float, failures: tuple,
                     rule: SignificanceRule = DEFAULT_RULE, refitted: list | tuple = ()) -> dict:
    """:func:`detection_limit` of every fitted candidate, ``fits`` {id: CandidateFit} (its fit, keys
    and scales are read); the parts every candidate shares (the rule's smallest D per number of added parameters,
    the held-out mean square) computed once. A candidate whose simulation raises one of ``failures``
    gets value None and the failure as its note."""
    held = [d.y[d.held] - d.y[d.held].mean() for d in data if d.held.any()]
    ms_y = float(np.mean(np.concatenate(held) ** 2)) if held else 0.0
    d_min = {}
    out = {}
    for cid, cf in fits.items():
        fr, keys, scales = cf.fit, cf.keys, cf.scales
        if len(keys) not in d_min:
            d_min[len(keys)] = smallest_detectable_mse(ref, len(keys), noise_mse, rule)
        try:
            out[cid] = detection_limit(ref, fr.model, keys, scales, data, d_min[len(keys)], ms_y, refitted)
        except failures as exc:
            out[cid] = {"parameter": keys[0].split(":", 1)[-1], "value": None,
                        "note": f"{type(exc).__name__}: {exc}"}
    return out


def detection_limit(ref: rank.FitResult, fitted: AugmentedModel, keys: list[str], scales: dict,
                    data: list, d_min: float, ms_y: float, refitted: list | tuple = ()) -> dict:
    """The size of a candidate's first parameter at which its effect would be named (module
    docstring), given the rule's smallest held-out mean square ``d_min`` for its number of
    parameters and the held-out samples' mean square ``ms_y``: {parameter, value,
    held_out_signature_nrmse, shape {other keys: values}}, or {parameter, value: None, note} when
    its term does not change the held-out prediction at that shape."""
    key = keys[0]
    shape = {k.split(":", 1)[-1]: float(get_parameter(fitted, k)) for k in keys[1:]}
    if "side" in fitted.extras:
        shape["side"] = float(fitted.extras["side"])
    out = {"parameter": key.split(":", 1)[-1], "shape": shape}
    nominal = abs(float(scales.get(key) or 0.0))
    if not (math.isfinite(d_min) and nominal > 0 and ms_y > 0):
        return {**out, "value": None, "note": "no held-out samples to judge on"}
    fr = rank.fit(nominal_model(ref.model, fitted, keys, nominal), [], data)
    if not (fr.resid_held is not None and fr.resid_held.size == ref.resid_held.size and math.isfinite(fr.mse_held)):
        return {**out, "value": None, "note": "the reference with the term did not simulate"}
    d_alone = float(np.mean((fr.resid_held - ref.resid_held) ** 2))
    d0 = d_alone
    if refitted and d_alone > 0:
        # the reference is the baseline refitted (the null model): were the effect in the record, that
        # refit would take up part of its signature. The part it cannot: the reference refitted, with
        # the keys the null model frees, to the record the term makes (its simulated output), and
        # compared with that record on the held-out samples
        made = [dataclasses.replace(d, y=ys) for d, ys in zip(fr.sim_stages, fr.sims)]
        absorbed = rank.fit(ref.model, refitted, made)
        if not (absorbed.resid_held is not None and absorbed.resid_held.size == ref.resid_held.size
                and math.isfinite(absorbed.mse_held)):
            return {**out, "value": None, "note": "the reference refitted to the term's record did not simulate"}
        d0 = min(float(np.mean(absorbed.resid_held ** 2)), d_alone)
    if not d0 > 0:
        return {**out, "value": None, "note": "the term does not change the held-out prediction at this shape"}
    return {**out, "value": nominal * math.sqrt(d_min / d0),
            "held_out_signature_nrmse": math.sqrt(d_min / ms_y),
            "absorbed_share": 1.0 - d0 / d_alone}

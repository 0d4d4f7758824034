"""hysteresis: a Bouc-Wen loop the baseline without hysteresis cannot produce."""
import math

import numpy as np

from recon.diagnosis.candidates.base import Candidate, start_model

# shares of the baseline's stiffness K that the hysteresis candidate also starts with in its loop,
# k lowered by as much (see starts)
HYSTERESIS_SPLIT_SHARES = (0.1, 0.3)
# A Bouc-Wen law with gamma + delta < 0 does not saturate: loaded one way its tangent stiffness
# grows as alpha exp(|gamma + delta| y). Within a bounded motion that is a hardening loop, and a
# published one: the Bouc-Wen benchmark (Noel & Schoukens 2016; beta gamma = 800, beta delta = -1100
# per m) stiffens 4.4 times across its training record. A law that stiffens more than this many
# times across the recorded displacement range is a stiffening spring in disguise, not a loop
HARDENING_LIMIT = 10.0
# A Bouc-Wen law whose loop does not open over the recorded motion: (|gamma| + |delta|) times half the
# recorded displacement range, the relative change of its tangent stiffness across the range, under
# this. Such a law is a linear spring alpha y whose state's start, fitted per stage, is a constant
# force, and can be named in place of an offset; a real loop opens by orders of magnitude more
LOOP_MIN_OPENING = 0.01


def loop_starts(base, ctx, alpha_share: float, bounds: dict, split_shares: tuple = ()):
    """Starts of the hysteresis candidate: alpha at ``alpha_share`` of K beside the baseline's k, and
    for each of ``split_shares`` alpha at that share of K with k lowered by as much (K = k + alpha
    kept); each at two loop widths (gamma + delta = 1 and 3 over the response's rms)."""
    out = []
    K = abs(base.K_m)
    for share, split in [(alpha_share, False)] + [(s, True) for s in split_shares]:
        for lam_y in (1.0, 3.0):
            m = start_model(base, {}, "hysteresis")
            lam = lam_y / ctx["y_rms"]
            m.baseline.alpha_m = share * K
            if split:
                m.baseline.k_m = base.k_m - share * K
            m.baseline.gamma = 0.6 * lam
            m.baseline.delta = 0.4 * lam
            out.append((m, ["alpha_m", "gamma", "delta"],
                        {"alpha_m": 0.05 * K, "gamma": 0.3 * lam, "delta": 0.3 * lam}, dict(bounds)))
    return out


def starts(base, ctx):
    # a model without the law has taken the loop's small-amplitude stiffness into k (a Bouc-Wen
    # oscillator's tangent stiffness at rest is k + alpha): the starts also give part of k to the
    # loop. From alpha = 0 beside the whole k the fits can end in a narrow loop (a large gamma) far
    # from the truth; from a share of K in alpha they reach it
    return loop_starts(base, ctx, 0.0, {}, HYSTERESIS_SPLIT_SHARES)


def admissible_starts(base, ctx):
    # alpha >= 0 (a loop traversed the other way feeds energy in), started inside the bound at 5 %
    # of K (from alpha = 0 on the bound the fit does not move): tried when the fit from alpha = 0
    # ends inadmissible (a negative alpha beside a stiffer k, which lets another candidate be named)
    return loop_starts(base, ctx, 0.05, {"alpha_m": (0.0, np.inf)})


def check(m, data) -> list[str]:
    """An admissible law (alpha > 0) whose loop opens over the recorded motion and that stiffens at
    most HARDENING_LIMIT times across it."""
    b = m.baseline
    lam = b.gamma + b.delta
    recorded = max((float(np.ptp(d.displacement)) for d in data), default=0.0)     # the recorded displacement range
    span = recorded if lam < 0 else 0.0
    opening = (abs(b.gamma) + abs(b.delta)) * 0.5 * recorded
    if not b.alpha_m > 0:
        return [f"inadmissible Bouc-Wen (alpha_m {b.alpha_m:.4g}, gamma + delta {lam:.4g})"]
    if opening < LOOP_MIN_OPENING:
        return [f"a Bouc-Wen law whose loop does not open: (|gamma| + |delta|) x half the recorded range "
                f"is {opening:.3g} (at least {LOOP_MIN_OPENING:g} asked): a linear spring, whose state's "
                f"start acts as a constant force"]
    if -lam * span > math.log(HARDENING_LIMIT):
        return [f"inadmissible Bouc-Wen (alpha_m {b.alpha_m:.4g}, gamma + delta {lam:.4g}): it stiffens "
                f"{math.exp(min(-lam * span, 700.0)):.3g} times across the recorded range {span:.4g} m "
                f"(at most {HARDENING_LIMIT:g})"]
    return []


def conceal(truth, baseline, strength):
    truth.alpha_m = 600.0 * strength
    truth.k_m = 9000.0 - truth.alpha_m
    for m in (truth, baseline):
        m.fn_m = {}
    baseline.alpha_m = baseline.gamma = baseline.delta = 0.0
    baseline.k_m = 9000.0
    return {}


CANDIDATE = Candidate(
    "hysteresis",
    "the restoring force depends on the history of motion (a Bouc-Wen hysteretic loop) "
    "that the baseline without hysteresis cannot produce",
    "Bouc-Wen state z' = alpha y' - gamma |y'| z - delta y' |z| added to the restoring force",
    "the SDOF with its Bouc-Wen state", ("alpha_m", "gamma", "delta"), starts,
    lambda b, c: b.alpha_m == 0.0, check=check, signature=("state_cluster", "correlation_tests"),
    amplitude_dependent=True, conceal=conceal, admissible_starts=admissible_starts,
    kernel=("alpha", "gamma", "delta"))

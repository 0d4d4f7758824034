"""coulomb_friction: dry friction, a force of constant size opposing the motion (mu tanh(y'/v0))."""
import numpy as np

from recon.diagnosis.candidates.base import Candidate, start_model

V0_FACTORS = (0.01, 0.05, 0.2, 1.0, 3.0)   # friction smoothing velocities tried, x the smallest stage rms velocity
V0_LOWEST = 0.01                 # the fitted v0 stays above this share of the smallest stage rms velocity


def starts(base, ctx):
    # the smoothing velocity v0 is not known: a sharp sign (0.01) fits a rig's friction, a joint's
    # micro-slip is smoother (0.2); each is a start, the best one is kept (see diagnose.py), and v0
    # is then fitted with mu. 1 and 3: a small stage that moves in pre-sliding, below v0, where the
    # friction acts as a viscous damper mu / v0 (a baseline reconstructed there holds it as a c many
    # times the true one). A fixed v0 far below a pre-sliding stage's velocity cannot fit that
    # stage; with v0 free the fit reaches mu and v0
    #
    # Where the reconstructed baseline's Bouc-Wen loop acts as a friction law (it slides within the
    # record's travel: ctx["loop_friction"], recon.diagnosis.wording.friction_reading), the
    # reconstruction has already measured a dry friction's size as the loop's sliding force. From a
    # start without that loop (the references' without-hysteresis core) the friction takes the loop's
    # place at that size; from mu = 0 a local fit does not get there (the sticking it must reproduce
    # is far from a small friction's effect).
    # A loop that reaches its sliding force only late in the travel is a smooth hysteresis (the
    # specimen's own), not a dry friction: the start is made where the record slides over most of
    # its travel (presliding within half of it)
    vmin = ctx["v_rms_min"]
    mus = [0.0]
    loop = ctx.get("loop_friction")
    if loop and base.alpha_m == 0.0 and loop["sliding_after_m"] <= 0.5 * loop["travel_m"]:
        mus.append(float(loop["sliding_force_m"]))
    out = []
    for mu in mus:
        for f in V0_FACTORS:
            m = start_model(base, {"mu": mu, "v0": f * vmin}, "coulomb_friction")
            out.append((m, ["x:mu", "x:v0"], {"x:mu": 0.01 * ctx["acc_rms"]},
                        {"x:mu": (0.0, np.inf), "x:v0": (V0_LOWEST * vmin, np.inf)}))
    return out


def conceal(truth, baseline, strength):
    return {"mu": 0.02 * strength}


CANDIDATE = Candidate(
    "coulomb_friction",
    "dry friction: a force of constant size opposing the motion, independent of amplitude",
    "term mu sign(y') (smoothed: tanh(y'/v0)) in the restoring force",
    "extra force mu tanh(y'/v0); v0 fitted from 1, 5, 20, 100 or 300 % of the smallest stage rms velocity "
    "(the best start)",
    ("x:mu", "x:v0"), starts,
    signature=("state_near_zero_velocity", "state_cluster"), amplitude_dependent=True, conceal=conceal,
    column=lambda am, t, y, dy: np.tanh(dy / am.get("v0")), screen_output=True, hysteresis_absorbs=True,
    kernel=("mu", "v0"))

"""The catalog of candidate missing physics: stable ids, plain explanations, model changes.

Each entry says what it adds to the model (library terms or a model change) and how
the augmented model is simulated (see :mod:`recon.diagnosis.augmented`).
``starts(baseline, ctx)`` gives the starting points of its fit: a list of
(AugmentedModel, new free keys, scales, bounds); several starts when the fit is
multimodal (contact gap and side, higher-mode frequency).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from shakerlab.run_data import BASE
from recon.diagnosis.augmented import AugmentedModel
from recon.model import HystereticModel


@dataclass(frozen=True)
class Candidate:
    id: str
    explanation: str
    adds: str
    simulated: str
    parameters: tuple           # the keys reported for it
    starts: Callable
    applies: Callable = lambda base, ctx: True
    screen_keys: int = 99       # with several starts: how many of the new keys the screening frees
    column: Callable | None = None   # col(am, t, y, dy): the term's regressor when linear in its first key
    screen_output: bool = False      # with a column and several starts: pick the start by a short output-error fit
    admissible_starts: Callable | None = None   # starts inside the physical range, tried when a fit ends implausible
    fit_each: str | None = None      # an extra the fit cannot move (discrete): fitted once per value, the best kept
    # an effect a reconstructed Bouc-Wen law can take up (a dissipation: its |y'| z terms dissipate more
    # at larger amplitude; or a reading error: a law the record does not hold fits part of it): also
    # fitted from the baseline without its hysteresis (diagnose.hysteresis_free_core)
    hysteresis_absorbs: bool = False
    # a one-sided stiffness the reconstruction may have made even-powered stiffness terms of (y^2, y^4:
    # the asymmetric part of the force): also fitted from the baseline without them
    # (diagnose.even_stiffness_free_core)
    even_stiffness_absorbs: bool = False


def _am(base: HystereticModel, extras: dict, cid: str) -> AugmentedModel:
    return AugmentedModel(HystereticModel.from_dict(base.to_dict()), dict(extras), [cid])


def _fn_start(term: str, cid: str, scale_of: Callable):
    def starts(base, ctx):
        m = _am(base, {}, cid)
        m.baseline.fn_m[term] = 0.0
        return [(m, [f"fn:{term}"], {f"fn:{term}": scale_of(ctx)}, {})]
    return starts


V0_FACTORS = (0.01, 0.05, 0.2, 1.0, 3.0)   # friction smoothing velocities tried, x the smallest stage rms velocity
V0_LOWEST = 0.01                 # the fitted v0 stays above this share of the smallest stage rms velocity


def _coulomb(base, ctx):
    # the smoothing velocity v0 is not known: a sharp sign (0.01) fits a rig's friction, a joint's
    # micro-slip is smoother (0.2); each is a start, the best one is kept (see diagnose.py), and v0
    # is then fitted with mu. 1 and 3: a small stage that moves in pre-sliding, below v0, where the
    # friction acts as a viscous damper mu / v0 (a baseline reconstructed there holds it as a c many
    # times the true one). A fixed v0 far below a pre-sliding stage's velocity cannot fit that
    # stage; with v0 free the fit reaches mu and v0
    out = []
    vmin = ctx["v_rms_min"]
    for f in V0_FACTORS:
        m = _am(base, {"mu": 0.0, "v0": f * vmin}, "coulomb_friction")
        out.append((m, ["x:mu", "x:v0"], {"x:mu": 0.01 * ctx["acc_rms"]},
                    {"x:mu": (0.0, np.inf), "x:v0": (V0_LOWEST * vmin, np.inf)}))
    return out


def _quad_damp(base, ctx):
    m = _am(base, {"c2": 0.0}, "quadratic_damping")
    # dissipative by definition: c2 >= 0 (a negative c2 would feed energy in at high speed)
    return [(m, ["x:c2"], {"x:c2": 0.01 * ctx["acc_rms"] / ctx["v_rms"] ** 2}, {"x:c2": (0.0, np.inf)})]


def _contact(base, ctx):
    out = []
    for side, ymax in ((1.0, ctx["y_max_pos"]), (-1.0, ctx["y_max_neg"])):
        for frac in (0.35, 0.55, 0.75):
            m = _am(base, {"kc": 0.0, "gap": frac * ymax, "side": side}, "contact_stiffness")
            out.append((m, ["x:kc", "x:gap"], {"x:kc": 0.1 * abs(base.K_m) + 1.0, "x:gap": 0.1 * ymax},
                        {"x:kc": (0.0, np.inf), "x:gap": (0.0, 0.98 * ymax)}))
    return out


def _delay(base, ctx):
    # the displacement reading lags the input reading (d >= 0; a lead is not a sensor delay); the
    # fit starts inside the bound, a quarter sample, not on it
    m = _am(base, {"delay": 0.25 * ctx["dt"]}, "channel_delay")
    return [(m, ["x:delay"], {"x:delay": ctx["dt"]}, {"x:delay": (0.0, 20 * ctx["dt"])})]


def _scale(base, ctx):
    m = _am(base, {"tip_scale": 0.0}, "sensor_scale")
    return [(m, ["x:tip_scale"], {"x:tip_scale": 0.01}, {"x:tip_scale": (-0.5, 0.5)})]


def _drift(base, ctx):
    m = _am(base, {"drift": 0.0}, "parameter_drift")
    return [(m, ["x:drift"], {"x:drift": 0.01 / max(ctx["t_end"], 1e-9)}, {})]


# the range a second mode's damping ratio is fitted in, and the most a mode may have: beyond
# MODE_ZETA_MAX the fitted 'mode' has no resonance (see diagnose.implausible)
ZETA2_RANGE = (0.001, 0.3)
MODE_ZETA_MAX = 0.2
# a second mode nearer the fundamental than this share of its frequency is refused (diagnose.implausible)
MODE_APART = 0.2


def _higher_mode(base, ctx):
    # input-driven starts (a structural mode), then one riding on the measured point (drive2 = 1,
    # driven by its absolute acceleration); which of the two is kept fixed in the fit: started on
    # its bound, a free drive2 in [0, 1] stops the trust-region fit at its first step
    out = []
    starts = [(f, phi, 0.0) for f, phi in ctx["mode_starts"][:3]]
    above = ctx.get("mode_start_above_band")
    if above is not None and all(abs(above - f) > 0.1 * f for f, _, _ in starts):
        starts.append((above, 0.0, 0.0))
    starts += [(f, phi, 1.0) for f, phi in ctx.get("mode_starts_point", [])[:1]]
    w1 = math.sqrt(max(base.K_m, 0.0))
    for f, phi, drive in starts:
        w = 2 * math.pi * f
        m = _am(base, {"w2": w, "zeta2": 0.02, "phi2": phi, "drive2": drive}, "higher_mode")
        out.append((m, ["x:phi2", "x:w2", "x:zeta2"], {"x:phi2": 0.01, "x:w2": 0.02 * w, "x:zeta2": 0.01},
                    {"x:w2": _mode_range(w, w1), "x:zeta2": ZETA2_RANGE}))
    return out


def _mode_range(w: float, w1: float) -> tuple[float, float]:
    """The range a second mode started at ``w`` is fitted in: within a factor 2 of its start, and on
    the start's side of the band MODE_APART around the fundamental ``w1``, where a fitted mode is
    refused (diagnose.implausible). A fit that may cross into that band settles beside the
    fundamental and takes up the baseline's error there instead of the mode it started at, and is
    then refused. A start inside the band keeps the plain range."""
    lo, hi = 0.5 * w, 2.0 * w
    if w1 > 0 and w > (1 + MODE_APART) * w1:
        lo = max(lo, (1 + MODE_APART) * w1)
    elif w1 > 0 and w < (1 - MODE_APART) * w1:
        hi = min(hi, (1 - MODE_APART) * w1)
    return lo, hi


def _exciter(base, ctx):
    # the drive's roll-off starts inside its bound (0.1 Hz), the distortion at 0 (recon.exciter)
    m = _am(base, {}, "exciter_distortion")
    m.baseline.drive_u2, m.baseline.drive_hp = 0.0, 2 * math.pi * 0.1
    return [(m, ["drive_u2", "drive_hp"], {"drive_u2": 0.01 / ctx["u_rms"], "drive_hp": 2 * math.pi * 0.5},
             {"drive_hp": (0.0, 2 * math.pi * 0.5 * ctx["f_res"])})]


# shares of the baseline's stiffness K that the hysteresis candidate also starts with in its loop,
# k lowered by as much (see _hysteresis)
HYSTERESIS_SPLIT_SHARES = (0.1, 0.3)


def _hysteresis_starts(base, ctx, alpha_share: float, bounds: dict, split_shares: tuple = ()):
    """Starts of the hysteresis candidate: alpha at ``alpha_share`` of K beside the baseline's k, and
    for each of ``split_shares`` alpha at that share of K with k lowered by as much (K = k + alpha
    kept); each at two loop widths (gamma + delta = 1 and 3 over the response's rms)."""
    out = []
    K = abs(base.K_m)
    for share, split in [(alpha_share, False)] + [(s, True) for s in split_shares]:
        for lam_y in (1.0, 3.0):
            m = _am(base, {}, "hysteresis")
            lam = lam_y / ctx["y_rms"]
            m.baseline.alpha_m = share * K
            if split:
                m.baseline.k_m = base.k_m - share * K
            m.baseline.gamma = 0.6 * lam
            m.baseline.delta = 0.4 * lam
            out.append((m, ["alpha_m", "gamma", "delta"],
                        {"alpha_m": 0.05 * K, "gamma": 0.3 * lam, "delta": 0.3 * lam}, dict(bounds)))
    return out


def _hysteresis(base, ctx):
    # a model without the law has taken the loop's small-amplitude stiffness into k (a Bouc-Wen
    # oscillator's tangent stiffness at rest is k + alpha): the starts also give part of k to the
    # loop. From alpha = 0 beside the whole k the fits can end in a narrow loop (a large gamma) far
    # from the truth; from a share of K in alpha they reach it
    return _hysteresis_starts(base, ctx, 0.0, {}, HYSTERESIS_SPLIT_SHARES)


def _hysteresis_admissible(base, ctx):
    # alpha >= 0 (a loop traversed the other way feeds energy in), started inside the bound at 5 %
    # of K (from alpha = 0 on the bound the fit does not move): tried when the fit from alpha = 0
    # ends inadmissible (a negative alpha beside a stiffer k, which lets another candidate be named)
    return _hysteresis_starts(base, ctx, 0.05, {"alpha_m": (0.0, np.inf)})


CATALOG: dict[str, Candidate] = {c.id: c for c in (
    Candidate("cubic_stiffness",
              "the spring stiffens (or softens) with amplitude symmetrically: a cubic restoring-force term",
              "library term y^3 in fn", "fn gains a_3 y^3 (RK4 of the augmented SDOF)", ("fn:y^3",),
              _fn_start("y^3", "cubic_stiffness", lambda c: 0.01 * c["acc_rms"] / c["y_rms"] ** 3),
              lambda b, c: "y^3" not in b.fn_m, column=lambda am, t, y, dy: y ** 3),
    Candidate("quadratic_stiffness",
              "the spring is stiffer on one side than on the other: a quadratic (asymmetric) restoring-force term",
              "library term y^2 in fn", "fn gains a_2 y^2", ("fn:y^2",),
              _fn_start("y^2", "quadratic_stiffness", lambda c: 0.01 * c["acc_rms"] / c["y_rms"] ** 2),
              lambda b, c: "y^2" not in b.fn_m, column=lambda am, t, y, dy: y ** 2),
    Candidate("quadratic_damping",
              "dissipation grows with the square of the velocity (air drag, turbulent losses)",
              "term c2 y'|y'| in the restoring force", "extra force c2 y'|y'|", ("x:c2",), _quad_damp,
              column=lambda am, t, y, dy: dy * np.abs(dy), hysteresis_absorbs=True),
    Candidate("coulomb_friction",
              "dry friction: a force of constant size opposing the motion, independent of amplitude",
              "term mu sign(y') (smoothed: tanh(y'/v0)) in the restoring force",
              "extra force mu tanh(y'/v0); v0 fitted from 1, 5, 20, 100 or 300 % of the smallest stage rms velocity (the best start)",
              ("x:mu", "x:v0"), _coulomb, column=lambda am, t, y, dy: np.tanh(dy / am.get("v0")), screen_output=True,
              hysteresis_absorbs=True),
    Candidate("contact_stiffness",
              "one-sided contact: beyond a gap the specimen touches a stop and gets stiffer on that side only",
              "term kc max(s*y - gap, 0) (s = +1 or -1) in the restoring force",
              "extra force kc (y - gap) when y is beyond the gap on side s", ("x:kc", "x:gap", "x:side"), _contact,
              screen_keys=1, column=lambda am, t, y, dy: (1.0 if am.get("side") >= 0 else -1.0)
              * np.maximum((1.0 if am.get("side") >= 0 else -1.0) * y - am.get("gap"), 0.0), fit_each="side",
              even_stiffness_absorbs=True),
    Candidate("channel_delay",
              "the two sensors are not sampled at the same instant: the displacement channel lags the input channel",
              "model change: output y_rec(t) = x_tip(t - d) - x_base(t) (force: y(t - d))",
              "simulate, then delay the displacement channel by d (linear interpolation)", ("x:delay",), _delay),
    Candidate("sensor_scale",
              "a sensor is mis-calibrated: the tip reading is (1 + e) times the true value "
              "(a base-sensor error of -e looks nearly the same)",
              "model change: y_rec = (1 + e) x_tip - x_base",
              "simulate, then scale the tip channel", ("x:tip_scale",), _scale,
              lambda b, c: b.excitation == BASE,
              # a tip-scale error can be taken up by a spurious Bouc-Wen law in the baseline; the
              # scale fitted from that baseline (as given, refitted, or alone) then ends worse than
              # the baseline, while from the baseline without the law it reaches the true scale
              # (the truth's figure)
              hysteresis_absorbs=True),
    Candidate("parameter_drift",
              "the stiffness changes slowly during the session (temperature, fatigue, settling)",
              "model change: k(t) = k (1 + drift t), t = recorded stage time",
              "k_m varies linearly with the recorded time", ("x:drift",), _drift,
              column=lambda am, t, y, dy: am.baseline.k_m * t * y),
    Candidate("higher_mode",
              "a second resonance the one-mode model leaves out shows up in the displacement reading",
              "model change: extra mode q'' + 2 zeta w q' + w^2 q = g u - drive2 a, reading += phi q "
              "(a: the measured point's absolute acceleration beyond the input's)",
              "a second-order oscillator driven by the input (drive2 = 0, a structural mode) or by the measured "
              "point's motion (drive2 = 1, a resonance riding on it), added to the displacement output",
              ("x:w2", "x:zeta2", "x:phi2"), _higher_mode, screen_keys=1, fit_each="drive2"),
    Candidate("offset",
              "a constant force acts on the specimen (a preload, gravity on a tilted rig, a sensor or amplifier "
              "offset): the response sits off its centre by f0 / k",
              "library term y^0 (a constant f0 per unit mass) in fn", "fn gains f0 y^0 (RK4 of the augmented SDOF)",
              ("fn:y^0",), _fn_start("y^0", "offset", lambda c: 0.01 * c["acc_rms"]),
              lambda b, c: "y^0" not in b.fn_m, column=lambda am, t, y, dy: np.ones_like(y)),
    Candidate("amplitude_damping",
              "the damping grows with the displacement amplitude (micro-slip in bolted or clamped joints): "
              "a y^2 y' dissipation term",
              "library term y^2*dy in fn", "fn gains b y^2 y' (RK4 of the augmented SDOF)", ("fn:y^2*dy",),
              _fn_start("y^2*dy", "amplitude_damping", lambda c: 0.01 * c["acc_rms"] / (c["y_rms"] ** 2 * c["v_rms"])),
              lambda b, c: "y^2*dy" not in b.fn_m, column=lambda am, t, y, dy: y ** 2 * dy,
              hysteresis_absorbs=True),
    Candidate("exciter_distortion",
              "the input is the exciter's drive (an amplifier voltage), and the exciter does not turn it into "
              "force in proportion: an even-order distortion (u^2) and a low-frequency roll-off",
              "model change: the force is HP(u + u2 u^2), a first-order high-pass of corner hp",
              "the drive transformed (recon.exciter), then the SDOF (force excitation only)",
              ("drive_u2", "drive_hp"), _exciter, lambda b, c: b.excitation != BASE and not b.has_drive),
    Candidate("hysteresis",
              "the restoring force depends on the history of motion (a Bouc-Wen hysteretic loop) "
              "that the baseline without hysteresis cannot produce",
              "Bouc-Wen state z' = alpha y' - gamma |y'| z - delta y' |z| added to the restoring force",
              "the SDOF with its Bouc-Wen state", ("alpha_m", "gamma", "delta"), _hysteresis,
              lambda b, c: b.alpha_m == 0.0, admissible_starts=_hysteresis_admissible),
)}


def describe() -> list[dict]:
    """The catalog as plain records (for docs and --json consumers)."""
    return [{"id": c.id, "explanation": c.explanation, "adds": c.adds, "simulated": c.simulated}
            for c in CATALOG.values()]

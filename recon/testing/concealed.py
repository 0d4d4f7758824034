"""Ground-truth recordings with one extra effect concealed in them (tests and bench).

The integrator (recon.testing.truth.integrate, shared with the plain ground truth) is
independent of :mod:`recon.diagnosis.augmented`: the input is an analytic
multisine evaluated exactly at every RK4 stage on a fine internal step, the
friction uses the simulated rig's smoothing (tanh(y'/1e-4 m/s)), the
channel delay is a band-limited fractional shift (cubic spline; the simulated rig
delays by whole samples at 10 kHz) and the noise is white at a given SNR per channel. Stage times run on one session clock
(stage k starts where stage k-1 ended), so a stiffness drift accumulates over
the session as on the rig.
"""
from __future__ import annotations


import numpy as np
from scipy.interpolate import CubicSpline

from recon.diagnosis.catalog import CATALOG
from recon.model import HystereticModel
from recon.testing.truth import Multisine, integrate, model_params
from shakerlab.run_data import BASE, FORCE, Run, Stage

# the effects the concealed runs of the tests use (every registered candidate with a recipe can be
# concealed: Candidate.conceal)
EFFECTS = ("coulomb_friction", "quadratic_damping", "contact_stiffness", "channel_delay", "sensor_scale",
           "parameter_drift", "higher_mode", "cubic_stiffness", "quadratic_stiffness", "hysteresis")


def base_truth(excitation: str = BASE) -> HystereticModel:
    """The clean specimen (like recon.testing.truth.sdof_truth, with the rig's quadratic stiffness too)."""
    return HystereticModel(excitation=excitation, c_m=3.0, k_m=4000.0, alpha_m=5000.0, gamma=500.0, delta=300.0,
                           fn_m={"y^2": 2.0e5, "y^3": 2.0e8, "y^2*dy": 3.0e6},
                           inv_m=2.0 if excitation == FORCE else None, provenance={"source": "concealed.base_truth"})


def effect_truth(effect: str | None, strength: float, excitation: str = BASE):
    """(truth model, extras dict, baseline model to test) for one concealed effect.

    ``strength`` 1 is "concealed": the baseline's validation NRMSE rises by a few percent.
    The baseline is the truth without the effect (for stiffness terms and hysteresis: the
    truth with that term removed)."""
    truth = base_truth(excitation)
    extras = {}
    baseline = HystereticModel.from_dict(truth.to_dict())
    if effect is None:
        return truth, extras, baseline
    cand = CATALOG.get(effect)
    if cand is None or cand.conceal is None:
        known = [c for c, v in CATALOG.items() if v.conceal is not None]
        raise ValueError(f"unknown effect {effect!r} (known: {', '.join(known)})")
    # the candidate's own recipe (its module in recon/diagnosis/candidates/)
    extras = dict(cand.conceal(truth, baseline, strength))
    return truth, extras, baseline


def stage_signals(excitation: str, duration: float, rng: np.random.Generator) -> dict:
    """Excitation of the three stages: small broadband, large near resonance (ramped), validation."""
    if excitation == BASE:
        fr = np.array([4.0, 7.0, 11.0, 16.0, 23.0, 31.0, 45.0, 60.0])
        lin = Multisine(list(fr), list(2e-5 * (10.0 / fr) ** 1.0), list(rng.uniform(0, 2 * np.pi, fr.size)))
        non = Multisine([12.5, 19.0, 48.0], [6.0e-4, 1.0e-4, 1.0e-5], [0.0, 1.0, 2.0], ramp=duration)
        val = Multisine([9.0, 14.0, 21.0, 52.0], [2.5e-4, 1.0e-4, 8e-5, 8e-6], [0.0, 1.0, 2.0, 0.5])
    else:
        fr = np.array([4.0, 7.0, 11.0, 16.0, 23.0, 31.0, 45.0, 60.0])
        lin = Multisine(list(fr), [0.01] * fr.size, list(rng.uniform(0, 2 * np.pi, fr.size)))
        non = Multisine([12.5, 19.0, 48.0], [2.0, 0.5, 0.3], [0.0, 1.0, 2.0], ramp=duration)
        val = Multisine([9.0, 14.0, 21.0, 52.0], [0.8, 0.4, 0.4, 0.2], [0.0, 1.0, 2.0, 0.5])
    return {"linear": lin, "nonlinear": non, "validation": val}


def concealed_run(effect: str | None = None, strength: float = 1.0, excitation: str = BASE, fs: float = 1000.0,
                  duration: float = 4.0, snr_db: float | None = 70.0, seed: int = 0, fine: int = 8):
    """A recorded run (linear, nonlinear, validation) with ``effect`` concealed.

    Returns (run, truth_model, extras, baseline_model)."""
    truth, extras, baseline = effect_truth(effect, strength, excitation)
    rng = np.random.default_rng(seed)
    sigs = stage_signals(excitation, duration, rng)
    n = int(round(duration * fs)) + 1
    coef, p, r = truth.fn_arrays()
    P = model_params(truth, extras)
    stages = {}
    t0 = 0.0
    for name, sig in sigs.items():
        a, w, ph = sig.arrays()
        base = excitation == BASE
        amp = a * w * w if base else a
        out = integrate(n, 1.0 / fs, fine, t0, amp, w, ph, float(sig.ramp), base, P, coef, p, r)
        tl = np.arange(n) / fs
        y = out[0] + extras.get("phi2", 0.0) * out[3]
        x_in = sig.value(tl)
        x_disp = x_in + y if base else y
        d = extras.get("delay", 0.0)
        if d:   # band-limited (cubic-spline) fractional delay, independent of the model's interpolation
            x_disp = CubicSpline(tl, x_disp)(np.clip(tl - d, 0.0, None))
        x_disp = (1.0 + extras.get("tip_scale", 0.0)) * x_disp

        def noisy(x):
            if snr_db is None:
                return x
            rms = np.sqrt(np.mean((x - x.mean()) ** 2))
            return x + rng.normal(0.0, rms / 10 ** (snr_db / 20), x.size)

        ch = {"x_base": noisy(x_in), "x_tip": noisy(x_disp)} if base else {"force": noisy(x_in), "x": noisy(x_disp)}
        st = Stage(name=name, t=t0 + tl, channels=ch, excitation=excitation)
        st.settings["truth"] = {"y": out[0], "dy": out[1], "z": out[2]}
        stages[name] = st
        t0 += duration + 1.0 / fs
    run = Run(stages=stages, source=f"concealed:{effect or 'clean'}:{strength:g}:{excitation}:{seed}")
    return run, truth, extras, baseline

"""The linear step's stage: c and K (and 1/m) from the linear stage, or, when that stage is too noisy to
determine them, from the stage that carries the least noise against its motion.

Principle: a stage's information on c and K is judged by its own noise (recon.steps.linear.fit_linear
refuses a regression whose columns' noise buries their weakest direction). A linear stage recorded at a
few dB (noise ten times the usual against a small motion) does not fix c and K, but the larger stages do:
their equivalent-linear fit is a start, and the nonlinear step refits c and K together with the
hysteresis and the fn terms on the nonlinear stage (``ReconSettings.refit_linear``), after which the
output-error polish and the joint fit of the stages (recon.estimator.two_stage) finish them. The
held-out (validation) stages are never used, so that the validation stays out of sample.
"""
from __future__ import annotations

import numpy as np

from recon.differentiation import estimate_spectrum
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.estimator.fallback import held_out_stages
from recon.signals import stage_signals
from recon.steps.linear import LinearFit, NoisyLinearStage, count_lines, fit_linear
from shakerlab.run_data import BASE, Run


def stage_linear_fit(run: Run, name: str, offset: bool = False,
                     tuning: EstimatorTuning = DEFAULT_TUNING) -> tuple[LinearFit, object]:
    """fit_linear on stage ``name`` (its pointwise-optimal signals), and those signals."""
    st = run.stage(name)
    sig = stage_signals(st, deriv=2, for_regression=False, tuning=tuning)
    lines = None
    if st.excitation != BASE:
        spec = estimate_spectrum(st.channels["force"], st.dt)
        lines = count_lines(spec.freqs, 1.0 / (st.t.size * st.dt), spec.power)
    return fit_linear(sig.y[0], sig.y[1], sig.y[2], sig.u[0], st.excitation, sig.column_noise, name, lines,
                      offset=offset), sig


def linear_step(run: Run, linear_stage: str, nonlinear_stage: str | None = None,
                offset: bool = False, tuning: EstimatorTuning = DEFAULT_TUNING) -> tuple[LinearFit, object, str]:
    """(fit, signals, stage used). The linear stage first; when it is too noisy (NoisyLinearStage) the
    fitted stages other than the held-out ones, smallest motion first (the closest to the small-amplitude
    regime whose c and K = k + alpha the linear step stands for), the first whose columns determine c and
    K; the fit then carries a warning saying so. When none does, the linear stage's refusal stands."""
    try:
        lf, sig = stage_linear_fit(run, linear_stage, offset, tuning)
        return lf, sig, linear_stage
    except NoisyLinearStage as noisy:
        refusal = noisy
    held, is_held = held_out_stages(run, (linear_stage, nonlinear_stage or linear_stage))
    others = [n for n in run.stages if n != linear_stage and not (is_held and n in held)]
    others.sort(key=lambda n: float(np.std(run.stage(n).y)))
    for name in others:
        try:
            lf, sig = stage_linear_fit(run, name, offset, tuning)
        except NoisyLinearStage:
            continue
        except Exception:      # noqa: BLE001 - a stage that cannot stand in (rank-deficient, too short): the next
            continue
        lf.warnings.append(
            f"linear stage {linear_stage!r} too noisy for c and K (its columns' noise is {refusal.noise:.2g} of "
            f"their rms): c and K started from stage {name!r} (noise {lf.noise_floor:.2g}) and were refitted with "
            f"the hysteresis on the nonlinear stage, then all stages fitted together")
        lf.stage = name
        return lf, sig, name
    raise refusal

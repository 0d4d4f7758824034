"""Stage signals: the smoothed motion, its derivatives and the model input of one recorded stage."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_coeffs

from recon.differentiation import choose_window, derivatives, estimate_spectrum
from shakerlab.run_data import BASE, Stage


@dataclass
class StageSignals:
    """Smoothed signals and derivatives of one stage (edges trimmed)."""

    t: np.ndarray
    y: list          # y, y', y'', y'''
    u: list          # u, u' (per-unit-mass input for base, force for force excitation)
    choice: dict
    column_noise: dict


def stage_signals(stage: Stage, deriv: int, window: int | None = None, order: int | None = None,
                  for_regression: bool = True) -> StageSignals:
    dt = stage.dt
    if stage.excitation == BASE:
        xb, xt = stage.channels["x_base"], stage.channels["x_tip"]
        ch = choose_window({"x_tip": xt, "x_base": xb}, dt, deriv=deriv, window=window, order=order,
                           for_regression=for_regression)
        yd = derivatives(xt - xb, dt, ch.window, ch.order, deriv)
        bd = derivatives(xb, dt, ch.window, ch.order, deriv)
        u = [-bd[2]] + ([-bd[3]] if deriv >= 3 else [])
        noise_u = ch.noise_level["x_base"]
    else:
        x, f = stage.channels["x"], stage.channels["force"]
        # the displacement's highest derivative dominates the error (force enters only as u, u')
        ch = choose_window({"x": x}, dt, deriv=deriv, window=window, order=order,
                           for_regression=for_regression)
        ch.noise_level["force"] = estimate_spectrum(f, dt).noise_std
        yd = derivatives(x, dt, ch.window, ch.order, deriv)
        fd = derivatives(f, dt, ch.window, ch.order, 1)
        u = [fd[0], fd[1]]
        noise_u = ch.noise_level["force"]
    # expected rms error of the filtered columns, used for the rank decision
    noise_y = float(np.sqrt(sum(v ** 2 for k, v in ch.noise_level.items() if k != "force")))
    cn = {}
    for d, name in ((0, "y"), (1, "dy"), (2, "ddy")):
        c = savgol_coeffs(ch.window, ch.order, deriv=d, delta=dt, use="dot")
        cn[name] = noise_y * float(np.sqrt(c @ c))
    c0 = savgol_coeffs(ch.window, ch.order, deriv=2 if stage.excitation == BASE else 0, delta=dt, use="dot")
    cn["u"] = noise_u * float(np.sqrt(c0 @ c0))
    half = ch.window // 2
    sl = slice(half, stage.t.size - half)
    return StageSignals(t=stage.t[sl], y=[a[sl] for a in yd], u=[a[sl] for a in u],
                        choice=ch.to_dict(), column_noise=cn)

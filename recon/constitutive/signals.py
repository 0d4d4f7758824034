"""The smoothed signals of one component-test stage: x, x', x'', F, F' and the command.

One Savitzky-Golay filter (recon.differentiation) for every channel of the stage, its window
chosen from the displacement for the second derivative (the highest one the force law
needs), or from a measured velocity for its first derivative. The edges (half a window) are
trimmed. The raw force of the same samples is kept: the output error compares with it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.differentiation import choose_window, estimate_spectrum, stable_coefficients, stable_derivatives
from shakerlab.errors import UserFacingError
from shakerlab.modes import COMMAND_CHANNEL, VELOCITY_CHANNEL
from shakerlab.run_data import FORCE, Stage


@dataclass
class ComponentSignals:
    t: np.ndarray
    dt: float
    y: np.ndarray
    dy: np.ndarray
    ddy: np.ndarray
    dddy: np.ndarray | None   # x''' (only when asked for: an inertia term)
    F: np.ndarray           # smoothed force
    dF: np.ndarray
    F_raw: np.ndarray       # the recorded force on the same samples
    cmd: np.ndarray | None
    choice: dict


def component_signals(stage: Stage, window: int | None = None, order: int | None = None,
                      for_regression: bool = True, third: bool = False) -> ComponentSignals:
    """``third``: also x''' (an inertia term m x'' enters the agent model's F' as m x''')."""
    if stage.excitation != FORCE or "force" not in stage.channels:
        raise UserFacingError(f"stage {stage.name!r}: a component test needs a force channel and a displacement "
                              f"channel x (t,x,force)")
    dt = stage.dt
    x = stage.channels["x"]
    f = stage.channels["force"]
    vel = stage.channels.get(VELOCITY_CHANNEL)
    if vel is not None:
        ch = choose_window({"v": vel}, dt, deriv=1, window=window, order=order, for_regression=for_regression,
                           coefficients=stable_coefficients)
    else:
        ch = choose_window({"x": x}, dt, deriv=2, window=window, order=order, for_regression=for_regression,
                           coefficients=stable_coefficients)
    if ch.window >= x.size // 2:
        raise UserFacingError(f"stage {stage.name!r}: {x.size} samples are too few for the smoothing window "
                              f"{ch.window}; record longer")
    ch.noise_level["force"] = estimate_spectrum(f, dt).noise_std
    xd = stable_derivatives(x, dt, ch.window, ch.order, (3 if third else 2) if vel is None else 0)
    if vel is not None:
        vd = stable_derivatives(vel, dt, ch.window, ch.order, 2 if third else 1)
        xd = [xd[0]] + vd
    fd = stable_derivatives(f, dt, ch.window, ch.order, 1)
    cmd = stage.channels.get(COMMAND_CHANNEL)
    half = ch.window // 2
    sl = slice(half, x.size - half)
    choice = ch.to_dict()
    choice["velocity"] = "measured" if vel is not None else "differentiated"
    return ComponentSignals(t=stage.t[sl], dt=dt, y=xd[0][sl], dy=xd[1][sl], ddy=xd[2][sl],
                            dddy=xd[3][sl] if third else None, F=fd[0][sl],
                            dF=fd[1][sl], F_raw=f[sl], cmd=None if cmd is None else np.asarray(cmd, float)[sl],
                            choice=choice)

"""Sensor quantities: displacement, velocity and acceleration channels, and their integration.

A motion channel is recorded in one quantity; its name says which: ``x_tip`` (displacement,
m), ``v_tip`` (velocity, m/s), ``a_tip`` (acceleration, m/s^2), and likewise ``x_base`` /
``v_base`` / ``a_base`` (base excitation) and ``x`` / ``v`` / ``a`` (force excitation).
The *role* of a channel is its displacement name (``x_tip``, ``x_base``, ``x``).

Displacement from velocity or acceleration (:func:`integrate`): each integration is a
fourth-order cumulative quadrature (the cubic through four neighbouring samples; the
trapezoid on the first and last step), after which a straight line (offset and slope) is
removed, fitted by least squares with a Hann weight over the stage. The line is what an
integration cannot know: the unknown start value (a constant) and a constant sensor offset (a
linear drift after one integration). Acceleration is integrated twice, the line removed
after each, so a constant accelerometer offset goes too. The Hann weight keeps the motion
out of the fit better than an unweighted one (measured on a 5 Hz tone over 10 s: the
displacement error falls from 1.5 % to 0.4 % of its rms in the 10 s linear stage of the
ground truth; over 10 periods the line leaks 0.25 % of the amplitude at the record's ends).
What stays is the integrated noise, a random walk (:func:`integrated_noise_rms`), and any
real drift of the structure's rest position, which a velocity sensor does not see.
tests/test_quantities.py measures the removal's effect on the identified parameters.

A velocity stage recorded by the rig (stage setting ``integration = "continuous"``, written by
``rig/recorder.py``) is integrated with nothing removed, from the displacement at its first
sample that the recorder integrated over the whole run since the common trigger, where the rig
is at rest (the dataset attribute ``start_m``; the unrecorded rests between stages included).
The line removal would take a real slow change of the rest position for drift (the mean shift
a quadratic stiffness makes as the amplitude grows: on the simulated rig's nonlinear stage a
0.3 mm ramp, 12 % of the motion), and a start at zero would lose the residual set a hysteretic
specimen keeps after a large stage (20 um before the simulated rig's validation stage: its
NRMSE rose from 0.006 to 0.034). What stays is the random walk of the noise over the run
(2e-5 m/s per sample at 10 kHz over 70 s: 2 um) and any offset of the sensor (a vibrometer has
none: a Doppler shift measures velocity with no zero offset).
"""
from __future__ import annotations

import numpy as np

DISPLACEMENT, VELOCITY, ACCELERATION = "displacement", "velocity", "acceleration"
QUANTITIES = (DISPLACEMENT, VELOCITY, ACCELERATION)
PREFIX = {DISPLACEMENT: "x", VELOCITY: "v", ACCELERATION: "a"}
ORDER = {DISPLACEMENT: 0, VELOCITY: 1, ACCELERATION: 2}
UNITS = {DISPLACEMENT: "m", VELOCITY: "m/s", ACCELERATION: "m/s^2"}
# the short forms a user may write (--map x_tip=NAME:v)
ALIASES = {"x": DISPLACEMENT, "d": DISPLACEMENT, "disp": DISPLACEMENT, DISPLACEMENT: DISPLACEMENT,
           "v": VELOCITY, "vel": VELOCITY, VELOCITY: VELOCITY,
           "a": ACCELERATION, "acc": ACCELERATION, ACCELERATION: ACCELERATION}
MOTION_ROLES = ("x_base", "x_tip", "x")
DEGREE = {VELOCITY: 1, ACCELERATION: 3}     # polynomial removed after each integration
CONTINUOUS = "continuous"   # stage setting ``integration``: from the dataset's ``start_m``, remove no line


def channel_name(role: str, quantity: str) -> str:
    """The channel name of a motion role recorded in ``quantity``: (x_tip, velocity) -> v_tip."""
    return PREFIX[quantity] + role[1:]


def parse_channel(name: str) -> tuple[str, str] | None:
    """(role, quantity) of a motion channel name, None for anything else (force, t, ...)."""
    for quantity, prefix in PREFIX.items():
        role = "x" + name[len(prefix):] if name.startswith(prefix) else None
        if role in MOTION_ROLES:
            return role, quantity
    return None


def cumulative_integral(values: np.ndarray, dt: float) -> np.ndarray:
    """Running integral from 0 at the first sample: per step the integral of the cubic through
    the four neighbouring samples, (-v[i-1] + 13 v[i] + 13 v[i+1] - v[i+2]) dt / 24 (error
    O(dt^5) per step); the trapezoid on the first and last step."""
    v = np.asarray(values, float)
    n = v.size
    inc = np.empty(max(n - 1, 0))
    if n >= 2:
        inc[:] = 0.5 * (v[:-1] + v[1:])
    if n >= 4:
        inc[1:-1] = (-v[:-3] + 13.0 * v[1:-2] + 13.0 * v[2:-1] - v[3:]) / 24.0
    return np.concatenate([[0.0], np.cumsum(inc) * dt])


def remove_line(x: np.ndarray, degree: int = 1) -> np.ndarray:
    """``x`` less its polynomial of ``degree`` (1: a straight line) over the stage, fitted by
    least squares with a Hann weight (module docstring)."""
    x = np.asarray(x, float)
    n = x.size
    if n <= degree + 2:
        return x - x.mean()
    s = 2.0 * np.arange(n) / (n - 1) - 1.0
    w = np.sqrt(np.sin(np.pi * np.arange(n) / (n - 1)) ** 2)
    A = np.polynomial.legendre.legvander(s, degree) * w[:, None]
    coef, *_ = np.linalg.lstsq(A, x * w, rcond=None)
    return x - np.polynomial.legendre.legval(s, coef)


def integrate(values: np.ndarray, dt: float, quantity: str, start: float | None = None) -> list[np.ndarray]:
    """[displacement, velocity, ...] down from a channel recorded in ``quantity``: the lower
    quantities by integration, the weighted line removed after each; ``values`` itself is the
    last element (unchanged). ``start`` (velocity only): the displacement at the first sample,
    known from a continuous integration (module docstring); then nothing is removed."""
    out = [np.asarray(values, float)]
    if start is not None:
        if quantity != VELOCITY:
            raise ValueError(f"a start value applies to a velocity channel, not {quantity}")
        return [float(start) + cumulative_integral(out[0], dt), out[0]]
    for _ in range(ORDER[quantity]):
        out.insert(0, remove_line(cumulative_integral(out[0], dt), DEGREE[quantity]))
    return out


# mean square of white noise (1 per sample) after 1 or 2 integrations with the weighted line
# removal, in units of (dt^2 n) and (dt^4 n^3): measured by Monte Carlo (n = 4000, 400 draws)
_NOISE_GAIN = {1: 0.094, 2: 8.2e-4}


def integrated_noise_rms(sigma: float, dt: float, n: int, times: int) -> float:
    """Rms of white noise (``sigma`` per sample) after ``times`` integrations of :func:`integrate`."""
    if times == 0:
        return float(sigma)
    return float(sigma * np.sqrt(_NOISE_GAIN[times] * dt ** (2 * times) * n ** (2 * times - 1)))

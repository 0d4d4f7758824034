"""Stage signals: the smoothed motion, its derivatives and the model input of one recorded stage.

The one place a stage's signals are made. The regression (:func:`stage_signals`), the weak
form (untrimmed, ``trim=False``), the diagnosis's equation residual, the model's input
(:func:`stage_input`) and the uncertainty's input-noise model (:func:`input_filter`) all take
them from here, so each follows the quantity the sensors measured.

Each motion channel is differentiated from the quantity its sensor measured, so that every
column takes the fewest numerical derivatives: from velocity, y' is the smoothed recording,
y'' its first derivative and y''' its second; from acceleration, y'' is the smoothed
recording. The columns below the measured quantity (y from velocity; y and y' from
acceleration) are integrals of the recording (line removed after each integration:
shakerlab/quantities.py), smoothed by the same filter. The displacement column integrated
twice from an acceleration record also has its cosine series below the record's band dropped
(:func:`drift_free_displacement`): there it holds the integrated noise, not motion. A
displacement-only stage takes the original path unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.fft import dct, idct

from recon.differentiation import (choose_window, derivatives, estimate_spectrum, savgol_coeffs, stable_coefficients,
                                   stable_derivatives, undo_passband_loss)
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.input_band import BandLimit
from shakerlab.quantities import (ACCELERATION, CONTINUOUS, DISPLACEMENT, ORDER, VELOCITY, channel_name, integrate,
                                  integrated_noise_rms)
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
                  for_regression: bool = True, trim: bool = True,
                  tuning: EstimatorTuning = DEFAULT_TUNING) -> StageSignals:
    """Smoothed y, y', ..., y^(deriv) and the input u (u' too when deriv >= 3) of one stage, with the
    expected noise of each column; ``trim`` drops the filter's half window at both edges. ``tuning``
    (``drift_band_share``) applies to a stage with a velocity or acceleration channel."""
    if any(q != DISPLACEMENT for q in stage.quantities.values()):
        return measured_signals(stage, deriv, window, order, for_regression, trim, tuning)
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
    sl = slice(half, stage.t.size - half) if trim else slice(None)
    return StageSignals(t=stage.t[sl], y=[a[sl] for a in yd], u=[a[sl] for a in u],
                        choice=ch.to_dict(), column_noise=cn)


def channel_derivatives(stage: Stage, role: str, deriv: int, window: int, order: int,
                        tuning: EstimatorTuning = DEFAULT_TUNING) -> list:
    """[x, x', ..., x^(deriv)] of one motion role: Savitzky-Golay derivatives of the measured
    quantity from its own order up, the smoothed integrals below it (numerically stable
    Savitzky-Golay coefficients: the windows here are longer, recon.differentiation); the
    displacement without its drift (:func:`drift_free_displacement`)."""
    q = stage.quantities[role]
    k = ORDER[q]
    measured = stage.channels[role] if k == 0 else stage.measured[channel_name(role, q)]
    lower = integrate(measured, stage.dt, q)[:-1]         # displacement, velocity, ... below q
    if k:   # the stage's own displacement (integrated as its recording says: shakerlab.quantities)
        lower[0] = drift_free_displacement(stage, role, tuning)[0]
    out = [stable_derivatives(lower[d], stage.dt, window, order, 0)[0] for d in range(min(k, deriv + 1))]
    if deriv >= k:
        out += stable_derivatives(measured, stage.dt, window, order, deriv - k)
    return out


def measured_signals(stage: Stage, deriv: int, window: int | None, order: int | None,
                     for_regression: bool, trim: bool = True,
                     tuning: EstimatorTuning = DEFAULT_TUNING) -> StageSignals:
    """:func:`stage_signals` of a stage with a velocity or acceleration channel."""
    dt = stage.dt
    n = stage.t.size
    roles = ("x_tip", "x_base") if stage.excitation == BASE else ("x",)
    k = {r: ORDER[stage.quantities[r]] for r in roles}
    name = {r: channel_name(r, stage.quantities[r]) for r in roles}
    raw = {r: stage.channels[r] if k[r] == 0 else stage.measured[name[r]] for r in roles}
    kmin = min(k.values())
    # one window for every channel, chosen for the channel(s) that need the most derivatives
    ch = choose_window({name[r]: raw[r] for r in roles if k[r] == kmin}, dt, deriv=max(deriv - kmin, 0),
                       window=window, order=order, for_regression=for_regression,
                       coefficients=stable_coefficients)
    for r in roles:
        if name[r] not in ch.noise_level:
            ch.noise_level[name[r]] = estimate_spectrum(raw[r], dt).noise_std
    if stage.excitation == BASE:
        d = {r: channel_derivatives(stage, r, max(deriv, 2), ch.window, ch.order, tuning) for r in roles}
        yd = [d["x_tip"][i] - d["x_base"][i] for i in range(deriv + 1)]
        u = [-d["x_base"][2]] + ([-d["x_base"][3]] if deriv >= 3 else [])
    else:
        yd = channel_derivatives(stage, "x", deriv, ch.window, ch.order, tuning)
        f = stage.channels["force"]
        ch.noise_level["force"] = estimate_spectrum(f, dt).noise_std
        fd = stable_derivatives(f, dt, ch.window, ch.order, 1)
        u = [fd[0], fd[1]]
    # expected rms error of each filtered column: a channel's white noise through the filter at
    # and above its measured order, its integrated noise (shakerlab.quantities) below it, without
    # the coefficients drift_free_displacement dropped
    cn = {}
    for dd, colname in ((0, "y"), (1, "dy"), (2, "ddy")):
        var = 0.0
        for r in roles:
            sigma = ch.noise_level[name[r]]
            if dd >= k[r]:
                c = stable_coefficients(ch.window, ch.order, dd - k[r], dt)
                var += float(sigma * sigma * (c @ c))
            elif dd == 0 and drift_free_displacement(stage, r, tuning)[1]:   # the drift dropped
                var += drift_free_noise_rms(sigma, dt, n, k[r], drift_free_displacement(stage, r, tuning)[1]) ** 2
            else:
                var += integrated_noise_rms(sigma, dt, n, k[r] - dd) ** 2
        cn[colname] = float(np.sqrt(var))
    if stage.excitation == BASE:
        c0 = stable_coefficients(ch.window, ch.order, max(2 - k["x_base"], 0), dt)
        cn["u"] = ch.noise_level[name["x_base"]] * float(np.sqrt(c0 @ c0))
    else:
        c0 = stable_coefficients(ch.window, ch.order, 0, dt)
        cn["u"] = ch.noise_level["force"] * float(np.sqrt(c0 @ c0))
    choice = ch.to_dict()
    choice["quantities"] = dict(stage.quantities)
    half = ch.window // 2
    sl = slice(half, n - half) if trim else slice(None)
    return StageSignals(t=stage.t[sl], y=[a[sl] for a in yd], u=[a[sl] for a in u],
                        choice=choice, column_noise=cn)


def band_bottom(spectrum, size: int, dt: float) -> float | None:
    """The lowest frequency [Hz] of a record's band: its lowest significant bin
    (:func:`recon.differentiation.estimate_spectrum` of the record, ``size`` samples) that is not
    the leakage of a trend. A trend (the record's slow change over the stage, the motion at its
    ends) leaks into the bins next to zero frequency and falls bin by bin away from it; the
    significant bins from the first one up whose power keeps falling are that leakage. None when no
    bin is left."""
    df = 1.0 / (size * dt)
    k = np.round(np.asarray(spectrum.freqs, float) / df).astype(np.int64)
    p = np.asarray(spectrum.power, float)
    order = np.argsort(k)
    last_k, last_p = 0, np.inf
    for ki, pi in zip(k[order], p[order]):
        if ki == last_k + 1 and pi < last_p:
            last_k, last_p = int(ki), float(pi)
            continue
        return float(ki * df)
    return None


def drift_free_displacement(stage: Stage, role: str, tuning: EstimatorTuning = DEFAULT_TUNING) -> tuple:
    """(displacement, dropped): the stage's displacement of ``role`` when it was recorded as
    acceleration (integrated twice as :func:`shakerlab.quantities.integrate` says) less its
    cosine-series (DCT-II) coefficients below ``tuning.drift_band_share`` of the lowest frequency of
    the record's band (:func:`band_bottom`), and how many were dropped. A coefficient there that
    stands more than ``tuning.drift_keep_sigmas`` times above the integrated noise's expected level
    (the record's white noise over w_k^2) is motion and is kept: a stage that starts or ends in
    motion has a cosine series below its band.

    Below its band a record holds its noise only, and twice integrated that noise is the
    displacement's drift, its power rising as 1/f^4: it lies almost all below the band, where a
    stage that starts and ends at rest has next to no motion. Measured on the independent
    generator's twelve draws at 60 dB recorded as acceleration (36 stages): the displacement
    column's rms error against the true displacement fell from 0.8-49 % to 0.03-4.4 % of its rms
    (the rest: the part of a quadratic stiffness's mean shift that lies below the band, which the
    record does not hold above its noise). A velocity record's displacement is returned as it is:
    its noise below the band is a vibrometer's 1/f noise, above the white level the keep rule
    reads (dropping by that rule changed the velocity draws' worst parameter errors both ways,
    0.15 -> 0.53 % on one draw, 1.52 -> 3.24 % with two spurious terms on another), and its
    output-error fits never read this column. A displacement channel is returned as it is."""
    def make():
        x = stage.channels[role]
        q = stage.quantities[role]
        if not (ORDER[q] == ORDER[ACCELERATION] and tuning.drift_band_share > 0.0):
            return x, 0
        spectrum = estimate_spectrum(stage.measured[channel_name(role, q)], stage.dt)
        f_lo = band_bottom(spectrum, x.size, stage.dt)
        n = x.size
        kb = 0 if f_lo is None else int(np.ceil(2.0 * n * stage.dt * tuning.drift_band_share * f_lo))
        if not kb:
            return x, 0
        c = dct(x, type=2, norm="ortho")
        # the integrated noise's expected level in each coefficient below the band; one that stands
        # above it holds motion (a stage that starts or ends in motion has a cosine series there)
        k = np.arange(1, min(kb, n))
        w = 2.0 * np.sin(np.pi * k / (2.0 * n)) / stage.dt
        level = spectrum.noise_std / w ** ORDER[q]
        drop = np.concatenate([[True], np.abs(c[k]) <= tuning.drift_keep_sigmas * level])
        c[:kb][drop] = 0.0
        return idct(c, type=2, norm="ortho"), int(np.count_nonzero(drop))
    return stage.derived(("drift_free_displacement", role, tuning.drift_band_share, tuning.drift_keep_sigmas),
                         make)


def drift_free_noise_rms(sigma: float, dt: float, n: int, times: int, dropped: int) -> float:
    """Rms of white noise (``sigma`` per sample) integrated ``times`` times, its first ``dropped``
    cosine-series coefficients dropped (:func:`drift_free_displacement`): each coefficient k carries
    sigma / w_k^times, w_k = 2 sin(pi k / 2n) / dt."""
    k = np.arange(max(int(dropped), 1), n)
    w = 2.0 * np.sin(np.pi * k / (2.0 * n)) / dt
    return float(sigma * np.sqrt(np.sum(w ** (-2.0 * times)) / n))


@dataclass
class InputFilter:
    """How the model input u of a stage is made from its input channel: u = -x_base'' of a
    base-excited stage, the recorded force itself under force excitation.

    - base displacement: a Savitzky-Golay second derivative, with the filter's known passband loss
      undone (0.08 % at a 12.5 Hz drive with a 109-sample window at 2 kHz; left in, the
      output-error fit turned it into a -0.1 % bias of the cubic stiffness);
    - base velocity: one Savitzky-Golay derivative of the velocity;
    - base acceleration: the smoothed acceleration with the passband loss undone;
    the integrated displacement is never differentiated back.
    The same filter applied to white noise of ``noise_std`` gives the noise u carries
    (the uncertainty ensemble's input-noise draws)."""

    channel: str
    raw: np.ndarray
    dt: float
    window: int | None = None      # None: u is the channel itself (force)
    order: int | None = None
    deriv: int = 0                 # Savitzky-Golay derivative taken of the channel
    measured: bool = False         # velocity or acceleration channel (stable coefficients)
    noise_std: float = 0.0
    band: BandLimit | None = None  # the recording's own band (recon.input_band); None: as recorded

    def __call__(self, x: np.ndarray) -> np.ndarray:
        if self.band is None:
            return self._smoothed(x)
        inner = self.band(x) if self.window is None else -self.band(x, self.deriv, self.dt)
        # an end in motion from the Savitzky-Golay filter (a local fit: the cosine series of a
        # record that starts or stops abruptly rings there), crossfaded into the band over one
        # window; an end at rest (BandLimit.level_ends) from the band
        start, end = self.band.level_ends
        if start and end:
            return inner
        w = edge_crossfade(x.size, self.window or self.band.window, start, end)
        return w * inner + (1.0 - w) * self._smoothed(x)

    def _smoothed(self, x: np.ndarray) -> np.ndarray:
        if self.window is None:
            return x
        if not self.measured:
            return undo_passband_loss(-derivatives(x, self.dt, self.window, self.order, 2)[2], self.dt,
                                      self.window, self.order)
        acc = stable_derivatives(x, self.dt, self.window, self.order, self.deriv)[self.deriv]
        if self.deriv == 0:
            acc = undo_passband_loss(acc, self.dt, self.window, self.order, deriv=0)
        return -acc

    def info(self) -> dict:
        out = {"channel": self.channel, "noise_std": float(self.noise_std)}
        if self.band is not None:
            out["band_share"] = self.band.kept_share
        if self.window is not None:
            out.update(window=self.window, order=self.order)
        return out


def edge_crossfade(n: int, window: int, start_level: bool = False, end_level: bool = False) -> np.ndarray:
    """Weights 0 over the first and last ``window`` samples, 1 from two windows in, a raised cosine
    between; 1 throughout at an end that is level."""
    w = np.ones(n)
    m = max(min(window, n // 4), 1)
    fade = np.concatenate([np.zeros(m), 0.5 * (1.0 - np.cos(np.pi * np.arange(m) / m))])
    if not start_level:
        w[:2 * m] = fade
    if not end_level:
        w[n - 2 * m:] = np.minimum(w[n - 2 * m:], fade[::-1])
    return w


def _band_key(band: bool, tuning: EstimatorTuning):
    """What a stage's input depends on besides its channels: the band and the numbers it is decided with."""
    return (tuning.band_slope_sigmas, tuning.band_smooth, tuning.band_false_alarm, tuning.band_grow) if band else None


def input_filter(stage: Stage, band: bool = True, tuning: EstimatorTuning = DEFAULT_TUNING) -> InputFilter:
    """The :class:`InputFilter` of ``stage`` (its input channel, window and noise level, and, with
    ``band``, the channel's own band where it can be told from the noise: recon.input_band, with
    ``tuning``'s band_* fields); made once per stage (Stage.derived)."""
    def make():
        f = _savitzky_golay_filter(stage)
        if band:
            f.band = BandLimit.of(f.raw, f.noise_std, f.window, f.order, tuning)
        return f
    return stage.derived(("input_filter", _band_key(band, tuning)), make)


def _savitzky_golay_filter(stage: Stage) -> InputFilter:
    if stage.excitation != BASE:
        f = stage.channels["force"]
        return InputFilter("force", f, stage.dt, noise_std=float(estimate_spectrum(f, stage.dt).noise_std))
    q = stage.quantities.get("x_base", DISPLACEMENT)
    if q == DISPLACEMENT:
        xb = stage.channels["x_base"]
        ch = choose_window({"x_base": xb}, stage.dt, deriv=2, for_regression=False)
        return InputFilter("x_base", xb, stage.dt, ch.window, ch.order, 2,
                           noise_std=float(ch.noise_level["x_base"]))
    k = ORDER[q]
    name = channel_name("x_base", q)
    raw = stage.measured[name]
    ch = choose_window({name: raw}, stage.dt, deriv=2 - k, for_regression=False, coefficients=stable_coefficients)
    return InputFilter(name, raw, stage.dt, ch.window, ch.order, 2 - k, measured=True,
                       noise_std=float(ch.noise_level[name]))


def stage_input(stage: Stage, band: bool = True, tuning: EstimatorTuning = DEFAULT_TUNING) -> np.ndarray:
    """The model input u of ``stage`` (:class:`InputFilter`; ``band``, ``tuning``: see :func:`input_filter`)."""
    def make():
        f = input_filter(stage, band, tuning)
        return f(f.raw)
    return stage.derived(("stage_input", _band_key(band, tuning)), make)


def edge_fit(size: int, window: int, order: int) -> tuple[int, int, np.ndarray]:
    """The edge of a stage for its start-state estimates: the samples looked at (at most four
    windows), the odd window that fits in them, and the pseudo-inverse pinv of the polynomial fit over
    the first w samples on x = 0..1 (coefficient j at the first sample: (pinv @ x)[j] / ((w-1) dt)^j;
    scipy's savgol_coeffs(pos=0) loses accuracy for long windows, hence the own fit)."""
    n = min(size, 4 * window)
    w = min(window, n - (1 - n % 2))
    return n, w, np.linalg.pinv(np.vander(np.arange(w) / (w - 1), order + 1, increasing=True))


def start_derivatives(stage: Stage) -> tuple[float, float, float, float, float, float]:
    """y, y', y'' at the stage's first sample, from a Savitzky-Golay fit over its first
    samples (at most four windows), with the noise of y, the noise of that edge estimate of y',
    and the stage's rms y' (for the model's start state, HystereticModel.stage_start); made once
    per stage (Stage.derived)."""
    return stage.derived("start_derivatives", lambda: _start_derivatives(stage))


def _start_derivatives(stage: Stage) -> tuple[float, float, float, float, float, float]:
    y = stage.y
    ch = choose_window({"y": y}, stage.dt, deriv=2, for_regression=False)
    n, w, pinv = edge_fit(y.size, ch.window, ch.order)
    d = derivatives(y[:n], stage.dt, w, ch.order, 2)
    sigma = ch.noise_level["y"]
    # y'(0) of the least-squares polynomial over the first w samples: weights pinv[1]/((w-1) dt)
    sig_v = sigma * float(np.linalg.norm(pinv[1])) / ((w - 1) * stage.dt)
    v_rms = float(np.sqrt(np.mean(derivatives(y, stage.dt, ch.window, ch.order, 1)[1] ** 2)))
    return d[0][0], d[1][0], d[2][0], sigma, sig_v, v_rms


def continuous_velocity_start(stage: Stage):
    """Made once per stage (Stage.derived) by :func:`_continuous_velocity_start`."""
    return stage.derived("continuous_velocity_start", lambda: _continuous_velocity_start(stage))


def _continuous_velocity_start(stage: Stage):
    """(y0, y'0, y''0, at_rest) at the first sample of a stage whose motion the rig recorded as
    velocity and integrated continuously (``integration = "continuous"``,
    :mod:`shakerlab.quantities`); None for any other stage.

    y0 is the integrated displacement's first value (a real residual set: the rig integrated it
    since the trigger). y'0 and y''0 come from the measured relative velocity (a polynomial fit at
    the edge, the window chosen for its noise), never from differentiating the integral: the
    integral's own noise level is far below its start value's uncertainty, so the displacement
    rule (``|y0| < 5 sigma``) never saw a rest and took y''0 from two derivatives of the integral
    (z0 = 5.1 m/s^2 on the simulated rig's nonlinear stage, truth ~0). At rest (:func:`at_rest`:
    y'0 within 5 times its edge noise, y''0 small) y'0 = y''0 = 0, and the caller
    takes the input as 0 too (the stage starts from a static state, z0 = -k y0 - fn(y0)): a
    Savitzky-Golay input's edge value is no rest value (u[0] = 0.95 m/s^2 at the simulated rig's
    validation start, where its mean over 800 samples is 0.01)."""
    if stage.settings.get("integration") != CONTINUOUS:
        return None
    roles = ("x_tip", "x_base") if stage.excitation == BASE else ("x",)
    if any(stage.quantities.get(r) != VELOCITY for r in roles):
        return None
    v = {r: stage.measured[channel_name(r, VELOCITY)] for r in roles}
    vel = v["x_tip"] - v["x_base"] if stage.excitation == BASE else v["x"]
    ch = choose_window({"v": vel}, stage.dt, deriv=1, for_regression=False, coefficients=stable_coefficients)
    _, w, pinv = edge_fit(vel.size, ch.window, ch.order)
    c = pinv @ vel[:w]
    v0, a0 = float(c[0]), float(c[1] / ((w - 1) * stage.dt))
    sig_v = ch.noise_level["v"] * float(np.linalg.norm(pinv[0]))
    sig_a = ch.noise_level["v"] * float(np.linalg.norm(pinv[1])) / ((w - 1) * stage.dt)
    a_rms = float(np.sqrt(np.mean(stable_derivatives(vel, stage.dt, ch.window, ch.order, 1)[1] ** 2)))
    y0 = float(stage.y[0])
    if at_rest(v0, sig_v, a0, sig_a, a_rms):
        return y0, 0.0, 0.0, True
    return y0, v0, a0, False


# The recorded quantities the output-error fits are judged in without integrating to displacement
# (response_target): velocity as measured, and acceleration integrated once, to velocity. An
# acceleration record judged as y'' weights the start's transient by w^2 and the input filter's
# edge (a stage that starts with the base accelerating) dominates it; judged on its twice-integrated
# displacement it carries that integral's drift: white noise of 1e-3 of the acceleration's rms
# becomes about 10 % of the displacement's at 8 kHz over 10 s (shakerlab.quantities.integrated_noise_rms),
# and the fits then took the drift for motion (validation NRMSE 0.7-1.0 on the independent
# generator at 60 dB, against 0.002 for the same draws recorded as displacement). One integration
# (its line removed) leaves about the acceleration's own relative noise in the velocity, and every
# fit in velocity already takes a constant offset as a nuisance parameter.
MEASURED_ORDERS = (1, 2)


def compared_response(stage: Stage) -> np.ndarray:
    """The response as the fits and the validation compare it: :func:`response_target`'s values for a
    record in velocity or acceleration, y for a displacement record."""
    target = response_target(stage)
    return stage.y if target is None else target[1]


def target_noise_std(stage: Stage) -> float:
    """The rms of the noise in :func:`compared_response`: its spectrum's white floor, and for an
    acceleration integrated once to velocity also the integral of the acceleration's white noise
    (shakerlab.quantities.integrated_noise_rms: a random walk with its line removed), which the
    velocity's white floor does not see."""
    floor = float(estimate_spectrum(compared_response(stage), stage.dt).noise_std)
    if response_order(stage) != 2:
        return floor
    role = "x_tip" if stage.excitation == BASE else "x"
    acc = np.asarray(stage.measured[channel_name(role, ACCELERATION)], float)
    sigma = float(estimate_spectrum(acc, stage.dt).noise_std)
    return float(np.hypot(floor, integrated_noise_rms(sigma, stage.dt, acc.size, 1)))


def target_order(stage: Stage) -> int | None:
    """The derivative order of :func:`response_target`'s values (1: velocity, for a velocity or an
    acceleration record), None for a displacement record."""
    return 1 if response_order(stage) in MEASURED_ORDERS else None


def response_order(stage: Stage) -> int:
    """The derivative order of the quantity the response (x_tip, or x under force excitation) was
    recorded in: 0 displacement, 1 velocity, 2 acceleration."""
    role = "x_tip" if stage.excitation == BASE else "x"
    return ORDER[stage.quantities.get(role, DISPLACEMENT)]


def response_target(stage: Stage):
    """(order, values): the relative motion y^(order) in the quantity the response was recorded in,
    for the output-error fits to compare the simulated state with; None for a response recorded as
    displacement (the fits compare y itself). Made once per stage (Stage.derived).

    The record is used as measured: no integration, so the integrated noise's drift (a velocity
    sensor's low-frequency noise, a random walk after one integration) never enters the fit. Under
    base excitation the base's motion in the same quantity is taken away: the base channel itself
    when it is recorded in that quantity; a Savitzky-Golay derivative of it when it is recorded
    lower (the input filter's window, its passband loss undone); an integral
    (shakerlab.quantities) when it is recorded higher. An acceleration record is judged in
    velocity, integrated once (:func:`measured_velocity`, MEASURED_ORDERS)."""
    if response_order(stage) not in MEASURED_ORDERS:
        return None
    return stage.derived("response_target", lambda: _response_target(stage))


def _response_target(stage: Stage):
    k = target_order(stage)
    tip = measured_velocity(stage)
    if stage.excitation != BASE:
        return k, tip
    return k, tip - base_motion(stage, k)


def measured_velocity(stage: Stage) -> np.ndarray:
    """The response channel (x_tip, or x under force excitation) as a velocity: as recorded, or an
    acceleration integrated once with its line removed (shakerlab.quantities.integrate). Made once
    per stage (Stage.derived): the target and the diagnosis's noise floor both read it."""
    return stage.derived("measured_velocity", lambda: _measured_velocity(stage))


def _measured_velocity(stage: Stage) -> np.ndarray:
    role = "x_tip" if stage.excitation == BASE else "x"
    q = stage.quantities[role]
    x = np.asarray(stage.measured[channel_name(role, q)], float)
    return x if ORDER[q] == 1 else integrate(x, stage.dt, q)[1]


def base_motion(stage: Stage, k: int) -> np.ndarray:
    """The base's motion x_base^(k) (k: 0 or 1, :func:`target_order`) as :func:`response_target`
    subtracts it."""
    qb = stage.quantities.get("x_base", DISPLACEMENT)
    kb = ORDER[qb]
    if kb == k:
        return stage.channels["x_base"] if kb == 0 else stage.measured[channel_name("x_base", qb)]
    if kb > k:
        return integrate(stage.measured[channel_name("x_base", qb)], stage.dt, qb)[k]
    f = input_filter(stage, band=False)       # kb = 0, k = 1: the base displacement's derivative
    d = derivatives(stage.channels["x_base"], stage.dt, f.window, f.order, 1)[1]
    return undo_passband_loss(d, stage.dt, f.window, f.order, deriv=1)


def base_noise_in_target(stage: Stage, noise: np.ndarray) -> tuple[np.ndarray, bool]:
    """What white noise ``noise`` on the base channel puts into the fitted target (y, or
    :func:`response_target`), with its sign, and whether it is that channel's own white noise (then
    it is part of the target's white floor)."""
    k = target_order(stage) or 0
    kb = ORDER[stage.quantities.get("x_base", DISPLACEMENT)]
    if k == kb:
        return -noise, True
    f = input_filter(stage, band=False)
    if kb == 0:
        d = derivatives(noise, stage.dt, f.window, f.order, 1)[1]
        return -undo_passband_loss(d, stage.dt, f.window, f.order, deriv=1), False
    return -integrate(noise, stage.dt, stage.quantities["x_base"])[k], False


def target_edge(stage: Stage) -> tuple[float, float, float, float, float, float]:
    """(x0, x0', noise of x0, rms of x, noise of x0', rms of x') of :func:`response_target`'s values
    x at the first sample: a polynomial fit over the stage's first samples (as
    :func:`_continuous_velocity_start`), the window chosen for the target's own noise. Made once
    per stage (Stage.derived)."""
    return stage.derived("target_edge", lambda: _target_edge(stage))


def _target_edge(stage: Stage):
    _, x = response_target(stage)
    ch = choose_window({"x": x}, stage.dt, deriv=1, for_regression=False, coefficients=stable_coefficients)
    _, w, pinv = edge_fit(x.size, ch.window, ch.order)
    c = pinv @ x[:w]
    noise = ch.noise_level["x"]
    sig = noise * float(np.linalg.norm(pinv[0]))
    sig1 = noise * float(np.linalg.norm(pinv[1])) / ((w - 1) * stage.dt)
    x1_rms = float(np.sqrt(np.mean(stable_derivatives(x, stage.dt, ch.window, ch.order, 1)[1] ** 2)))
    return (float(c[0]), float(c[1] / ((w - 1) * stage.dt)), sig, float(np.sqrt(np.mean(x ** 2))), sig1, x1_rms)


def at_rest(value: float, noise: float, slope: float, slope_noise: float, slope_rms: float) -> bool:
    """Whether a stage's first sample is at rest, judged as the displacement rule judges y0 and y'0
    (recon.model.HystereticModel.stage_start): the recorded quantity's edge ``value`` within 5 times
    its edge estimate's ``noise``, and its derivative's ``slope`` within 5 % of the stage's rms of
    it or within 4 times its noise. A start that is small against the stage's motion but stands out
    of the noise is motion: taken for rest, its free decay stays in the fit (a start at 1 % of the
    stage's rms velocity, 16 times its noise, cost a 7 % damping error on the independent
    generator at 60 dB), while a rest taken for motion is fitted back to rest."""
    return abs(value) < 5 * noise and (abs(slope) < 0.05 * slope_rms or abs(slope) < 4 * slope_noise)

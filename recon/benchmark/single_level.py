"""Identification from ONE excitation level under force excitation.

The project's main pipeline (recon.estimator.pipeline) separates a small-amplitude
*linear* stage from a large-amplitude *nonlinear* stage: the linear step sees
almost no hysteresis, so its (c, K, 1/m) are unbiased, and the agent-model
step then works on the nonlinear restoring force ``Fn``.  Data sets such as
the Bouc-Wen benchmark have a single level: the hysteresis is fully active in
the only record, so a linear least-squares fit absorbs the hysteretic force
into "equivalent" damping and stiffness (on the benchmark: c/m +740 %,
K/m +20 %), and ``Fn`` computed from those is not the hysteretic force.

What this module does instead (all on the same record):

1. **Periodic preprocessing** (:func:`periodic_record`).  A multisine record of
   P whole periods is averaged over periods 2..P (period 1 holds the start-up
   transient), the noise variance of every DFT bin is estimated from the
   period-to-period scatter, and only bins whose signal-to-noise ratio exceeds
   10 dB are kept.  Derivatives are taken exactly in the frequency domain on
   those bins and the signals are interpolated to ``upsample`` times the
   recording rate, so that products such as ``|y'| z`` (whose spectra reach far
   past the recording's Nyquist frequency) are formed without aliasing.
   A record that is not periodic (and starts from rest) goes through
   :func:`transient_record` instead: Savitzky-Golay derivatives (recon core),
   polyphase interpolation, running integrals from the first sample.
2. **Linear step** (:func:`linear_step`): least squares of
   ``y'' = b u - c y' - K y`` (b = 1/m), band-limited to the kept bins.  Its
   result is biased by the hysteresis; it is reported and used only to seed
   the next steps.
   **Agent-model step** (:func:`agent_model_step`): the paper's regression with
   the recon core (library, grouped sparse selection, extraction, structured
   refit with the linear terms free), iterated from the linear step.  Reported,
   and its estimate is the first start of step 3; at 40 dB SNR its third
   derivatives are too noisy for accurate parameters on their own.
3. **Hysteresis-aware linear re-estimation** (:func:`hysteresis_step`).  The
   hysteretic force is not measurable, but its ODE
   ``z' = alpha y' - gamma |y'| z - delta y' |z|`` is driven by the velocity
   alone.  For a trial (alpha, gamma, delta), ``z(t)`` is integrated from the
   measured velocity (periodic steady state); then the linear part is
   re-estimated with the hysteresis force accounted for, by least squares on
   the once-integrated momentum equation
   ``y' = b I[u] - c y - k I[y] - I[z]`` (``I`` the zero-mean periodic
   integral; only the first derivative of the noisy displacement is needed).
   The three nonlinear parameters are then adjusted by
   :func:`scipy.optimize.least_squares` on the remaining equation error
   (variable projection: "linear estimate -> nonlinear step -> re-estimate the
   linear part" iterated to convergence by the optimiser).  Optional static
   nonlinear terms ``fn`` (monomials ``y^p y'^r``) enter the inner linear
   least squares as extra columns ``I[y^p y'^r]``; by default they are added
   only when the refined model leaves more than noise in the residual
   (:func:`select_fn_terms`, adequacy test in :func:`identify`).
4. **Output-error refinement** (:mod:`recon.output_error.newmark_refine`): the benchmark's
   own simulation chain, fitted to the full record from zero initial state.

The result of every step is kept so that their accuracy can be compared
(bench/boucwen.py, docs/boucwen-benchmark.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.optimize import least_squares

from recon.differentiation import choose_window, derivatives
from recon.library import monomials
from recon.library.agent import AgentLibrary
from recon.library.clustering import cluster
from recon.model import HystereticModel
from recon.output_error.newmark_refine import refine as oe_refine
from recon.output_error.problem import FD_STEP
from recon.regression.sparse import AutoSTLSQ, GroupedSparseSelector
from recon.simulation import resampling
from recon.simulation.newmark import NewmarkParameters
from recon.steps.bouc_wen import estimate_delta, extract, refit
from shakerlab import __version__
from shakerlab.errors import UserFacingError

__all__ = ["PeriodicRecord", "detect_period", "periodic_record", "TransientRecord", "transient_record",
           "linear_step", "hysteresis_step",
           "agent_model_step", "AgentStep", "SingleLevelResult", "identify", "LinearStep", "HysteresisStep"]

SNR_DB_DEFAULT = 10.0       # a DFT bin is kept when its power is ten times its noise (identify's snr_db)


def detect_period(u, min_periods: int = 2, rtol: float = 1e-9) -> int:
    """Smallest period (in samples) such that ``u`` holds >= ``min_periods`` exact repeats."""
    u = np.asarray(u, dtype=float)
    n = u.size
    scale = np.max(np.abs(u)) or 1.0
    for p in range(1, n // min_periods + 1):
        if n % p:
            continue
        if np.max(np.abs(u.reshape(-1, p) - u[:p])) <= rtol * scale:
            return p
    raise UserFacingError(
        f"single-level identification: the input record ({n} samples) is not made of {min_periods} or more "
        "identical periods; record whole periods of a periodic excitation (e.g. a multisine) or give period="
    )


@dataclass
class PeriodicRecord:
    """One averaged period with its noise figures and band-limited derivatives."""

    fs: float                 # recording rate [Hz]
    period: int               # samples per period at fs
    n_periods_used: int       # periods averaged (the first one is skipped)
    upsample: int             # interpolation factor for the derivative signals
    u: np.ndarray             # one period of the input at fs
    y: np.ndarray             # averaged output period at fs
    snr_db: float             # threshold used to keep DFT bins
    kept: np.ndarray          # bool per rfft bin of one period: bins that carry signal
    noise_rms: float          # estimated rms noise of one raw sample [m]
    # band-limited signals at fs * upsample (one period)
    u_up: np.ndarray = field(repr=False, default=None)
    y0: np.ndarray = field(repr=False, default=None)
    y1: np.ndarray = field(repr=False, default=None)
    y2: np.ndarray = field(repr=False, default=None)

    @property
    def h(self) -> float:
        return 1.0 / (self.fs * self.upsample)

    def band_project(self, x: np.ndarray) -> np.ndarray:
        """Keep only the DFT bins that carry signal (columns of a 2-D array projected alike)."""
        n = self.period * self.upsample
        spec = np.fft.rfft(x, axis=0)
        mask = np.zeros(spec.shape[0], dtype=bool)
        mask[: self.kept.size] = self.kept
        spec[~mask] = 0
        return np.fft.irfft(spec, n=n, axis=0)

    def integral(self, x: np.ndarray) -> np.ndarray:
        """Zero-mean periodic antiderivative (spectral), of the signals at fs * upsample."""
        n = self.period * self.upsample
        spec = np.fft.rfft(x, axis=0)
        w = 2 * np.pi * np.fft.rfftfreq(n, self.h)
        spec[0] = 0
        spec[1:] = spec[1:] / (1j * w[1:]).reshape((-1,) + (1,) * (spec.ndim - 1))
        return np.fft.irfft(spec, n=n, axis=0)

    def derivative(self, x: np.ndarray, order: int) -> np.ndarray:
        """Spectral derivative of a signal at fs * upsample (periodic, exact for band-limited signals)."""
        n = self.period * self.upsample
        w = 2 * np.pi * np.fft.rfftfreq(n, self.h)
        return np.fft.irfft(np.fft.rfft(x) * (1j * w) ** order, n=n)

    kind = "periodic"

    def hysteresis_force(self, alpha: float, gamma: float, delta: float, passes: int = 3) -> np.ndarray:
        """z(t) per unit mass driven by the band-limited velocity, periodic steady state."""
        return _z_driven(np.ascontiguousarray(self.y1), alpha, gamma, delta, self.h, passes, True)

    def summary(self) -> dict:
        return {"kind": self.kind, "period": self.period, "periods_averaged": self.n_periods_used, "snr_db": self.snr_db,
                "bins_kept": int(self.kept.sum()), "noise_rms": self.noise_rms, "upsample": self.upsample,
                "highest_kept_hz": float(np.flatnonzero(self.kept).max() * self.fs / self.period)
                if self.kept.any() else 0.0}


def _record(u, y):
    """``u``, ``y`` as float arrays after the checks every single-level record needs: 1-D, equal
    length, finite."""
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    if u.shape != y.shape or u.ndim != 1:
        raise UserFacingError(f"single-level identification: input and output must be 1-D records of equal "
                              f"length, got {u.shape} and {y.shape}")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        raise UserFacingError("single-level identification: the record has non-finite samples")
    return u, y


def periodic_record(u, y, fs: float, period: int | None = None, skip_periods: int = 1,
                    upsample: int = 8, snr_db: float = SNR_DB_DEFAULT) -> PeriodicRecord:
    """Average the periods of a periodic record and build band-limited derivatives.

    ``skip_periods`` leading periods are dropped (start-up transient); at least
    two periods must remain so that the noise can be estimated.
    """
    u, y = _record(u, y)
    period = detect_period(u) if period is None else int(period)
    if period < 16 or u.size % period:
        raise UserFacingError(f"single-level identification: record of {u.size} samples is not a whole number "
                              f"of periods of {period} samples")
    total = u.size // period
    used = total - skip_periods
    if used < 2:
        raise UserFacingError(f"single-level identification: {total} period(s) recorded, {skip_periods} skipped "
                              "as transient; need at least 2 more to estimate the noise")
    yp = y.reshape(total, period)[skip_periods:]
    spec = np.fft.rfft(yp, axis=1)
    mean = spec.mean(axis=0)
    var_mean = spec.var(axis=0, ddof=1) / used
    tiny = np.finfo(float).tiny
    snr = np.abs(mean) ** 2 / np.maximum(var_mean, tiny)
    kept = snr > 10 ** (snr_db / 10)
    kept[0] = False  # the mean displacement carries no dynamics (and is not identifiable with k)
    # per-sample noise of one raw period: sum of bin variances (Parseval, one-sided spectrum)
    var_raw = spec.var(axis=0, ddof=1)
    weights = np.full(var_raw.size, 2.0)
    weights[0] = 1.0
    if period % 2 == 0:
        weights[-1] = 1.0
    noise_rms = float(np.sqrt(np.sum(weights * var_raw)) / period)
    n = period * upsample
    w = 2 * np.pi * np.fft.rfftfreq(n, 1.0 / (fs * upsample))
    up = np.zeros(n // 2 + 1, dtype=complex)
    up[: mean.size] = mean * kept * upsample
    y0, y1, y2 = (np.fft.irfft(up * (1j * w) ** q, n=n) for q in range(3))
    u_up = resampling.upsample_periodic(u[:period], upsample)
    return PeriodicRecord(fs=float(fs), period=period, n_periods_used=used, upsample=upsample, u=u[:period].copy(),
                          y=np.fft.irfft(mean, n=period), snr_db=snr_db, kept=kept, noise_rms=noise_rms,
                          u_up=u_up, y0=y0, y1=y1, y2=y2)


@dataclass
class TransientRecord:
    """A record that starts from rest and is not periodic (e.g. a sweep): time-domain signals.

    Derivatives come from the recon core's Savitzky-Golay differentiation with
    the window chosen from the data (recon.differentiation.choose_window); the
    signals are then interpolated ``upsample`` times (polyphase) so that
    products are formed without aliasing.  Integrals run from the first
    sample with zero initial value (the record starts from rest, so the
    integrated momentum equation needs no initial-condition terms).  The last
    ``tail`` samples at the recording rate are left out of every fit (edge
    effects of the filters).
    """

    fs: float
    upsample: int
    u: np.ndarray
    y: np.ndarray
    noise_rms: float
    window: int
    order: int
    tail: int = 32
    u_up: np.ndarray = field(repr=False, default=None)
    y0: np.ndarray = field(repr=False, default=None)
    y1: np.ndarray = field(repr=False, default=None)
    y2: np.ndarray = field(repr=False, default=None)
    y3: np.ndarray = field(repr=False, default=None)
    kind = "transient"
    n_periods_used = None

    @property
    def h(self) -> float:
        return 1.0 / (self.fs * self.upsample)

    def band_project(self, x: np.ndarray) -> np.ndarray:
        out = np.array(x, dtype=float, copy=True)
        out[out.shape[0] - self.tail * self.upsample:] = 0.0
        return out

    def integral(self, x: np.ndarray) -> np.ndarray:
        """Running integral from the first sample (trapezoid at the fine rate)."""
        x = np.asarray(x, dtype=float)
        out = np.zeros_like(x)
        out[1:] = np.cumsum(0.5 * (x[1:] + x[:-1]) * self.h, axis=0)
        return out

    def derivative(self, x: np.ndarray, order: int) -> np.ndarray:
        if order == 3 and x is self.y0:
            return self.y3
        out = np.asarray(x, dtype=float)
        for _ in range(order):
            out = np.gradient(out, self.h)
        return out

    def hysteresis_force(self, alpha: float, gamma: float, delta: float, passes: int = 1) -> np.ndarray:
        """z(t) per unit mass from z = 0 at the first sample, driven by the smoothed velocity."""
        return _z_driven(np.ascontiguousarray(self.y1), alpha, gamma, delta, self.h, 1, False)

    def summary(self) -> dict:
        return {"kind": self.kind, "samples": int(self.y.size), "noise_rms": self.noise_rms,
                "savgol_window": self.window, "savgol_order": self.order, "upsample": self.upsample}


def transient_record(u, y, fs: float, upsample: int = 8) -> TransientRecord:
    """Band-limited derivative signals of a record that starts from rest (see TransientRecord)."""

    u, y = _record(u, y)
    if y.size < 512:
        raise UserFacingError(f"single-level identification: {y.size} samples is too short a record")
    dt = 1.0 / fs
    # the velocity drives the hysteresis ODE sample by sample, so the pointwise-optimal filter for
    # the first derivative is used (a regression-optimal one passes too much noise into |y'|)
    choice = choose_window({"y": y}, dt, deriv=1, for_regression=False)
    ds = derivatives(y, dt, choice.window, choice.order, 3)
    ups = [resampling.upsample_polyphase(d, upsample) for d in ds]
    return TransientRecord(fs=float(fs), upsample=upsample, u=u.copy(), y=y.copy(),
                           noise_rms=float(choice.noise_level["y"]), window=choice.window, order=choice.order,
                           u_up=resampling.upsample_polyphase(u, upsample), y0=ups[0], y1=ups[1], y2=ups[2],
                           y3=ups[3])


@dataclass
class LinearStep:
    """Least squares ``y'' = b u - c y' - K y`` on the single level (biased by the hysteresis)."""

    b: float
    c: float
    K: float
    condition: float

    def to_dict(self) -> dict:
        return {"inv_m": self.b, "c_m": self.c, "K_m": self.K, "condition": self.condition}


def linear_step(rec: PeriodicRecord) -> LinearStep:
    cols = rec.band_project(np.column_stack([rec.u_up, -rec.y1, -rec.y0]))
    target = rec.band_project(rec.y2)
    scale = np.linalg.norm(cols, axis=0)
    sv = np.linalg.svd(cols / scale, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    if not np.isfinite(cond) or cond > 1e8:
        raise UserFacingError(f"single-level identification: linear regression is rank-deficient (condition "
                              f"{cond:.3g}); the excitation must contain several frequencies (multisine)")
    coef, *_ = np.linalg.lstsq(cols / scale, target, rcond=None)
    b, c, K = coef / scale
    return LinearStep(b=float(b), c=float(c), K=float(K), condition=cond)


@dataclass
class AgentStep:
    """The paper's agent-model step (recon core) run on the single level, iterated with its linear refit."""

    params: NewmarkParameters
    lam: float
    fn: dict
    iterations: list          # per iteration: {inv_m, c_m, K_m, lambda, alpha_m, gamma, delta, fn_m}
    error: str | None = None  # why it failed, if it did

    def to_dict(self) -> dict:
        d = self.params.to_benchmark() if self.error is None else {}
        d.update(lam=self.lam, fn_m=self.fn, iterations=len(self.iterations), error=self.error)
        return d


def agent_model_step(rec: PeriodicRecord, lin: LinearStep, library_order: int = 3,
                     iterations: int = 4) -> AgentStep:
    """Agent-model sparse regression (recon.library.agent/optimizers/hysteresis) on the single level.

    Starts from the biased linear step; each iteration builds Fn and Fn' with
    the current (1/m, c/m, K/m), selects the library terms (GroupedSparseSelector),
    extracts lambda and alpha, refits the pattern jointly with (c/m, K/m, 1/m)
    (recon.steps.bouc_wen.refit with fit_linear: the linear part re-estimated with
    the hysteresis accounted for), then estimates delta from the h = 0 samples.
    Signals are the band-limited periodic ones at fs * upsample, with the third
    derivative taken spectrally.
    """

    y0, y1, y2 = rec.y0, rec.y1, rec.y2
    y3 = rec.derivative(y0, 3)
    u0 = rec.u_up
    u1 = rec.derivative(u0, 1)
    g, c, K = lin.b, lin.c, lin.K
    h = cluster(y0, y1)
    lib = AgentLibrary(library_order, "joint")
    groups, core = lib.groups()
    mask = lib.rows(h)
    sig = h[mask].astype(float)
    history = []
    hp = None
    try:
        for _ in range(iterations):
            Fn = g * u0 - y2 - c * y1 - K * y0
            dFn = g * u1 - y3 - c * y2 - K * y1
            theta, target = lib.build(y0, y1, y2, Fn, dFn, h)
            sp = GroupedSparseSelector(groups, core).fit(theta, target)
            hp = extract(lib, sp.coef, sp.stderr, sp.support)
            hp, c, K, g = refit(hp, y0[mask], y1[mask], y2[mask], y3[mask], u0[mask], u1[mask], sig, c, K, g,
                                fit_g=True, fit_linear=True)
            Fn = g * u0 - y2 - c * y1 - K * y0
            dFn = g * u1 - y3 - c * y2 - K * y1
            hp = estimate_delta(hp, y0, y1, y2, Fn, dFn, h)
            history.append({"inv_m": g, "c_m": c, "K_m": K, "lambda": hp.lam, "alpha_m": hp.alpha,
                            "gamma": hp.gamma, "delta": hp.delta, "fn_m": dict(hp.fn)})
    except UserFacingError as exc:
        if hp is None or not history:
            nan = float("nan")
            return AgentStep(params=NewmarkParameters(nan, nan, nan, nan, nan, nan), lam=nan, fn={},
                             iterations=history, error=str(exc))
    last = history[-1]
    params = NewmarkParameters(c=last["c_m"], k=last["K_m"] - last["alpha_m"], alpha=last["alpha_m"],
                               gamma=last["gamma"], delta=last["delta"], b=last["inv_m"],
                               fn=tuple(sorted(last["fn_m"].items())))
    return AgentStep(params=params, lam=last["lambda"], fn=last["fn_m"], iterations=history)


@njit(cache=True)
def _z_driven(v, alpha, gamma, delta, h, passes, periodic):
    """Integrate z' = alpha v - gamma |v| z - delta v |z| (Heun) driven by the sampled velocity ``v``.

    periodic: ``passes`` sweeps over the record with wrap-around, the last one returned (steady state);
    otherwise one sweep from z = 0 at the first sample (a record that starts from rest).
    """
    n = v.size
    z = 0.0
    out = np.empty(n)
    if not periodic:
        passes = 1
    for _ in range(passes):
        for i in range(n):
            out[i] = z
            v0 = v[i]
            if i + 1 < n:
                v1 = v[i + 1]
            elif periodic:
                v1 = v[0]
            else:
                v1 = v0
            f0 = alpha * v0 - gamma * abs(v0) * z - delta * v0 * abs(z)
            zp = z + h * f0
            f1 = alpha * v1 - gamma * abs(v1) * zp - delta * v1 * abs(zp)
            z = z + 0.5 * h * (f0 + f1)
    return out


@dataclass
class HysteresisStep:
    """Parameters from the hysteresis-aware re-estimation (per unit mass)."""

    params: NewmarkParameters
    equation_rms: float       # rms residual of the integrated momentum equation [m/s]
    nfev: int
    starts: int

    def to_dict(self) -> dict:
        d = self.params.to_benchmark()
        d.update(equation_rms=self.equation_rms, nfev=self.nfev, starts=self.starts)
        return d


def hysteresis_step(rec: PeriodicRecord, lin: LinearStep, fn_terms=(), passes: int = 3,
                    extra_starts=()) -> HysteresisStep:
    """Variable projection: (alpha, gamma, delta) outer, (b, c, k, fn) inner least squares.

    ``extra_starts``: further (alpha/m, gamma, delta) starting points (e.g. the
    agent-model step's estimate), tried before the built-in ones.
    """
    names = list(fn_terms)
    pe, re = monomials.exponents(names) if names else (np.zeros(0, int), np.zeros(0, int))
    # rows of the (smooth, integrated) equation: every fine sample for a periodic record (its band
    # projection needs the full grid); every upsample-th for a transient one (same information, 8x faster)
    rows = slice(None) if rec.kind == "periodic" else slice(None, None, rec.upsample)
    target = rec.band_project(rec.y1)[rows]
    cols = [rec.integral(rec.u_up), -rec.y0, -rec.integral(rec.y0)]
    cols += [-rec.integral(rec.y0 ** p * rec.y1 ** r) for p, r in zip(pe, re)]
    A = rec.band_project(np.column_stack(cols))[rows]
    scale = np.linalg.norm(A, axis=0)
    An = A / scale

    def inner(nl):
        z = rec.hysteresis_force(nl[0], nl[1], nl[2], passes)
        rhs = target + rec.band_project(rec.integral(z))[rows]
        coef, *_ = np.linalg.lstsq(An, rhs, rcond=None)
        return coef / scale, rhs - An @ (coef)

    y_rms = float(np.sqrt(np.mean(rec.y0 ** 2))) or 1.0
    # Starting points: alpha a share of the (biased) linear stiffness; gamma, delta of the size that makes
    # the hysteresis saturate within the response amplitude (|gamma z| ~ alpha).  Both sign patterns of
    # delta are tried; the smallest equation error wins (the step is cheap: ~1 s per start).
    g0 = 0.5 / y_rms
    starts = [np.asarray(x, dtype=float) for x in extra_starts
              if np.all(np.isfinite(x)) and np.all(np.asarray(x) != 0) and x[0] > 0]
    starts += [np.array([0.5 * lin.K, g0, -g0]), np.array([0.5 * lin.K, g0, 0.5 * g0]),
              np.array([0.8 * lin.K, 2 * g0, -2 * g0])]
    def solve(x0, max_nfev):
        sol = least_squares(lambda x: inner(x0 * (1.0 + x))[1], np.zeros(3), diff_step=FD_STEP, xtol=1e-12,
                            ftol=1e-12, max_nfev=max_nfev)
        return sol, x0 * (1.0 + sol.x)

    # a short run from every start, then the most promising one to convergence
    best = None
    nfev = 0
    for x0 in starts:
        sol, nl = solve(x0, 20)
        nfev += sol.nfev
        if np.all(np.isfinite(sol.fun)) and (best is None or sol.cost < best[0]):
            best = (sol.cost, nl)
    if best is None:
        raise UserFacingError("single-level identification: the hysteresis step failed from every start")
    sol, nl = solve(best[1], 300)
    nfev += sol.nfev
    fun = sol.fun
    coef, _ = inner(nl)
    b, c, k = coef[:3]
    fn = tuple((name, float(a)) for name, a in zip(names, coef[3:]))
    params = NewmarkParameters(c=float(c), k=float(k), alpha=float(nl[0]), gamma=float(nl[1]),
                               delta=float(nl[2]), b=float(b), fn=fn)
    return HysteresisStep(params=params, equation_rms=float(np.sqrt(np.mean(fun ** 2))), nfev=nfev,
                          starts=len(starts))


def select_fn_terms(rec: PeriodicRecord, hyst: HysteresisStep, order: int = 3, passes: int = 3) -> list[str]:
    """Candidate static terms fn for the current hysteresis, by sparse regression (recon.regression.sparse.AutoSTLSQ).

    With z fixed at the hysteresis step's estimate, the integrated momentum
    equation is linear in (1/m, c, k) and in every fn coefficient; the
    automatic-threshold STLSQ (the linear columns forced in) proposes terms.
    Only used when the refined model does not explain the record down to the
    noise (see :func:`identify`), because equation-error selection on
    band-limited, densely sampled signals tends to keep small spurious terms.
    """

    p = hyst.params
    z = rec.hysteresis_force(p.alpha, p.gamma, p.delta, passes)
    target = rec.band_project(rec.y1 + rec.integral(z))
    terms = monomials.up_to(order)
    cols = [rec.integral(rec.u_up), -rec.y0, -rec.integral(rec.y0)]
    cols += [-rec.integral(rec.y0 ** a * rec.y1 ** b) for a, b in terms]
    fit = AutoSTLSQ(forced=(0, 1, 2)).fit(rec.band_project(np.column_stack(cols)), target)
    return [monomials.name(*t) for t, keep in zip(terms, fit.support[3:]) if keep]


@dataclass
class SingleLevelResult:
    record: PeriodicRecord
    linear: LinearStep
    agent: AgentStep | None
    hysteresis: HysteresisStep
    refined: object | None = None   # recon.output_error.newmark_refine.OutputErrorResult
    adequacy: dict = field(default_factory=dict)

    @property
    def params(self) -> NewmarkParameters:
        return self.refined.params if self.refined is not None else self.hysteresis.params

    def to_model(self):
        """The identified model as a recon.model.HystereticModel (force excitation, per unit mass)."""

        p = self.params
        return HystereticModel(excitation="force", c_m=p.c, k_m=p.k, alpha_m=p.alpha, gamma=p.gamma,
                               delta=p.delta, fn_m=dict(p.fn), inv_m=p.b,
                               provenance={"method": "single-level identification (recon.benchmark.single_level)",
                                           "software": f"shakerlab {__version__}", "steps": self.to_dict()})

    def to_dict(self) -> dict:
        out = {"record": self.record.summary(), "linear_step": self.linear.to_dict(),
               "agent_model_step": self.agent.to_dict() if self.agent is not None else None,
               "hysteresis_step": self.hysteresis.to_dict(), "adequacy": self.adequacy}
        if self.refined is not None:
            d = self.refined.params.to_benchmark()
            d.update(fn_m=dict(self.refined.params.fn), rms_initial=self.refined.rms_initial,
                     rms_final=self.refined.rms_final, nfev=self.refined.nfev,
                     relative_std=self.refined.relative_std)
            out["output_error"] = d
        return out


def _adequacy(rec: PeriodicRecord, refined, n_samples: int) -> dict:
    """Is the output-error residual at the noise level estimated from the period-to-period scatter?"""
    ratio = (refined.rms_final / rec.noise_rms) ** 2
    # sampling spread of the ratio under "residual = noise": residual variance over n_samples, noise
    # variance estimated with (periods used - 1) * period degrees of freedom
    if rec.kind == "periodic":
        tol = 3.0 * np.sqrt(2.0 / n_samples + 2.0 / ((rec.n_periods_used - 1) * rec.period))
    else:  # noise from the spectrum's floor (recon.differentiation): allow 10 % for that estimate
        tol = 3.0 * np.sqrt(2.0 / n_samples) + 0.1
    return {"residual_rms": refined.rms_final, "noise_rms": rec.noise_rms, "variance_ratio": float(ratio),
            "tolerance": float(tol), "adequate": bool(ratio < 1.0 + tol)}


def identify(u, y, fs: float, period: int | None = None, refine: bool = True, upsample_sim: int = 20,
             fn_terms="auto", snr_db: float = SNR_DB_DEFAULT, agent: bool = True) -> SingleLevelResult:
    """Identify the force-excited SDOF Bouc-Wen model from one record at one excitation level.

    A record of three or more identical input periods (or ``period`` given) is
    handled as periodic (averaging, spectral derivatives); any other record is
    handled in the time domain (:class:`TransientRecord`) and must start from
    rest.

    Steps: periodic preprocessing, linear step, agent-model step (``agent``;
    reported, and its estimate is the first start of the next step),
    hysteresis-aware variable projection, output-error refinement (``refine``).
    ``fn_terms``: static monomials to include (e.g. ``("y^3",)``), or
    ``"auto"``: none unless the refined model leaves more than noise in the
    residual, in which case terms proposed by sparse regression are added and
    kept if the residual drops significantly.

    The record must start from rest (zero state) if ``refine`` is on: the
    output-error step simulates all of it from zero initial conditions with
    the input upsampled ``upsample_sim`` times (the benchmark's chain).
    """
    auto = isinstance(fn_terms, str)
    if auto and fn_terms != "auto":
        raise UserFacingError(f"single-level identification: fn_terms must be 'auto' or a list of monomials, "
                              f"got {fn_terms!r}")
    terms = () if auto else tuple(fn_terms)
    if period is None:
        try:
            period = detect_period(u, min_periods=3)
        except UserFacingError:
            period = None
    periodic = period is not None
    rec = periodic_record(u, y, fs, period=period, snr_db=snr_db) if periodic else transient_record(u, y, fs)
    lin = linear_step(rec)
    ag = agent_model_step(rec, lin) if agent else None
    extra = []
    if ag is not None and ag.error is None:
        extra.append((ag.params.alpha, ag.params.gamma, ag.params.delta))
    hyst = hysteresis_step(rec, lin, fn_terms=terms, extra_starts=extra)
    refined = None
    adequacy = {}
    if refine:

        def run_oe(h):
            return oe_refine(h.params, u, y, fs, periodic=periodic, upsample=upsample_sim, n_warmup_periods=0)

        refined = run_oe(hyst)
        adequacy = _adequacy(rec, refined, len(y))
        if auto and not adequacy["adequate"]:
            candidates = select_fn_terms(rec, hyst)
            adequacy["fn_candidates"] = candidates
            if candidates:
                hyst2 = hysteresis_step(rec, lin, fn_terms=candidates, extra_starts=extra)
                refined2 = run_oe(hyst2)
                adeq2 = _adequacy(rec, refined2, len(y))
                if adeq2["variance_ratio"] < adequacy["variance_ratio"] - adequacy["tolerance"]:
                    hyst, refined, adequacy = hyst2, refined2, dict(adeq2, fn_candidates=candidates)
                    # drop the terms the refined fit cannot tell from zero (under 3 standard errors)
                    weak = [n for n in candidates if refined.relative_std.get(f"fn:{n}", 0.0) > 1.0 / 3.0]
                    if weak:
                        kept = [n for n in candidates if n not in weak]
                        hyst3 = hysteresis_step(rec, lin, fn_terms=kept, extra_starts=extra)
                        refined3 = run_oe(hyst3)
                        adeq3 = _adequacy(rec, refined3, len(y))
                        if adeq3["variance_ratio"] < adequacy["variance_ratio"] + adequacy["tolerance"]:
                            hyst, refined = hyst3, refined3
                            adequacy = dict(adeq3, fn_candidates=candidates, fn_dropped=weak)
    return SingleLevelResult(record=rec, linear=lin, agent=ag, hysteresis=hyst, refined=refined,
                             adequacy=adequacy)

"""Weak (integral) form of the agent-model regression: no derivative beyond y'.

The pointwise regression needs y''' (in Fn') and y'' (in the columns). Here every
equation is multiplied by a smooth test function psi with compact support and
integrated; integration by parts moves the derivatives onto psi:

    int psi Fn'       = -int psi' Fn
    int psi' y''      =  int psi''' y          (and likewise for any displacement)
    int psi y' y''    = -1/2 int psi' y'^2
    int psi y' y^p    = -1/(p+1) int psi' y^(p+1)
    int psi s phi_j'  = -s int psi' phi_j      (s is constant inside the support)

Only the products of y' with an *input* acceleration (u = -x_base'' under base
excitation, the other masses' accelerations in a chain) keep a second derivative,
of the input channel only, taken from a Savitzky-Golay filter. Everything linear
in the recorded displacements is integrated against psi'', psi''' from the raw
samples, so the differentiation bias of the pointwise form disappears, constant
noise biases (e.g. E[n'^2]) integrate to zero against psi', and the remaining
noise is averaged over the support.

Test functions: psi(t) = (1 - x^2)^P, x in [-1, 1] over the support, P = 3
(EstimatorTuning.weak_bump_power; the weak form's numbers are EstimatorTuning's weak_* fields). Its
derivatives are not the analytic ones: psi^(d) is the d-fold 6th-order central
finite difference of the sampled, zero-padded psi, so summation by parts is exact
on the samples (the rows are psi-weighted sums of finite-difference derivatives).
With analytic derivatives the rectangle rule on psi''' D left a 7 % residual on
noise-free data with the true coefficients at P = 5 (5e-6 at P = 12, but a large P
narrows the bump and raises its noise gain); the discrete form leaves ~1e-10 at any P.
In the nonlinear step a support lies inside one AB or CD segment (a contiguous run
of h = +1 or h = -1), where s is constant: the whole segment and its first and last
two thirds. The delta step uses the h = 0 segments the same way. The linear step
tiles the whole stage.

In the SDOF estimator (:func:`reconstruct_weak`) this segment regression gives the
pilot: the fn pattern and lambda. The structured refit and delta are then taken from the
weak form along the hysteresis path (recon/weak_path.py), whose half-period test functions
need only psi'' and no sign of z. At 40 dB the segment refit can run far from alpha (more than
twice it) where the path form stays within a few per cent with the right pattern.

A layer is described generically (SDOF base/force and every layer of a chain):

    Fn = g F - D'' - c y' - K y,      D = y + R

``D`` is a linear combination of recorded displacements (x_tip for base
excitation, x for force excitation, x_i + sum_j (m_j/m_i) x_j in a chain), ``F`` a
force (zero under base excitation) and ``R'' = D'' - y''`` the part of the
acceleration that is not the layer's own (x_base'', other masses).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse

from recon.differentiation import estimate_spectrum, savgol_coeffs
from recon.estimator.tuning import DEFAULT_TUNING, EstimatorTuning
from recon.library import monomials
from recon.library.agent import AgentLibrary, phi
from recon.regression.sparse import GroupedSparseSelector
from recon.signals import stage_signals
from recon.steps.bouc_wen import HysteresisParams, extract, fn_values, project_lambda
from recon.steps.linear import LinearFit, fit_linear
from shakerlab.errors import EstimateRefused, UserFacingError
from shakerlab.run_data import BASE, FORCE

DISCRETE = True
# 6th-order central first-derivative stencil (x[i-3] .. x[i+3])
FD_STENCIL = np.array([-1.0 / 60, 3.0 / 20, -3.0 / 4, 0.0, 3.0 / 4, -3.0 / 20, 1.0 / 60])


# ------------------------------------------------------------------ test functions
def bump(n: int, dt: float, power: int = 9) -> list[np.ndarray]:
    """psi, psi', psi'', psi''' sampled on n points spanning the support (ends included)."""
    P = np.polynomial.polynomial
    c = P.polypow([1.0, 0.0, -1.0], power)
    x = np.linspace(-1.0, 1.0, n)
    scale = 2.0 / ((n - 1) * dt)
    out = []
    for d in range(4):
        out.append(P.polyval(x, c) * scale ** d)
        c = P.polyder(c)
    return out


@functools.lru_cache(maxsize=64)
def _discrete_bump(n: int, dt: float, power: int, pad: int) -> tuple:
    """psi on n points zero-padded by ``pad`` on each side, and its 1-3 fold 6th-order central
    differences (TestFunctions.build, discrete). The windows of one build mostly share a length:
    made once per length (read-only arrays)."""
    psi = np.zeros(n + 2 * pad)
    psi[pad:pad + n] = bump(n, dt, power)[0]
    ds = [psi]
    for _ in range(3):
        ds.append(np.convolve(ds[-1], FD_STENCIL[::-1] / dt, mode="same"))
    for a in ds:
        a.flags.writeable = False
    return tuple(ds)


@dataclass
class TestFunctions:
    """Rows of V_d (d = 0..3): int psi_k^(d) f dt = (V_d @ f)_k, one row per test function."""

    V: list
    sign: np.ndarray          # s of the segment holding each support (0 for tiled / h = 0 rows)
    segment: np.ndarray       # segment index of each row
    n_segments: int

    @classmethod
    def build(cls, windows: list, n_samples: int, dt: float, power: int,
              discrete: bool | None = None) -> "TestFunctions":
        """``windows``: (start, length, sign, segment) tuples; ``power``: P of the bump
        (1 - x^2)^P (EstimatorTuning.weak_bump_power).

        ``discrete`` (default: module DISCRETE): psi^(d) is the d-fold central finite
        difference (6th order) of the sampled psi, zero-padded. Summation by parts is then
        exact on the samples: sum psi (S^d D) = (-1)^d sum (S^d psi) D, so the weak rows are
        psi-weighted sums of finite-difference derivatives and carry no quadrature error."""
        discrete = DISCRETE if discrete is None else discrete
        pad = 3 * (FD_STENCIL.size // 2) if discrete else 0
        rows, cols, vals = [], [], [[], [], [], []]
        kept = []
        for a, n, sgn, seg in windows:
            if a - pad < 0 or a + n + pad > n_samples:
                continue
            k = len(kept)
            kept.append((a, n, sgn, seg))
            ds = _discrete_bump(n, dt, power, pad) if discrete else bump(n, dt, power)
            rows.append(np.full(n + 2 * pad, k))
            cols.append(np.arange(a - pad, a + n + pad))
            for d in range(4):
                vals[d].append(ds[d] * dt)
        if not kept:
            raise UserFacingError("weak form: no segment long enough to hold a test function")
        windows = kept
        r, c = np.concatenate(rows), np.concatenate(cols)
        V = [sparse.csr_matrix((np.concatenate(v), (r, c)), shape=(len(windows), n_samples)) for v in vals]
        seg = np.array([w[3] for w in windows])
        return cls(V=V, sign=np.array([w[2] for w in windows], float), segment=seg,
                   n_segments=int(np.unique(seg).size))

    def __len__(self) -> int:
        return self.sign.size


def runs(h: np.ndarray):
    """(start, length, value) of the maximal runs of constant h."""
    edges = np.flatnonzero(np.diff(h)) + 1
    starts = np.r_[0, edges]
    ends = np.r_[edges, h.size]
    return [(int(a), int(b - a), int(h[a])) for a, b in zip(starts, ends)]


def segment_windows(h: np.ndarray, min_len: int, values=(1, -1), sign_of=None) -> list:
    """Test-function supports inside the runs of h whose value is in ``values`` and that are at least
    ``min_len`` samples long (EstimatorTuning.weak_min_segment): the whole run plus, when it is long
    enough, its first and last two thirds."""
    out = []
    seg = 0
    for a, n, v in runs(h):
        if v not in values or n < min_len:
            continue
        s = float(v) if sign_of is None else float(sign_of(a, n))
        out.append((a, n, s, seg))
        if n >= 3 * min_len // 2 * 2:
            m = (2 * n) // 3
            out.append((a, m, s, seg))
            out.append((a + n - m, m, s, seg))
        seg += 1
    return out


def tiled_windows(n_samples: int, width: int, overlap: float) -> list:
    """Supports of ``width`` samples tiled over the stage, each advancing by 1/``overlap`` of the width
    (EstimatorTuning.weak_tile_overlap: each sample lies in that many rows)."""
    width = int(max(9, min(width, n_samples)))
    step = max(1, int(width // overlap))
    return [(a, width, 0.0, k) for k, a in enumerate(range(0, n_samples - width + 1, step))]


# ------------------------------------------------------------------ one layer
@dataclass
class WeakLayer:
    """Signals of one layer: Fn = g F - D'' - c y' - K y with D = y + R.

    y_raw, D_raw: recorded (noisy) displacement combinations, used in the integrals
    that are linear in them; y, dy: Savitzky-Golay smoothed y, y' for the products;
    Rdd: R'' (Savitzky-Golay); F: force (zeros under base excitation); y_noise: noise std of the
    smoothed y when a sensor measured velocity or acceleration (recon.signals' column noise;
    None: white displacement noise, :func:`smoothed_noise`)."""

    dt: float
    y_raw: np.ndarray
    D_raw: np.ndarray
    y: np.ndarray
    dy: np.ndarray
    Rdd: np.ndarray
    F: np.ndarray
    choice: dict = field(default_factory=dict)
    y_noise: float | None = None

    def kernel(self) -> np.ndarray:
        return np.sign(np.sign(self.y) + np.sign(self.dy)).astype(np.int8)


@dataclass
class WeakParts:
    """Integrated pieces of the nonlinear regression, linear in (c, K, g):

        target  = T0 + c Tc + K TK + g Tg            (= s int psi Fn')
        y' Fn   = P0 + c Pc + K PK + g Pg            (= int psi y' Fn)
    """

    T: tuple
    P: tuple
    Ca: dict        # (p, r) -> s int psi phi_j'
    Cl: dict        # (p, r) -> int psi y' phi_j
    Cyy: np.ndarray  # int psi y y'
    Clin: dict      # linear-correction columns: 's*ddy', 's*dy', 'dy^2'
    sign: np.ndarray

    def target(self, c, K, g):
        T0, Tc, TK, Tg = self.T
        return T0 + c * Tc + K * TK + g * Tg

    def yFn(self, c, K, g):
        P0, Pc, PK, Pg = self.P
        return P0 + c * Pc + K * PK + g * Pg


def weak_parts(L: WeakLayer, tf: TestFunctions, terms, Ddd=None) -> WeakParts:
    """``Ddd`` given: the target -s int psi' Fn uses the Savitzky-Golay D'' (one
    integration by parts, psi' only) instead of int psi''' D (fully weak)."""
    V0, V1, V2, V3 = tf.V
    s = tf.sign
    y, dy = L.y, L.dy
    if Ddd is None:
        T = (s * (V3 @ L.D_raw), -s * (V2 @ L.y_raw), s * (V1 @ L.y_raw), -s * (V1 @ L.F))
    else:
        T = (s * (V1 @ Ddd), s * (V1 @ dy), s * (V1 @ y), -s * (V1 @ L.F))
    P = (0.5 * (V1 @ (dy * dy)) - V0 @ (dy * L.Rdd), -(V0 @ (dy * dy)), 0.5 * (V1 @ (y * y)), V0 @ (dy * L.F))
    Ca, Cl = {}, {}
    for p, r in terms:
        Ca[(p, r)] = -s * (V1 @ phi(y, dy, p, r))
        if r == 0:
            Cl[(p, r)] = -(V1 @ y ** (p + 1)) / (p + 1)
        else:
            Cl[(p, r)] = V0 @ (dy * phi(y, dy, p, r))
    Cyy = -0.5 * (V1 @ (y * y))
    Clin = {"s*ddy": s * (V2 @ L.y_raw), "s*dy": -s * (V1 @ L.y_raw), "dy^2": V0 @ (dy * dy)}
    return WeakParts(T=T, P=P, Ca=Ca, Cl=Cl, Cyy=Cyy, Clin=Clin, sign=s)


def weak_theta(lib: AgentLibrary, parts: WeakParts, c, K, g):
    """(Theta, target) in the column order of the joint AgentLibrary."""
    cols = []
    for col in lib.columns:
        if col.role == "a":
            cols.append(parts.Ca[(col.p, col.r)])
        elif col.role == "lam_a":
            cols.append(parts.Cl[(col.p, col.r)])
        elif col.role == "lam_alpha":
            cols.append(parts.Cyy)
        elif col.role == "lam":
            cols.append(parts.yFn(c, K, g))
        elif col.role == "lin":
            cols.append(parts.Clin[{0: "s*ddy", 1: "s*dy", 2: "dy^2"}[col.r]])
        else:
            raise UserFacingError(f"weak form: library column role {col.role!r} is not supported")
    return np.column_stack(cols), parts.target(c, K, g)


def weak_refit(params: HysteresisParams, parts: WeakParts, c, K, g, fit_g: bool, fit_linear_terms: bool = True):
    """Structured refit on the weak equation, pattern fixed (variable projection on lambda):
        T + lam P = sum a_j (Ca_j + lam Cl_j) + b y y'          (b = -lam alpha)
    linear in (a_j, b[, c, K][, g]) for fixed lambda."""
    terms = [monomials.parse(k) for k in params.fn]
    T0, Tc, TK, Tg = parts.T
    P0, Pc, PK, Pg = parts.P

    def system(lam):
        cols = [parts.Ca[t] + lam * parts.Cl[t] for t in terms] + [parts.Cyy]
        rhs = T0 + lam * P0
        if fit_linear_terms:
            cols += [-(Tc + lam * Pc), -(TK + lam * PK)]
        else:
            rhs = rhs + c * (Tc + lam * Pc) + K * (TK + lam * PK)
        if fit_g:
            cols.append(-(Tg + lam * Pg))
        else:
            rhs = rhs + g * (Tg + lam * Pg)
        return np.column_stack(cols), rhs

    return project_lambda(params, system, c, K, g, fit_linear_terms, fit_g, alpha_sign=-1.0, relative=True,
                          form="weak")


def weak_delta(params: HysteresisParams, L: WeakLayer, h: np.ndarray, c, K, g, Ddd: np.ndarray,
               tuning: EstimatorTuning = DEFAULT_TUNING) -> HysteresisParams:
    """delta from the h = 0 segments (y and y' of opposite signs, sigma = sgn(y') constant):
        -int psi' (Fn - fn) + lam sigma int psi y' z = delta int psi (|y'| z - y' |z|)
    The left side is integrated by parts; the right needs z pointwise, built with the
    Savitzky-Golay D'' (second derivative only)."""
    sgn_dy = np.sign(L.dy)
    win = segment_windows(h, tuning.weak_min_segment, values=(0,),
                          sign_of=lambda a, n: np.sign(np.sum(sgn_dy[a:a + n])))
    if len(win) < 3:
        raise EstimateRefused("no segments where y' and z have opposite signs: delta cannot be identified "
                              "(the nonlinear stage must cycle through the whole loop)")
    tf = TestFunctions.build(win, L.y.size, L.dt, tuning.weak_bump_power)
    V0, V1, V2, V3 = tf.V
    sig = tf.sign
    y, dy = L.y, L.dy
    fnv = fn_values(params.fn, y, dy)
    # int psi' Fn
    iFn1 = g * (V1 @ L.F) - V3 @ L.D_raw + c * (V2 @ L.y_raw) - K * (V1 @ L.y_raw)
    # int psi y' Fn
    iyFn = 0.5 * (V1 @ (dy * dy)) - V0 @ (dy * L.Rdd) - c * (V0 @ (dy * dy)) + 0.5 * K * (V1 @ (y * y)) \
        + g * (V0 @ (dy * L.F))
    iyz = params.alpha * (-0.5 * (V1 @ (y * y))) + iyFn - V0 @ (dy * fnv)
    lhs = -(iFn1 - V1 @ fnv) + params.lam * sig * iyz
    z = params.alpha * y + g * L.F - Ddd - c * dy - K * y - fnv
    r = V0 @ (np.abs(dy) * z - dy * np.abs(z))
    rr = float(r @ r)
    if rr == 0:
        raise UserFacingError("delta: z never opposes y' in the h = 0 segments; the loop is not excited")
    delta = float(r @ lhs) / rr
    info = dict(params.info)
    info["delta_rows"] = int(len(tf))
    return HysteresisParams(lam=params.lam, alpha=params.alpha, fn=params.fn, delta=delta,
                            gamma=params.lam - delta, info=info)


@dataclass
class WeakLayerFit:
    params: HysteresisParams
    c_m: float
    K_m: float
    g: float
    sparse: dict
    library_names: list
    library_coef: list
    n_rows: int
    n_segments: int


def fit_layer(L: WeakLayer, lib: AgentLibrary, c, K, g, fit_g: bool, Ddd: np.ndarray, n_folds: int = 5,
              refit: bool = True, refit_linear: bool = True, stage_name: str = "nonlinear",
              tuning: EstimatorTuning = DEFAULT_TUNING) -> WeakLayerFit:
    """Sparse regression of the weak agent model, parameter extraction, refit, delta (``tuning``:
    the weak_* fields)."""
    h = L.kernel()
    tf = TestFunctions.build(segment_windows(h, tuning.weak_min_segment), L.y.size, L.dt, tuning.weak_bump_power)
    parts = weak_parts(L, tf, lib.terms)
    theta, target = weak_theta(lib, parts, c, K, g)
    if theta.shape[0] < 2 * theta.shape[1]:
        raise UserFacingError(f"stage {stage_name!r}: only {theta.shape[0]} weak-form rows (test functions in AB/CD "
                              f"segments) for {theta.shape[1]} library columns; record longer or lower --library-order")
    groups, core = lib.groups()
    corr = len(tf) / tf.n_segments          # rows of one segment overlap: one independent sample per segment
    sp = GroupedSparseSelector(groups, core, n_folds=n_folds, corr_len=corr).fit(theta, target)
    hp = extract(lib, sp.coef, sp.stderr, sp.support)
    if refit:
        hp, c, K, g = weak_refit(hp, parts, c, K, g, fit_g=fit_g, fit_linear_terms=refit_linear)
    hp = weak_delta(hp, L, h, c, K, g, Ddd, tuning)
    return WeakLayerFit(params=hp, c_m=c, K_m=K, g=g, sparse=sp.summary(), library_names=lib.names,
                        library_coef=[float(v) for v in sp.coef], n_rows=len(tf), n_segments=tf.n_segments)


def linear_weak(y_raw, D_raw, F, dt: float, width: int, fit_g: bool, noise: dict, stage_name: str = "linear",
                input_lines=None, tuning: EstimatorTuning = DEFAULT_TUNING) -> LinearFit:
    """Weak linear step: int psi'' D = g int psi F + c int psi' y - K int psi y, test functions
    tiled over the stage, solved by :func:`recon.steps.linear.fit_linear` (conditioning, refusal of a
    rank-deficient excitation, noise-aware rank decision) on the integrated columns (``tuning``: the
    weak_* fields)."""

    n = y_raw.size
    tf = TestFunctions.build(tiled_windows(n, width, tuning.weak_tile_overlap), n, dt, tuning.weak_bump_power)
    V0, V1, V2, _ = tf.V
    Y0 = V0 @ y_raw
    Y1 = -(V1 @ y_raw)            # int psi y'
    b = V2 @ D_raw               # int psi D''
    w = np.sqrt(np.sum(V0.multiply(V0), axis=1)).A.ravel().mean()
    w1 = np.sqrt(np.sum(V1.multiply(V1), axis=1)).A.ravel().mean()
    cn = {"y": noise.get("y", 0.0) * w, "dy": noise.get("y", 0.0) * w1, "u": noise.get("F", 0.0) * w}
    exc = FORCE if fit_g else BASE
    return fit_linear(Y0, Y1, b, V0 @ F if fit_g else np.zeros_like(b), exc, cn, stage_name, input_lines)


def linear_width(x: np.ndarray, dt: float) -> int:
    """Support of the linear-step test functions: about one period of the highest
    significant line (the bump passes it with little attenuation)."""

    sp = estimate_spectrum(x, dt)
    f = sp.bandwidth_hz if sp.bandwidth_hz > 0 else 1.0 / (x.size * dt / 20)
    return int(round(1.0 / (f * dt)))


# ------------------------------------------------------------------ SDOF estimator
def smoothed_noise(L: WeakLayer) -> float:
    """Noise std of the Savitzky-Golay smoothed y of a layer (the assumed white noise of the
    displacement channels times the filter's noise gain)."""

    if L.y_noise is not None:
        return L.y_noise
    c0 = savgol_coeffs(L.choice["window"], L.choice["order"])
    ny = np.sqrt(sum(v ** 2 for k, v in L.choice["noise_level"].items() if k != "force"))
    return float(ny * np.sqrt(c0 @ c0))


def sdof_layer(stage, window=None, order=None) -> tuple[WeakLayer, np.ndarray]:
    """The WeakLayer of an SDOF stage and the Savitzky-Golay D'' (recon.signals, untrimmed)."""

    sig = stage_signals(stage, deriv=2, window=window, order=order, for_regression=True, trim=False)
    y, dy, ddy = sig.y
    y_noise = sig.column_noise["y"] if "quantities" in sig.choice else None
    if stage.excitation == BASE:
        xb, xt = stage.channels["x_base"], stage.channels["x_tip"]
        rdd = -sig.u[0]                     # the base acceleration
        L = WeakLayer(dt=stage.dt, y_raw=xt - xb, D_raw=xt, y=y, dy=dy, Rdd=rdd, F=np.zeros_like(xt),
                      choice=sig.choice, y_noise=y_noise)
        return L, ddy + rdd
    x, f = stage.channels["x"], stage.channels["force"]
    L = WeakLayer(dt=stage.dt, y_raw=x, D_raw=x, y=y, dy=dy, Rdd=np.zeros_like(x), F=f, choice=sig.choice,
                  y_noise=y_noise)
    return L, ddy

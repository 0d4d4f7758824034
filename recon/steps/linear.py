"""The linear step: y'' = -c_m y' - K_m y + g u on the small-amplitude stage.

Base excitation fixes g = 1 (u = -x_base'', so y'' - u = x_tip''); force
excitation identifies g = inv_m = 1/m as well. The regression matrix is
column-normalised; its condition number is reported, and a matrix whose
smallest singular value is buried in the noise of its own columns is refused
(e.g. one pure tone under force excitation: y, y' and u span only sin and cos
at one frequency, three columns for two directions).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from shakerlab.errors import EstimateRefused, UserFacingError
from shakerlab.run_data import BASE


class NoisyLinearStage(EstimateRefused):
    """The linear stage's regression columns carry so much noise, judged by the stage's own noise level,
    that c and K are not determined there, although the excitation is not rank-deficient: another stage
    with less noise against its motion can give them (:func:`recon.estimator.linear_start.linear_step`)."""

    def __init__(self, message: str, stage: str, noise: float):
        super().__init__(message)
        self.stage, self.noise = stage, float(noise)


@dataclass
class LinearFit:
    c_m: float
    K_m: float
    inv_m: float | None
    condition_number: float
    singular_values: list
    noise_floor: float          # relative column perturbation expected from noise
    r2: float
    input_lines: int | None = None
    warnings: list = field(default_factory=list)    # plausibility: see :func:`plausibility_warnings`
    # the constant b of the input, y'' = -c_m y' - K_m y + g (u - b), when fitted (``offset=True``)
    offset: float | None = None
    # the stage the fit was made on when it is not the linear stage (recon.estimator.linear_start)
    stage: str | None = None

    def __post_init__(self):
        self.warnings = list(self.warnings) + [w for w in plausibility_warnings(self.c_m, self.K_m)
                                               if w not in self.warnings]

    def to_dict(self) -> dict:
        return asdict(self)


def plausibility_warnings(c_m: float, K_m: float) -> list[str]:
    """A passive specimen has positive damping and stiffness. Negative ones fit a response that moves
    against its input, as when the base and tip channels are exchanged (y = x_base - x_tip)."""
    bad = [f"{name} = {v:.4g}" for name, v in (("c_m", c_m), ("K_m", K_m)) if v < 0]
    if not bad:
        return []
    return [f"linear step: negative {' and '.join(bad)} (a passive specimen has positive damping and "
            f"stiffness): are base and tip swapped?"]


def count_lines(freqs: np.ndarray, df: float, power: np.ndarray | None = None) -> int:
    """Number of distinct spectral lines among the significant bins ``freqs`` (bin spacing ``df``).

    With ``power`` (the bins' power, :func:`recon.differentiation.estimate_spectrum`): the peaks
    of the log power that stand 10 dB above the valleys on both sides (``scipy.signal.find_peaks``
    prominence 1 decade; across bins that are not significant the log power is interpolated, so
    a stray bin in a line's skirt is no line; peaks below 3 cycles per record are the trend's
    leakage, not a line). A line's leakage decays monotonically from its peak, so its skirts add
    no peak however far they reach above the noise: a leaky 9-line multisine is 9 lines at any
    SNR, where the first rule (bins closer than 4 df merge, still used without ``power``) chained
    the lines whose skirts touch into 1-3 (tests/test_recon_lines.py). Measured: lines 5 bins
    apart or more are counted exactly at 40-120 dB; 3 bins apart they merge in part. A broadband
    input counts its bins within 10 dB of the strongest, one line per 4 bins (a 5-30 Hz chirp over
    10 s: 38 at 40-80 dB; the first rule said 1-2, a single tone)."""
    if freqs.size == 0:
        return 0
    if power is None:
        return int(1 + np.count_nonzero(np.diff(np.sort(freqs)) > 4 * df))
    k = np.round(np.asarray(freqs, float) / df).astype(np.int64)
    order = np.argsort(k)
    k, p = k[order], np.log10(np.maximum(np.asarray(power, float)[order], 1e-300))
    grid = np.arange(k[0] - 1, k[-1] + 2)
    dense = np.interp(grid, k, p)
    dense[0], dense[-1] = p[0] - 1.0, p[-1] - 1.0          # a valley beyond each end
    from scipy.signal import find_peaks  # heavy: scipy.signal costs ~0.4 CPU-s to import; only this path needs it
    peaks, _ = find_peaks(dense, prominence=1.0)
    # a broadband input (a chirp, noise) has no peaks but many independent lines: its bins within
    # 10 dB of the strongest, per Hann main lobe (4 bins)
    band = int(np.count_nonzero(p >= p.max() - 1.0)) // 4
    return max(int(np.count_nonzero(grid[peaks] >= 3)), band, 1)


def fit_linear(y, dy, ddy, u, excitation: str, column_noise: dict | None = None,
               stage_name: str = "linear", input_lines: int | None = None, offset: bool = False) -> LinearFit:
    """Least squares for (c_m, K_m[, inv_m][, offset]).

    ``column_noise`` maps 'y', 'dy', 'u' to the expected rms error of that
    column (from the differentiation choice) used for the rank decision.
    ``offset``: fit the input's constant b as well (a constant force holds the stage off centre,
    :mod:`recon.estimator.input_offset`). Without it the constant projects onto the mean of y and
    biases K_m: a constant force that holds the linear stage off centre by more than its rms motion
    can put K_m at several times the truth.
    """
    if excitation == BASE:
        A = np.column_stack([-dy, -y])
        b = ddy - u
        names = ["dy", "y"]
    else:
        A = np.column_stack([-dy, -y, u])
        b = ddy
        names = ["dy", "y", "u"]
    if offset:
        # the constant (-g b) is fitted by centring every column: the rank test and c, K then see
        # the motion about its mean, not the mean itself (a DC can be many times the motion)
        A_mean, b_mean = A.mean(axis=0), float(b.mean())
        A, b = A - A_mean, b - b_mean
    norms = np.sqrt(np.sum(A * A, axis=0))
    if np.any(norms == 0):
        raise UserFacingError(f"stage {stage_name!r}: the linear regression has an all-zero column (no motion?)")
    An = A / norms
    sv = np.linalg.svd(An, compute_uv=False)
    cond = float(sv[0] / sv[-1])
    rms = norms / np.sqrt(A.shape[0])
    cn = column_noise or {}
    eps = max([cn.get(nm, 0.0) / r for nm, r in zip(names, rms)] + [1e-9])
    # a direction weaker than a few times the noise in the columns is not determined
    # a single-line input must rely on the response's own (transient) content: demand a
    # well-conditioned matrix then (a steady single tone gives cond ~ 1e3 from harmonics alone)
    single_tone = excitation != BASE and input_lines is not None and input_lines < 2 and cond > 100
    if sv[-1] / sv[0] < 10 * eps or cond > 1e8 or single_tone:
        figures = (f"condition number {cond:.3g}, smallest singular value {sv[-1] / sv[0]:.2g} of the largest, "
                   f"column noise level {eps:.2g}, input lines {input_lines}")
        few_lines = excitation != BASE and input_lines is not None and input_lines <= 2
        if single_tone or few_lines:     # a tone and its harmonic: the tone explains the weak direction
            why = ("under force excitation a single tone leaves 1/m, c/m and K/m undetermined: "
                   "use a sweep, a multisine, or keep the start-up transient")
        elif cond > 1e8:
            why = ("the columns y, y'" + (", u" if excitation != BASE else "") + " are linearly dependent: "
                   + ("excite with a non-zero tone" if excitation == BASE else "the input does not move the structure "
                      "independently of its response (check the force channel)"))
        else:
            # not a rank deficiency: the columns span their directions, but the weakest is within 10 times
            # the noise they carry, so the regression on noisy columns (errors in variables) does not
            # determine c and K on this stage; a stage with less noise against its motion can
            raise NoisyLinearStage(
                f"stage {stage_name!r}: the linear step cannot determine c and K: the stage is too noisy (the "
                f"noise its columns carry is {eps:.2g} of their rms, about {-20 * np.log10(max(eps, 1e-12)):.0f} dB, "
                f"and buries their weakest direction, {sv[-1] / sv[0]:.2g} of the largest; condition number "
                f"{cond:.3g}, input lines {input_lines}): the motion of this stage is too small against the sensor "
                f"noise, or the noise "
                f"estimate is off (averaged or band-limited records): record a larger linear stage",
                stage_name, eps)
        raise UserFacingError(f"stage {stage_name!r}: the linear step cannot determine c and K, the excitation is "
                              f"rank-deficient ({figures}): {why}")
    x, *_ = np.linalg.lstsq(An, b, rcond=None)
    x = x / norms
    res = b - A @ x
    r2 = 1.0 - float(res @ res) / float(np.sum((b - b.mean()) ** 2))
    inv_m = None if excitation == BASE else float(x[2])
    b_in = None
    if offset:
        g_b = float(A_mean @ x) - b_mean          # ddy - u = A x - g b about the means
        b_in = g_b if inv_m is None else (g_b / inv_m if inv_m else float("nan"))
    return LinearFit(c_m=float(x[0]), K_m=float(x[1]), inv_m=inv_m,
                     condition_number=cond, singular_values=[float(s) for s in sv],
                     noise_floor=float(eps), r2=r2, input_lines=input_lines, offset=b_in)

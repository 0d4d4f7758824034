"""Sequentially thresholded least squares with an automatically chosen threshold.

Columns are normalised to unit norm and the target too, so a coefficient's
magnitude is the fraction of the target it explains; the threshold tau acts on
that scale. tau is scanned over a log grid; each candidate is scored by
K-fold cross-validation on interleaved blocks of samples (held-out residual).
Among the candidates the sparsest model whose held-out error is within one
standard error of the best one is chosen (the "one-standard-error" rule),
which is the knee of the error-vs-complexity Pareto front without a tuning
constant. All folds share Gram matrices, so the scan costs microseconds per
candidate after one pass over the data: each fold is compressed once by a QR
factorisation (A_f = Q_f R_f), training on the other folds is least squares on
their stacked R_f (exact, no squared condition number), and the held-out
residual is ||Q_f^T b_f - R_f x||^2 plus the part of b_f outside range(A_f).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import linalg


def scaled_lstsq(A, b):
    """Least squares of ``A x = b`` with the columns scaled to unit norm (zero columns left as
    they are); returns ``(x, rss)`` in the original column units."""
    if not np.all(np.isfinite(A)):
        # LAPACK would print "DLASCL parameter number 4 had an illegal value" on the terminal and
        # then raise this same error (a trial whose hysteresis column overflowed, as in the weak
        # path's (gamma, delta) search); raised here, without the message, and before the
        # scaling below would warn of an inf / inf
        raise np.linalg.LinAlgError("least squares: the design matrix holds non-finite values "
                                    "(a trial whose columns overflowed)")
    sc = np.sqrt(np.sum(A * A, axis=0))
    sc[sc == 0] = 1.0
    As = A / sc
    x, *_ = np.linalg.lstsq(As, b, rcond=None)
    r = b - As @ x
    return x / sc, float(r @ r)


def _solve(R, d, support):
    """Least squares on the compressed system R x = d restricted to ``support``."""
    idx = np.flatnonzero(support)
    x = np.zeros(R.shape[1])
    if idx.size:
        x[idx] = linalg.lstsq(R[:, idx], d, cond=None, lapack_driver="gelsd")[0]
    return x


def stlsq(R, d, tau, forced=None, max_iter=25):
    """STLSQ on a (QR-compressed) system; columns already normalised."""
    forced = np.zeros(R.shape[1], bool) if forced is None else forced
    support = np.ones(R.shape[1], bool)
    x = _solve(R, d, support)
    for _ in range(max_iter):
        new = support & ((np.abs(x) >= tau) | forced)
        if np.array_equal(new, support):
            break
        support = new
        x = _solve(R, d, support)
    return x, support


@dataclass
class SparseFit:
    coef: np.ndarray            # in the original column scaling
    support: np.ndarray
    threshold: float            # on the normalised scale (fraction of the target)
    thresholds: np.ndarray = field(repr=False, default=None)
    cv_error: np.ndarray = field(repr=False, default=None)
    cv_se: np.ndarray = field(repr=False, default=None)      # BIC for the grouped selector
    n_terms: np.ndarray = field(repr=False, default=None)
    rel_residual: float = 0.0
    stderr: np.ndarray = field(repr=False, default=None)   # standard error of coef (original scaling)
    origin: str = "stlsq"        # which candidate path produced the chosen support

    def summary(self) -> dict:
        return {"threshold": float(self.threshold), "n_terms": int(self.support.sum()), "support_from": self.origin,
                "rel_residual": float(self.rel_residual),
                "scan": {"thresholds": [float(t) for t in self.thresholds],
                         "cv_error": [float(e) for e in self.cv_error],
                         "n_terms": [int(n) for n in self.n_terms]}}


class AutoSTLSQ:
    """STLSQ whose threshold is chosen by blocked cross-validation + the 1-SE rule."""

    def __init__(self, n_folds: int = 5, grid=None, forced=()):
        self.n_folds = n_folds
        self.grid = np.geomspace(1e-6, 0.5, 46) if grid is None else np.asarray(grid, float)
        self.forced = tuple(forced)   # column indices never thresholded away

    def fit(self, A: np.ndarray, b: np.ndarray) -> SparseFit:
        n, p = A.shape
        norms = np.sqrt(np.sum(A * A, axis=0))
        norms[norms == 0] = 1.0
        bn = float(np.sqrt(b @ b)) or 1.0
        An = A / norms
        bs = b / bn
        # interleaved blocks: 20 contiguous chunks per fold, dealt round-robin, so every fold
        # sees every part of the record (start-up transient included) without sample-level leakage
        chunk = max(1, n // (20 * self.n_folds))
        fold_of = (np.arange(n) // chunk) % self.n_folds
        Rf, df, ef, bbf = [], [], [], []
        for i in range(self.n_folds):
            sl = fold_of == i
            Q, R = np.linalg.qr(An[sl])
            d = Q.T @ bs[sl]
            Rf.append(R)
            df.append(d)
            bbf.append(float(bs[sl] @ bs[sl]))
            ef.append(max(bbf[-1] - float(d @ d), 0.0))
        Rall = np.vstack(Rf)
        dall = np.concatenate(df)
        errs = np.empty((self.grid.size, self.n_folds))
        nterms = np.empty(self.grid.size, int)
        forced = np.zeros(p, bool)
        forced[list(self.forced)] = True
        for k, tau in enumerate(self.grid):
            _, sup = stlsq(Rall, dall, tau, forced)
            nterms[k] = sup.sum()
            for i in range(self.n_folds):
                keep = np.r_[0:i * p, (i + 1) * p:Rall.shape[0]]
                x, _ = stlsq(Rall[keep], dall[keep], tau, forced)
                r = df[i] - Rf[i] @ x
                errs[k, i] = (float(r @ r) + ef[i]) / bbf[i]
        errs = np.maximum(errs, 0.0)
        mean = errs.mean(axis=1)
        se = errs.std(axis=1, ddof=1) / np.sqrt(self.n_folds)
        best = int(np.argmin(mean))
        ok = np.flatnonzero(mean <= mean[best] + se[best])
        # sparsest admissible; among equal sparsity, the smallest threshold
        kmin = ok[np.lexsort((self.grid[ok], nterms[ok]))[0]]
        tau = float(self.grid[kmin])
        _, sup = stlsq(Rall, dall, tau, forced)
        idx = np.flatnonzero(sup)
        coef = np.zeros(p)
        stderr = np.zeros(p)
        if idx.size:
            sol, *_ = np.linalg.lstsq(An[:, idx], bs, rcond=None)
            res = bs - An[:, idx] @ sol
            coef[idx] = sol * bn / norms[idx]
            dof = max(n - idx.size, 1)
            s2 = float(res @ res) / dof
            cov = s2 * np.linalg.pinv(An[:, idx].T @ An[:, idx])
            stderr[idx] = np.sqrt(np.diag(cov)) * bn / norms[idx]
            rel = float(np.sqrt(res @ res))
        else:
            rel = 1.0
        return SparseFit(coef=coef, support=sup, threshold=tau, thresholds=self.grid, cv_error=mean,
                         cv_se=se, n_terms=nterms, rel_residual=rel, stderr=stderr)



def matrix_rows(A, index) -> np.ndarray:
    """``A[index]`` of an array, or the rows a matrix built on demand (an object with ``shape``,
    ``rows(index)`` and ``columns(idx)``, e.g. recon.library.agent.LibraryMatrix) builds."""
    return A[index] if isinstance(A, np.ndarray) else A.rows(index)


def matrix_columns(A, idx) -> np.ndarray:
    """``A[:, idx]`` of an array or of a matrix built on demand (:func:`matrix_rows`)."""
    return A[:, idx] if isinstance(A, np.ndarray) else A.columns(idx)


def column_sum_squares(A, rows: int = 16384) -> np.ndarray:
    """np.sum(A * A, axis=0), to the bit, without the n x p temporary: numpy adds the rows of a
    C-ordered array one after another along axis 0, and so does this, a block of rows at a time
    (each block's sum starting from the running total). ``A``: an array or a matrix built on
    demand (:func:`matrix_rows`), read a block at a time."""
    acc = None
    for start in range(0, A.shape[0], rows):
        block = matrix_rows(A, slice(start, start + rows))
        sq = block * block
        acc = np.add.reduce(sq, axis=0) if acc is None else np.add.reduce(np.vstack([acc[None], sq]), axis=0)
    return acc if acc is not None else np.zeros(A.shape[1])


class CompressedFolds:
    """Interleaved K-fold split of a normalised regression, each fold QR-compressed."""

    def __init__(self, A, b: np.ndarray, n_folds: int = 5):
        n, p = A.shape
        self.p = p
        # the caller's matrix (an array, or one built on demand: matrix_rows), normalised a fold (or a
        # support's columns) at a time: only one fold's rows are held at once
        self.A = A
        self.norms = np.sqrt(column_sum_squares(A))
        self.norms[self.norms == 0] = 1.0
        self.bn = float(np.sqrt(b @ b)) or 1.0
        bs = b / self.bn
        self.bs = bs
        chunk = max(1, n // (20 * n_folds))
        fold_of = (np.arange(n) // chunk) % n_folds
        self.Rf, self.df, self.ef, self.bbf = [], [], [], []
        for i in range(n_folds):
            sl = fold_of == i
            fold = matrix_rows(A, sl)
            fold /= self.norms
            Q, R = np.linalg.qr(fold)
            del fold
            d = Q.T @ bs[sl]
            self.Rf.append(R)
            self.df.append(d)
            self.bbf.append(float(bs[sl] @ bs[sl]))
            self.ef.append(max(self.bbf[-1] - float(d @ d), 0.0))
        self.R = np.vstack(self.Rf)
        self.d = np.concatenate(self.df)
        self.n_folds = n_folds
        # rows of each fold's R in the stack (a fold with fewer rows than columns has a shorter R)
        self.offsets = np.cumsum([0] + [R.shape[0] for R in self.Rf])

    def normalised(self, idx: np.ndarray) -> np.ndarray:
        """The normalised columns ``idx`` of the matrix (what the folds were made of)."""
        return matrix_columns(self.A, idx) / self.norms[idx]

    def cv(self, support: np.ndarray) -> np.ndarray:
        """Held-out relative squared residual of LS on ``support``, one value per fold."""
        e = np.empty(self.n_folds)
        off = self.offsets
        for i in range(self.n_folds):
            keep = np.r_[0:off[i], off[i + 1]:self.R.shape[0]]
            x = _solve(self.R[keep], self.d[keep], support)
            r = self.df[i] - self.Rf[i] @ x
            e[i] = (float(r @ r) + self.ef[i]) / self.bbf[i]
        return e

    def rss(self, support: np.ndarray) -> float:
        x = _solve(self.R, self.d, support)
        r = self.d - self.R @ x
        return float(r @ r)


class GroupedSparseSelector:
    """Choose a support among candidates from two paths, by cross-validation.

    Candidates: (1) the STLSQ path over a log grid of thresholds (normalised scale),
    (2) a greedy forward path over column *groups* (in the agent model a monomial
    brings two columns, s*phi_j' and y'*phi_j, that share a_j), starting from the
    ``core`` columns, which the STLSQ path never drops either. Every distinct support is scored by interleaved K-fold CV;
    the one minimising a Bayesian information criterion of the held-out error,
    BIC = N_eff ln(E_cv) + k ln(N_eff), is chosen. N_eff = N / corr_len is the number
    of independent samples: Savitzky-Golay filtered noise is correlated over about one
    window, so corr_len is the window length. (Plain CV keeps adding terms that fit the
    filter's systematic bias, which is as predictable in held-out folds as the signal.) STLSQ alone
    is fragile when monomials of a near-harmonic response are nearly collinear;
    the grouped forward path keeps the pattern physically paired.
    """

    def __init__(self, groups: list[list[int]], core: list[int], n_folds: int = 5, grid=None, max_groups: int = 12,
                 corr_len: float = 1.0):
        self.groups = groups
        self.core = core
        self.n_folds = n_folds
        self.grid = np.geomspace(1e-6, 0.5, 46) if grid is None else np.asarray(grid, float)
        self.max_groups = max_groups
        self.corr_len = max(1.0, float(corr_len))

    def fit(self, A, b: np.ndarray) -> SparseFit:
        """Select on ``A`` (an array, or a matrix built on demand: :func:`matrix_rows`) x = ``b``."""
        n, p = A.shape
        cf = CompressedFolds(A, b, self.n_folds)
        cands = {}   # support bytes -> (support, origin, threshold)
        core = np.zeros(p, bool)
        core[self.core] = True       # the hysteresis agent (y y', y' Fn) is the model's premise
        for tau in self.grid:
            _, sup = stlsq(cf.R, cf.d, tau, forced=core)
            cands.setdefault(sup.tobytes(), (sup, "stlsq", float(tau)))
        sup = np.zeros(p, bool)
        sup[self.core] = True
        cands.setdefault(sup.tobytes(), (sup.copy(), "forward", float("nan")))
        remaining = list(range(len(self.groups)))
        for _ in range(min(self.max_groups, len(self.groups))):
            best = None
            for gi in remaining:
                trial = sup.copy()
                trial[self.groups[gi]] = True
                r = cf.rss(trial)
                if best is None or r < best[0]:
                    best = (r, gi, trial)
            _, gi, sup = best
            remaining.remove(gi)
            cands.setdefault(sup.tobytes(), (sup.copy(), "forward", float("nan")))
        scored = []
        for sup, origin, tau in cands.values():
            e = cf.cv(sup)
            scored.append([float(e.mean()), 0.0, int(sup.sum()), origin, tau, sup, e])
        # information criterion on the held-out error with the effective number of
        # independent samples: the filtered noise is correlated over ``corr_len`` samples
        n_eff = max(n / self.corr_len, 2.0 * p)
        for s_ in scored:
            s_[1] = n_eff * np.log(max(s_[0], 1e-300)) + s_[2] * np.log(n_eff)
        chosen = min(scored, key=lambda s: (s[1], s[2]))
        m, se, k, origin, tau, sup, _ = chosen
        idx = np.flatnonzero(sup)
        coef = np.zeros(p)
        stderr = np.zeros(p)
        An = cf.normalised(idx)
        sol, *_ = np.linalg.lstsq(An, cf.bs, rcond=None)
        res = cf.bs - An @ sol
        coef[idx] = sol * cf.bn / cf.norms[idx]
        s2 = float(res @ res) / max(n - idx.size, 1)
        cov = s2 * np.linalg.pinv(An.T @ An)
        stderr[idx] = np.sqrt(np.abs(np.diag(cov))) * cf.bn / cf.norms[idx]
        # threshold equivalent: the smallest |normalised coefficient| kept
        tau_eq = float(np.min(np.abs(sol))) if np.isnan(tau) else tau
        order = np.argsort([s[2] for s in scored])
        return SparseFit(coef=coef, support=sup, threshold=tau_eq,
                         thresholds=np.array([scored[i][4] for i in order]),
                         cv_error=np.array([scored[i][0] for i in order]),
                         cv_se=np.array([scored[i][1] for i in order]),
                         n_terms=np.array([scored[i][2] for i in order]),
                         rel_residual=float(np.sqrt(res @ res)), stderr=stderr,
                         origin=origin)

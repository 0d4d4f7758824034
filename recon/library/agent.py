"""The agent-model library for Fn' (the derivative of the nonlinear force).

With fn = sum_j a_j phi_j(y, y') (phi_j = y^p y'^r, degree 2..q) and the
Bouc-Wen agent zn' = -s lambda y' z on the clusters AB (s = +1) and CD (s = -1):

    Fn' = sum_j a_j phi_j' + s lambda sum_j a_j y' phi_j - s lambda alpha y y' - s lambda y' Fn

Two forms of the regression are offered:

``joint`` (default): the CD rows are multiplied by s so that one coefficient
vector fits AB and CD together. Target s Fn'; columns

    s*d/dt(phi_j)   coefficient a_j           (named "d(phi)")
    y'*phi_j        coefficient lambda a_j    (named "dy*phi")
    y*y'            coefficient -lambda alpha
    y'*Fn           coefficient -lambda

No columns merge (s separates d(y^m)/dt = m y^(m-1) y' from y' y^(m-1)). With ``offset`` (a
fitted input offset, recon.estimator.input_offset) a core column y' takes lambda d for a constant
error d of Fn.

``ab`` (the paper's form, AB samples only, s = +1): columns merge, so the
pure-y coefficients must be recovered by back-substitution:

    xi block   y^(m-i) y'^(i+1), m = 2..q, i = 0..m
               (y^m y' has coefficient lambda a_{y^m} + (m+1) a_{y^(m+1)})
    psi block  d/dt(y^p y'^r) for r >= 1, coefficient a_{y^p y'^r}
    y*y'       coefficient 2 a_{y^2} - lambda alpha
    y'*Fn      coefficient -lambda

The columns are plain functions of per-sample arrays, so the same library is
reused per layer (MDOF) and by an integral (weak-form) builder.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.library import monomials
from shakerlab.errors import UserFacingError

FORMS = ("joint", "ab")


def phi(y, dy, p, r):
    """y^p y'^r."""
    return phi_of(Powers(y, dy), p, r)


def dphi(y, dy, ddy, p, r):
    """d/dt (y^p y'^r) = p y^(p-1) y'^(r+1) + r y^p y'^(r-1) y''."""
    return dphi_of(Powers(y, dy), ddy, p, r)


def phi_of(pw: "Powers", p: int, r: int) -> np.ndarray:
    """:func:`phi` from the samples' powers ``pw`` (each taken once, shared by the columns)."""
    return pw.of_y(p) * pw.of_dy(r)


def dphi_of(pw: "Powers", ddy, p: int, r: int) -> np.ndarray:
    """:func:`dphi` from the samples' powers ``pw``."""
    out = np.zeros_like(pw.y)
    if p:
        out = out + p * pw.of_y(p - 1) * pw.of_dy(r + 1)
    if r:
        out = out + r * pw.of_y(p) * pw.of_dy(r - 1) * ddy
    return out


@dataclass(frozen=True)
class Column:
    name: str
    role: str            # joint: a, lam_a, lam_alpha, lam ; ab: xi, psi, yy, yFn
    p: int = 0
    r: int = 0


class AgentLibrary:
    def __init__(self, order: int = 5, form: str = "joint", linear_correction: bool = False,
                 offset: bool = False):
        if order < 2:
            raise UserFacingError(f"library order must be >= 2, got {order}")
        if form not in FORMS:
            raise UserFacingError(f"library form must be one of {FORMS}, got {form!r}")
        self.order = int(order)
        self.form = form
        self.linear_correction = bool(linear_correction)
        self.offset = bool(offset) and form == "joint"
        self.terms = monomials.up_to(self.order)
        cols = []
        if form == "joint":
            for p, r in self.terms:
                cols.append(Column(f"d({monomials.name(p, r)})", "a", p, r))
            for p, r in self.terms:
                cols.append(Column(f"dy*{monomials.name(p, r)}", "lam_a", p, r))
            cols.append(Column("y*dy", "lam_alpha", 1, 1))
            cols.append(Column("dy*Fn", "lam"))
            if self.linear_correction:
                # absorb the linear step's errors dc, dK: Fn carries -dc y' - dK y, so s Fn'
                # gains s y'', s y' and the y' Fn column gains y'^2 (and y y', already present)
                cols.append(Column("s*ddy", "lin", 0, 0))
                cols.append(Column("s*dy", "lin", 0, 1))
                cols.append(Column("dy^2", "lin", 0, 2))
            if self.offset:
                # a constant error d of Fn (the input offset as the linear stage saw it, where a
                # hysteretic element held part of a constant force): -lambda y' Fn gains lambda d y'
                cols.append(Column("dy", "const", 0, 0))
        else:
            for m in range(2, self.order + 1):
                for i in range(m + 1):
                    cols.append(Column(monomials.name(m - i, i + 1), "xi", m - i, i))
            for p, r in self.terms:
                if r >= 1:
                    cols.append(Column(f"d({monomials.name(p, r)})", "psi", p, r))
            cols.append(Column("y*dy", "yy", 1, 1))
            cols.append(Column("dy*Fn", "yFn"))
        self.columns = cols

    def groups(self):
        """(groups, core): the columns one monomial's a_j enters, and the always-offered core.

        joint: y^p y'^r -> {s*d(phi), y'*phi}. ab: non-pure -> {psi, xi}; pure y^m ->
        {xi(y^m y'), xi(y^(m-1) y')} because d(y^m)/dt = m y^(m-1) y' merges into the
        lower column (for m = 2 that is the core column y y')."""
        core = [k for k, c in enumerate(self.columns) if c.role in ("lam_alpha", "lam", "yy", "yFn", "lin", "const")]
        by_term = {}
        index = {(c.role, c.p, c.r): k for k, c in enumerate(self.columns)}
        for k, c in enumerate(self.columns):
            if c.role in ("a", "lam_a", "psi"):
                by_term.setdefault((c.p, c.r), []).append(k)
            elif c.role == "xi":
                by_term.setdefault((c.p, c.r), []).append(k)
                if c.r == 0 and ("xi", c.p - 1, 0) in index:
                    by_term[(c.p, c.r)].append(index[("xi", c.p - 1, 0)])
        return [sorted(set(g)) for g in by_term.values()], core

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.columns]

    def rows(self, h: np.ndarray) -> np.ndarray:
        """Samples this form uses (boolean mask) given the cluster array h."""
        return (h != 0) if self.form == "joint" else (h == 1)

    def build(self, y, dy, ddy, Fn, dFn, h):
        """(Theta, target) over the rows this form uses (Theta: the whole rows x columns matrix)."""
        matrix, target = self.matrix(y, dy, ddy, Fn, dFn, h)
        return matrix.rows(slice(None)), target

    def matrix(self, y, dy, ddy, Fn, dFn, h):
        """(LibraryMatrix, target) over the rows this form uses: Theta as :meth:`build` gives it,
        made a block of rows or a set of columns at a time when read (the sparse regression's folds
        never hold the whole matrix)."""
        mask = self.rows(h)
        y, dy, ddy, Fn, dFn = (a[mask] for a in (y, dy, ddy, Fn, dFn))
        s = h[mask].astype(float)
        target = s * dFn if self.form == "joint" else dFn
        return LibraryMatrix(self, y, dy, ddy, Fn, s), target

    def column(self, c: Column, pw: "Powers", ddy, Fn, s) -> np.ndarray:
        """The values of column ``c`` on samples (y, y' in ``pw``, y'', Fn) with cluster sign ``s``:
        :func:`phi` and :func:`dphi` on the powers of y and y' the columns share."""
        y, dy = pw.y, pw.dy
        p, r = c.p, c.r
        if c.role in ("a", "psi"):
            out = dphi_of(pw, ddy, p, r)
            return s * out if c.role == "a" else out
        if c.role in ("lam_a", "xi"):
            return dy * phi_of(pw, p, r)
        if c.role in ("lam_alpha", "yy"):
            return y * dy
        if c.role == "lin":
            return s * ddy if r == 0 else (s * dy if r == 1 else dy * dy)
        if c.role == "const":
            return dy
        return dy * Fn

    def true_coefficients(self, fn_m: dict, lam: float, alpha: float) -> np.ndarray:
        """The coefficient vector a model implies (used to check the algebra)."""
        a = {monomials.parse(k): v for k, v in fn_m.items()}
        out = np.zeros(len(self.columns))
        for k, c in enumerate(self.columns):
            pr = (c.p, c.r)
            if c.role == "a" or c.role == "psi":
                out[k] = a.get(pr, 0.0)
            elif c.role == "lam_a":
                out[k] = lam * a.get(pr, 0.0)
            elif c.role == "lam_alpha":
                out[k] = -lam * alpha
            elif c.role in ("lam", "yFn"):
                out[k] = -lam
            elif c.role == "yy":
                out[k] = 2 * a.get((2, 0), 0.0) - lam * alpha
            elif c.role == "xi":
                v = lam * a.get(pr, 0.0)
                if c.r == 0:
                    v += (c.p + 1) * a.get((c.p + 1, 0), 0.0)
                out[k] = v
        return out


class LibraryMatrix:
    """The library matrix Theta (rows: the samples the form uses, one column per library column)
    without holding it: :meth:`rows` builds the rows asked for, :meth:`columns` the columns asked
    for, each entry by the same arithmetic on the same samples, so equal to the whole matrix's to the
    bit. What recon.regression.sparse.CompressedFolds reads in place of an array."""

    def __init__(self, lib: AgentLibrary, y, dy, ddy, Fn, s):
        self.lib = lib
        self.samples = (y, dy, ddy, Fn, s)
        self.shape = (y.size, len(lib.columns))

    def rows(self, index) -> np.ndarray:
        """Theta[index] (a slice or a boolean mask of the rows), a new C-ordered array."""
        y, dy, ddy, Fn, s = (a[index] for a in self.samples)
        pw = Powers(y, dy)
        out = np.empty((y.size, self.shape[1]))
        for k, c in enumerate(self.lib.columns):
            out[:, k] = self.lib.column(c, pw, ddy, Fn, s)
        return out

    def columns(self, idx) -> np.ndarray:
        """Theta[:, idx] (column indices), laid out as numpy lays out that indexing (Fortran order)."""
        y, dy, ddy, Fn, s = self.samples
        pw = Powers(y, dy)
        out = np.empty((self.shape[0], len(idx)), order="F")
        for j, k in enumerate(idx):
            out[:, j] = self.lib.column(self.lib.columns[k], pw, ddy, Fn, s)
        return out


class Powers:
    """The powers y^k and y'^k of a set of samples, each taken once (``y ** k``, the numbers
    :func:`phi` and :func:`dphi` take) and kept for the columns that share it."""

    def __init__(self, y: np.ndarray, dy: np.ndarray):
        self.y, self.dy = y, dy
        self._y: dict[int, np.ndarray] = {}
        self._dy: dict[int, np.ndarray] = {}

    def of_y(self, k: int) -> np.ndarray:
        if k not in self._y:
            self._y[k] = self.y ** k
        return self._y[k]

    def of_dy(self, k: int) -> np.ndarray:
        if k not in self._dy:
            self._dy[k] = self.dy ** k
        return self._dy[k]

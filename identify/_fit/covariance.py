"""The covariance of a fit at its optimum, densely or block by block.

At the optimum, with `J` the weighted residuals' Jacobian and `s^2 = RSS / (N - n_par)`
the residual variance, the Gauss-Newton covariance is

    Cov = s^2 (J^T J)^+

(the pseudo-inverse by SVD, singular values below `s_max max(N, n_par) eps` dropped:
`dense`). A joint fit of `L` logs has a block-arrow `J = [S | blockdiag(U_1, ..., U_L)]`
(`P` shared parameters, a few nuisances per log: `identify.residuals`), and the dense `J`
is `L n x (P + L k)`: 1.5 GB at 500 logs of 600 residuals with 3 nuisances each, and its
SVD cubic in `L`. `blocked` gets the same standard errors without forming it, by the
block inverse of `J^T J` (Schur complement of the nuisance blocks):

    Cov_SS = s^2 (sum_l S_l^T (I - P_l) S_l)^+,       P_l = U_l U_l^+  (projector on U_l's range)
    Cov_ll = s^2 (U_l^T U_l)^+ + G_l Cov_SS G_l^T,    G_l = U_l^+ S_l

(`U_l^+` by a per-log SVD with the same relative cut-off; `Cov_SS` from one SVD of the
stacked `(I - P_l) S_l`, an `L n x P` matrix). With every block of full rank this is
`(J^T J)^-1` exactly; with a rank-deficient block it is a generalised inverse, which
gives what the data determine as the dense pseudo-inverse does (an estimable quantity's
variance does not depend on the generalised inverse), and both mark the rest undetermined
(below).

**Cluster-robust covariance** (`clustered`). `s^2 (J^T J)^+` assumes white residuals. On
real data the residual of each log is mostly model error, correlated along the log, and
those intervals are far too narrow. Treating each log as a cluster whose residuals may be
correlated in any way, but independent of the other logs', the sandwich estimator of Liang
& Zeger (1986) for the shared parameters, with each log's nuisances profiled out, is

    Cov_SS = c A^+ (sum_l g_l g_l^T) A^+,   A = sum_l S~_l^T S~_l,   g_l = S~_l^T r_l,
    S~_l = (I - P_l) S_l,   c = L / (L - 1)

(`c`: the usual small-sample factor, CR1). It needs several logs (its variance has about
`L - 1` degrees of freedom; intervals use Student's t with `L - 1`), and it is not
scaled by `s^2`: the spread of the per-log scores sets it.

**Undetermined variables.** The pseudo-inverse is taken of the column-normalised `J`
(`_Svd`: the rank decision does not depend on the parameters' units). Where `J` has a
null space (a combination of parameters the data do not see at all, e.g. a pendulum's
centre of mass and inertia about it when only `m g c / (I + m c^2)` shows), the
pseudo-inverse's variance of a parameter in that combination is the variance of its
projection on the determined directions: finite, small and wrong. Such parameters (and a
nuisance that moves with them) get an infinite standard error and no interval instead.

Identifiability: the right singular vectors of the column-normalised `J` with a singular
value below `threshold` times the largest. `blocked` looks at the shared parameters after
eliminating the nuisances (the stacked `(I - P_l) S_l`, scaled by the columns of `S`): a weak
combination of the physical parameters is found either way; its singular values are the
eliminated block's (`P` of them), not the whole `J`'s.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass
class Covariance:
    """`std_errors`: natural coordinates, all variables (shared, then initial-state entries,
    then offsets, each in vector order); `correlation`: the shared parameters'."""

    rss: float
    n_residuals: int
    residual_variance: float
    std_errors: np.ndarray
    correlation: np.ndarray
    singular_values: np.ndarray
    identifiability: list
    # how the shared parameters' standard errors were computed: "white" (`s^2 (J^T J)^+`)
    # or "rounding" (the sensors' quantisation propagated, `identify/_fit/rounding.py`)
    method: str = "white"


# A variable whose unit vector has more than this fraction of its length in the null space
# of the column-normalised Jacobian is not determined by the data (roundoff in an
# orthonormal basis leaves ~1e-8 here; a real null direction loads its variables O(0.1-1)).
NULL_LOADING = 1e-6


@dataclasses.dataclass(frozen=True)
class _Svd:
    """The SVD `W diag(s) Vt` of the column-normalised `A D^-1` (`D`: the column norms, 1 for
    a zero column), with `keep`: singular values above `s_max max(A.shape) eps` (numpy's
    `matrix_rank` rule, here on a scale-free matrix: the rank does not depend on the
    parameters' units)."""

    W: np.ndarray
    s: np.ndarray
    Vt: np.ndarray
    norms: np.ndarray
    keep: np.ndarray

    @staticmethod
    def of(A: np.ndarray, norms: np.ndarray | None = None) -> _Svd:
        """`norms`: the column scales (default `A`'s column norms). A projected block is
        scaled by its columns before the projection, so that a column the projection
        removed (a parameter the nuisances absorb) keeps only roundoff, which is dropped."""
        norms = np.linalg.norm(A, axis=0) if norms is None else np.asarray(norms, float)
        norms = np.where(norms > 0, norms, 1.0)
        W, s, Vt = np.linalg.svd(A / norms, full_matrices=False)
        # the reference is the scaled columns' size, 1 (a projected block's largest
        # singular value can be far below it when the projection took most of every column)
        keep = s > (max(s[0], 1.0) * max(A.shape) * np.finfo(float).eps if s.size else 0.0)
        return _Svd(W, s, Vt, norms, keep)

    @property
    def range_basis(self) -> np.ndarray:
        """Orthonormal columns spanning `A`'s range."""
        return self.W[:, self.keep]

    def pinv(self) -> np.ndarray:
        """`A^+ = D^-1 V_k diag(1/s_k) W_k^T` (`P x m`)."""
        return ((self.Vt[self.keep].T / self.s[self.keep]) @ self.W[:, self.keep].T) / self.norms[:, None]

    def normal_pinv(self) -> np.ndarray:
        """`(A^T A)^+ = D^-1 V_k diag(s_k^-2) V_k^T D^-1` (`P x P`)."""
        V = self.Vt[self.keep]
        return ((V.T / self.s[self.keep] ** 2) @ V) / np.outer(self.norms, self.norms)

    def undetermined(self) -> np.ndarray:
        """Per column: variable `i` has a component in `A`'s null space (more than
        `NULL_LOADING` of its unit vector). Moving along a null direction changes it without
        changing the fit, so its variance is infinite, not the finite number the
        pseudo-inverse gives (the variance of its projection on the determined directions)."""
        V = self.Vt[self.keep]
        return np.sqrt(np.clip(1.0 - np.sum(V**2, axis=0), 0.0, None)) > NULL_LOADING

    def null_space(self) -> NullSpace:
        """The complement of the kept right singular vectors."""
        V = self.Vt[self.keep]
        P = V.shape[1]
        if V.shape[0] == 0:
            return NullSpace(np.eye(P), self.norms)
        _, _, Wt = np.linalg.svd(V, full_matrices=True)
        return NullSpace(Wt[V.shape[0] :].T, self.norms)

    def sees_null_space(self, G: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """Per row of `G` (`k x P`): `g . n != 0` for a null vector `n` of `A` (more than
        `NULL_LOADING` of the row's `scale`, the size it has when nothing cancels, in the
        normalised coordinates: a row that is zero in exact arithmetic is roundoff pointing
        anywhere). A nuisance `x_l = U_l^+ (r_l - S_l theta)` moves with `theta` along `n`
        when its row of `G = U_l^+ S_l` does, so it is not determined either."""
        V = self.Vt[self.keep]
        Gn = G / self.norms  # theta = D^-1 theta_n
        null_part = np.linalg.norm(Gn - (Gn @ V.T) @ V, axis=1)
        return null_part > NULL_LOADING * scale


@dataclasses.dataclass(frozen=True)
class NullSpace:
    """The directions of the parameters the data do not see: `basis` (`P x m`,
    orthonormal columns) in the scaled coordinates `theta_n = D theta` of `_Svd` (`scales`:
    `D`), so that `theta + D^-1 basis c` fits the data as well as `theta` for any `c`."""

    basis: np.ndarray
    scales: np.ndarray

    def undetermined(self) -> np.ndarray:
        """Per parameter: it moves along a null direction (`_Svd.undetermined`)."""
        return np.linalg.norm(self.basis, axis=1) > NULL_LOADING

    def determines(self, grad: np.ndarray) -> bool:
        """Whether the data determine a function of the parameters with gradient `grad`
        (natural coordinates): `grad . D^-1 n = 0` for every null direction `n` (to
        `NULL_LOADING` of its size; e.g. the sum of two parameters of which only the sum
        is seen is determined, either alone is not)."""
        g = np.asarray(grad, float) / self.scales
        size = np.linalg.norm(g)
        return bool(np.linalg.norm(self.basis.T @ g) <= NULL_LOADING * size) if size > 0 else True


def _correlation(cov: np.ndarray, undetermined: np.ndarray) -> np.ndarray:
    """The correlation matrix of `cov`, NaN off the diagonal for undetermined variables."""
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(d, d)
    bad = undetermined[:, None] | undetermined[None, :]
    return np.where(bad & ~np.eye(len(d), dtype=bool), np.nan, corr)


def _weak_directions(names, log_scale, Vt, S, threshold, p):
    warnings = []
    for k in range(len(S)):
        ratio = S[k] / S[0] if S[0] > 0 else 0.0
        if ratio < threshold:
            v = Vt[k, :p]
            if np.linalg.norm(v) < 0.5:  # the weak direction is in the nuisances
                continue
            terms = [
                f"{v[i]:+.2f} {'log ' if log_scale[i] else ''}{names[i]}"
                for i in np.argsort(-np.abs(v))
                if abs(v[i]) > 0.1
            ]
            warnings.append({"combination": " ".join(terms), "ratio": float(ratio)})
    return warnings


def dense(names, log_scale, r: np.ndarray, J: np.ndarray, threshold: float = 1e-6) -> Covariance:
    """The covariance from the dense Jacobian `J` (rows: the residuals that count only)."""
    p = len(names)
    n_res, n_par = J.shape
    rss = float(r @ r)
    s2 = rss / max(n_res - n_par, 1)
    svd = _Svd.of(J)
    cov = s2 * svd.normal_pinv()
    undetermined = svd.undetermined()
    se = np.where(undetermined, np.inf, np.sqrt(np.clip(np.diag(cov), 0, None)))
    corr = _correlation(cov, undetermined)[:p, :p]
    ident = _weak_directions(names, log_scale, svd.Vt, svd.s, threshold, p)
    return Covariance(rss, n_res, s2, se, corr, svd.s, ident)


def blocked(
    names,
    log_scale,
    r: np.ndarray,
    S: np.ndarray,
    U: np.ndarray,
    slots: np.ndarray,
    used: np.ndarray,
    threshold: float = 1e-6,
) -> Covariance:
    """The covariance from the blocks of a block-arrow Jacobian (module docstring).

    - `r`: `(L, n)` residuals, `S`: `(L, n, P)`, `U`: `(L, n, k)` per-log nuisance columns
      (padding columns allowed);
    - `slots`: `(L, k)` position of each nuisance column among the nuisance variables
      (initial-state entries then offsets), -1 on padding;
    - `used`: `(L, n)` whether each residual counts (the others are ignored).
    """
    L, n, P = S.shape
    n_nuis = int(np.max(slots, initial=-1)) + 1
    mask = used.astype(float)
    r, S, U = r * mask, S * mask[:, :, None], U * mask[:, :, None]
    n_res = int(used.sum())
    n_par = P + n_nuis
    rss = float(np.sum(r**2))
    s2 = rss / max(n_res - n_par, 1)

    projected = np.empty_like(S)
    se = np.zeros(P + n_nuis)
    G, Uinv, nuis_undetermined = [], [], []  # per log: U_l^+ S_l (k_l x P), U_l^+ (k_l x n)
    for l in range(L):
        cols = slots[l] >= 0
        Ul = U[l][:, cols]
        if Ul.shape[1] == 0:
            projected[l] = S[l]
            G.append(np.zeros((0, P)))
            Uinv.append(np.zeros((0, n)))
            nuis_undetermined.append(np.zeros(0, bool))
            continue
        svd_l = _Svd.of(Ul)
        Wl = svd_l.range_basis
        projected[l] = S[l] - Wl @ (Wl.T @ S[l])
        pinv = svd_l.pinv()  # k_l x n
        Uinv.append(pinv)
        G.append(pinv @ S[l])
        nuis_undetermined.append(svd_l.undetermined())

    stacked = projected.reshape(L * n, P)
    # scaled by the columns of S (not of the projection: a parameter the nuisances absorb
    # shows a small singular value, for the rank and the identifiability warnings alike)
    norms = np.sqrt(np.sum(S**2, axis=(0, 1)))
    if P:
        svd = _Svd.of(stacked, norms)
        cov_ss = s2 * svd.normal_pinv()
        shared_undetermined = svd.undetermined()
    else:
        svd, cov_ss, shared_undetermined = None, np.zeros((0, 0)), np.zeros(0, bool)
    se[:P] = np.where(shared_undetermined, np.inf, np.sqrt(np.clip(np.diag(cov_ss), 0, None)))
    for l in range(L):
        cols = np.flatnonzero(slots[l] >= 0)
        if cols.size == 0:
            continue
        var = s2 * np.sum(Uinv[l] ** 2, axis=1) + np.einsum("ip,pq,iq->i", G[l], cov_ss, G[l])
        # a row of G = U_l^+ S_l at its largest: |U_l^+ row| |S_l D^-1| (normalised coordinates)
        scale = np.linalg.norm(Uinv[l], axis=1) * np.linalg.norm(S[l] / svd.norms) if P else 0.0
        bad = nuis_undetermined[l] | (svd.sees_null_space(G[l], scale) if P else False)
        se[P + slots[l, cols]] = np.where(bad, np.inf, np.sqrt(np.clip(var, 0, None)))

    corr = _correlation(cov_ss, shared_undetermined)
    Sn, Vtn = (svd.s, svd.Vt) if P else (np.zeros(0), np.zeros((0, 0)))
    ident = _weak_directions(names, log_scale, Vtn, Sn, threshold, len(names))
    return Covariance(rss, n_res, s2, se, corr, Sn, ident)


def projected_shared(S: np.ndarray, U: np.ndarray, slots: np.ndarray, used: np.ndarray) -> np.ndarray:
    """`S~_l = (I - P_l) S_l` for each log (arguments as for `blocked`): its shared
    columns with what its own nuisances can reproduce projected out, zero where unused."""
    mask = used.astype(float)
    S, U = S * mask[:, :, None], U * mask[:, :, None]
    out = np.empty_like(S)
    for l in range(S.shape[0]):
        Ul = U[l][:, slots[l] >= 0]
        if Ul.shape[1]:
            W = _Svd.of(Ul).range_basis
            out[l] = S[l] - W @ (W.T @ S[l])
        else:
            out[l] = S[l]
    return out


def clustered(
    r: np.ndarray, S: np.ndarray, U: np.ndarray, slots: np.ndarray, used: np.ndarray, *, null_space: bool = False
):
    """The cluster-robust covariance of the `P` shared parameters, clusters = logs (module
    docstring), natural coordinates; arguments as for `blocked`. Needs at least 2 logs.

    With `A` singular the sandwich uses a generalised inverse of it: right for what the
    data determine, finite and meaningless for the rest. `null_space=True` returns
    `(cov, NullSpace)` to tell them apart (`NullSpace.undetermined`, `.determines`)."""
    L, n, P = S.shape
    if L < 2:
        raise ValueError(f"clustered: the cluster-robust covariance needs at least 2 logs, got {L}")
    r, S = r * used, S * used[:, :, None]
    projected = projected_shared(S, U, slots, used)
    scores = np.einsum("lnp,ln->lp", projected, r)
    svd = _Svd.of(projected.reshape(L * n, P), np.sqrt(np.sum(S**2, axis=(0, 1))))
    bread = svd.normal_pinv()
    cov = L / (L - 1) * bread @ (scores.T @ scores) @ bread
    return (cov, svd.null_space()) if null_space else cov


def digits(value: float, spread: float) -> int:
    """Significant digits that show a change of `spread` in `value` (a standard error, an
    interval's width): two beyond the first digit the spread touches, at least 4 and at most
    12; 4 where either is zero or not finite."""
    value, spread = abs(float(value)), abs(float(spread))
    if not (value > 0 and spread > 0 and np.isfinite(value) and np.isfinite(spread)):
        return 4
    # (the difference of logarithms: the quotient itself can underflow to 0 or overflow)
    return int(min(12, max(4, math.floor(math.log10(value) - math.log10(spread)) + 2)))


def interval_text(lo: float, hi: float, std_error: float | None = None) -> str:
    """`[lo, hi]` with the digits that tell its ends apart (`digits` of each end against
    the width): `[11.995, 12.001]`, not `[12, 12]`. An infinite end is "not determined"
    when the standard error is infinite or not given; with a finite `std_error` (a
    parameter fitted in log space whose interval overflowed) it reads `[lo, inf)`, since
    "not determined" beside a finite standard error would read as a contradiction."""
    if np.isinf(lo) or np.isinf(hi):
        if std_error is not None and np.isfinite(std_error) and np.isfinite(lo):
            return f"[{lo:.3g}, inf)"
        return "not determined"
    d = max(digits(lo, hi - lo), digits(hi, hi - lo))
    return f"[{lo:.{d}g}, {hi:.{d}g}]"

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
`(J^T J)^-1` exactly; with a rank-deficient block it is a generalised inverse that may
differ from the dense pseudo-inverse in the unidentifiable directions (whose standard
errors mean nothing either way; they are reported by the identifiability check).

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

Identifiability: the right singular vectors of the column-normalised `J` with a singular
value below `threshold` times the largest. `blocked` looks at the shared parameters after
eliminating the nuisances (the column-normalised `(I - P_l) S_l` stacked): a weak
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


def _pinv_parts(A: np.ndarray):
    """SVD of `A` truncated at `s_max max(A.shape) eps`: `(W, s, Vt)`."""
    W, s, Vt = np.linalg.svd(A, full_matrices=False)
    if s.size == 0:
        return W, s, Vt
    tol = s[0] * max(A.shape) * np.finfo(float).eps
    keep = s > tol
    return W[:, keep], s[keep], Vt[keep]


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
    U, S, Vt = np.linalg.svd(J, full_matrices=False)
    tol = S[0] * max(J.shape) * np.finfo(float).eps if S.size else 0.0
    Sinv2 = np.where(S > tol, 1.0 / np.where(S > tol, S, 1.0) ** 2, 0.0)
    cov = s2 * (Vt.T * Sinv2) @ Vt
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = (cov / np.outer(d, d))[:p, :p]
    norms = np.linalg.norm(J, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    _, Sn, Vtn = np.linalg.svd(J / norms, full_matrices=False)
    ident = _weak_directions(names, log_scale, Vtn, Sn, threshold, p)
    return Covariance(rss, n_res, s2, se, corr, Sn, ident)


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
    G, Uinv = [], []  # per log: U_l^+ S_l (k_l x P), U_l^+ (k_l x n)
    for l in range(L):
        cols = slots[l] >= 0
        Ul = U[l][:, cols]
        if Ul.shape[1] == 0:
            projected[l] = S[l]
            G.append(np.zeros((0, P)))
            Uinv.append(np.zeros((0, n)))
            continue
        W, s, Vt = _pinv_parts(Ul)
        projected[l] = S[l] - W @ (W.T @ S[l])
        pinv = (Vt.T / s) @ W.T  # k_l x n
        Uinv.append(pinv)
        G.append(pinv @ S[l])

    stacked = projected.reshape(L * n, P)
    _, ss, Vts = _pinv_parts(stacked) if P else (None, np.zeros(0), np.zeros((0, 0)))
    cov_ss = s2 * (Vts.T / ss**2) @ Vts if P else np.zeros((0, 0))

    se = np.zeros(P + n_nuis)
    se[:P] = np.sqrt(np.clip(np.diag(cov_ss), 0, None))
    for l in range(L):
        cols = np.flatnonzero(slots[l] >= 0)
        if cols.size == 0:
            continue
        var = s2 * np.sum(Uinv[l] ** 2, axis=1) + np.einsum("ip,pq,iq->i", G[l], cov_ss, G[l])
        se[P + slots[l, cols]] = np.sqrt(np.clip(var, 0, None))

    d = np.sqrt(np.clip(np.diag(cov_ss), 1e-300, None))
    corr = cov_ss / np.outer(d, d) if P else np.zeros((0, 0))
    norms = np.sqrt(np.sum(S**2, axis=(0, 1)))
    norms = np.where(norms > 0, norms, 1.0)
    if P:
        _, Sn, Vtn = np.linalg.svd(stacked / norms, full_matrices=False)
    else:
        Sn, Vtn = np.zeros(0), np.zeros((0, 0))
    ident = _weak_directions(names, log_scale, Vtn, Sn, threshold, len(names))
    return Covariance(rss, n_res, s2, se, corr, Sn, ident)


def clustered(r: np.ndarray, S: np.ndarray, U: np.ndarray, slots: np.ndarray, used: np.ndarray) -> np.ndarray:
    """The cluster-robust covariance of the `P` shared parameters, clusters = logs (module
    docstring), natural coordinates; arguments as for `blocked`. Needs at least 2 logs."""
    L, n, P = S.shape
    if L < 2:
        raise ValueError(f"clustered: the cluster-robust covariance needs at least 2 logs, got {L}")
    mask = used.astype(float)
    r, S, U = r * mask, S * mask[:, :, None], U * mask[:, :, None]
    projected = np.empty_like(S)
    scores = np.empty((L, P))
    for l in range(L):
        Ul = U[l][:, slots[l] >= 0]
        if Ul.shape[1]:
            W, _, _ = _pinv_parts(Ul)
            projected[l] = S[l] - W @ (W.T @ S[l])
        else:
            projected[l] = S[l]
        scores[l] = projected[l].T @ r[l]
    _, ss, Vts = _pinv_parts(projected.reshape(L * n, P))
    bread = (Vts.T / ss**2) @ Vts
    return L / (L - 1) * bread @ (scores.T @ scores) @ bread


def digits(value: float, spread: float) -> int:
    """Significant digits that show a change of `spread` in `value` (a standard error, an
    interval's width): two beyond the first digit the spread touches, at least 4 and at most
    12; 4 where either is zero or not finite."""
    value, spread = abs(float(value)), abs(float(spread))
    if not (value > 0 and spread > 0 and np.isfinite(value) and np.isfinite(spread)):
        return 4
    return int(min(12, max(4, math.floor(math.log10(value / spread)) + 2)))


def interval_text(lo: float, hi: float) -> str:
    """`[lo, hi]` with the digits that tell its ends apart (`digits` of each end against
    the width): `[11.995, 12.001]`, not `[12, 12]`."""
    d = max(digits(lo, hi - lo), digits(hi, hi - lo))
    return f"[{lo:.{d}g}, {hi:.{d}g}]"

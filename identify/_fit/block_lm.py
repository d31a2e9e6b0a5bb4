"""Levenberg-Marquardt for many logs: the damped step solved block by block.

A joint fit of `L` logs has `P` shared variables and `k` nuisances per log (initial-state
entries, sensor offsets), so its Jacobian is block-arrow shaped (`identify.residuals`):
`J = [S | blockdiag(U_1, ..., U_L)]`, `S_l` the `n x P` rows of log `l`, `U_l` its `n x k`
nuisance block. Each Levenberg-Marquardt step solves the damped least-squares problem

    min_d ||J d - r||^2 + lambda ||d||^2,

which optimistix's `LevenbergMarquardt` does by a dense QR of `[J; sqrt(lambda) I]`:
`O(L n (P + L k)^2)` operations and an `L n x (P + L k)` matrix, cubic in the number of
logs: with many logs the factorisation costs more than the Jacobian (docs/performance.md).
`BlockLevenbergMarquardt` is the same algorithm (optimistix's Gauss-Newton loop and
classical trust region, only the descent differs) with the step solved by
eliminating each log's nuisances first (a Schur complement, done with orthogonal
factorisations, not normal equations, so that the conditioning is QR's):

1. per log, the reduced QR `[U_l; sqrt(lambda) I_k] = Q_l R_l`;
2. the shared step from the stacked projected blocks,
   `min_ds ||(I - Q_l Q_l^T)([S_l; 0] ds - [r_l; 0])||^2 summed over l + lambda ||ds||^2`
   (one QR of an `L (n + k) x P` matrix);
3. each log's step `du_l = R_l^-1 (Q_l^T ([r_l; 0] - [S_l; 0] ds))`.

`O(L n (P + k)^2)`: linear in the number of logs. The blocks are read from optimistix's
linearisation by `P + k` products with compressed probes (one probe per nuisance slot for
all logs at once: their rows do not overlap), so this works with any residual function
whose Jacobian has this structure (the fit's, through `identify.residuals.log_blocked`).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from .._model.residuals import Layout
from .._model.variables import AbstractVariables


class _State(eqx.Module):
    template: AbstractVariables  # zeros in the structure of the variables
    r: jax.Array  # (L, n)
    S: jax.Array  # (L, n, P)
    U: jax.Array  # (L, n, k): y0 slots then offset slots


def read_blocks(layout: Layout, y, f_info) -> _State:
    """The residuals `r` `(L, n)` and the blocks `S` `(L, n, P)`, `U` `(L, n, k)` of the
    block-arrow Jacobian at `y`, read from optimistix's linearisation `f_info` with `P + k`
    products `f_info.jac.mv` (one probe per shared variable, one per nuisance slot for all
    logs at once: their rows do not overlap)."""
    L = layout.n_logs
    flat, unravel = ravel_pytree(y.shared)
    P = flat.shape[0]
    no_shared = unravel(jnp.zeros_like(flat))
    no_y0, no_offset = jnp.zeros_like(y.y0), jnp.zeros_like(y.offset)
    probes = [y.with_parts(unravel(jnp.zeros_like(flat).at[i].set(1.0)), no_y0, no_offset) for i in range(P)]
    for kind, nuisance in enumerate((no_y0, no_offset)):  # the layout's order: y0, then offset
        pos, used = layout.arrays(kind)
        for j in range(pos.shape[1]):
            v = nuisance.at[pos[used[:, j], j]].set(1.0)
            probes.append(y.with_parts(no_shared, *((v, no_offset) if kind == 0 else (no_y0, v))))
    r = f_info.residual.reshape(L, -1)
    template = jax.tree_util.tree_map(jnp.zeros_like, y)
    if not probes:
        return _State(template, r, jnp.zeros((*r.shape, 0), r.dtype), jnp.zeros((*r.shape, 0), r.dtype))
    batch = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *probes)
    cols = jax.vmap(f_info.jac.mv)(batch)  # (P + k, L n)
    cols = cols.reshape(len(probes), L, -1)
    S = jnp.moveaxis(cols[:P], 0, -1)
    U = jnp.moveaxis(cols[P:], 0, -1)
    return _State(template, r, S, U)


class BlockDampedNewtonDescent(optx.AbstractDescent):
    """The damped Newton (Levenberg-Marquardt) step, `lambda = 1 / step_size` as in
    `optx.DampedNewtonDescent`, solved block by block (module docstring). The variables `y`
    are a variables record (`AbstractVariables`: nuisances `y.y0`, `y.offset` in the vector
    order of `layout`, the rest `y.shared`)."""

    layout: Layout

    def init(self, y, f_info_struct):
        L = self.layout.n_logs
        n = f_info_struct.residual.shape[0] // L
        P = ravel_pytree(y.shared)[0].shape[0]
        k = sum(self.layout.arrays(i)[0].shape[1] for i in range(2))
        dtype = f_info_struct.residual.dtype
        template = jax.tree_util.tree_map(jnp.zeros_like, y)
        return _State(template, jnp.zeros((L, n), dtype), jnp.zeros((L, n, P), dtype), jnp.zeros((L, n, k), dtype))

    def query(self, y, f_info, state):
        """Read the blocks of the Jacobian at `y` from `f_info.jac` (`read_blocks`)."""
        del state
        return read_blocks(self.layout, y, f_info)

    def step(self, step_size, state):
        pred = step_size > jnp.finfo(step_size.dtype).eps
        lam = jnp.where(pred, 1 / jnp.where(pred, step_size, 1), jnp.finfo(step_size.dtype).max)
        used = np.concatenate([self.layout.arrays(i)[1] for i in range(2)], axis=1)
        d_shared, d_local = damped_block_solve(state.r, state.S, state.U, used, lam)
        ok = jnp.all(jnp.isfinite(d_shared)) & jnp.all(jnp.isfinite(d_local))
        diff = _to_tree(state.template, -d_shared, -d_local, self.layout)
        return diff, optx.RESULTS.where(ok, optx.RESULTS.successful, optx.RESULTS.singular)


def _to_tree(template, d_shared, d_local, layout: Layout):
    """The flat step `(d_shared, d_local)` in the variables' structure."""
    _, unravel = ravel_pytree(template.shared)
    parts = []
    col = 0
    for kind, zeros in enumerate((template.y0, template.offset)):
        pos, used = layout.arrays(kind)
        k = pos.shape[1]
        parts.append(zeros.at[pos[used]].set(d_local[:, col : col + k][used]) if k else zeros)
        col += k
    return template.with_parts(unravel(d_shared), *parts)


def damped_block_solve(r, S, U, used, lam):
    """`d` minimising `||J d - r||^2 + lam ||d||^2` for the block-arrow `J = [S | blockdiag(U_l)]`
    (`r` `(L, n)`, `S` `(L, n, P)`, `U` `(L, n, k)`); returns `(d_shared (P,), d_local (L, k))`.
    Unused slots (`used` False, zero columns) get 0."""
    L, n, P = S.shape
    k = U.shape[2]
    s = jnp.sqrt(lam)
    dtype = r.dtype
    if k:
        # per log: [U_l; D_l] = Q_l R_l with D_l = sqrt(lam) on used slots, 1 on padding
        D = jnp.where(jnp.asarray(used), s, 1.0).astype(dtype)
        A = jnp.concatenate([U, jax.vmap(jnp.diag)(D)], axis=1)  # (L, n + k, k)
        B = jnp.concatenate([S, jnp.zeros((L, k, P), dtype)], axis=1)  # (L, n + k, P)
        b = jnp.concatenate([r, jnp.zeros((L, k), dtype)], axis=1)  # (L, n + k)
        Q, R = jnp.linalg.qr(A)  # reduced: (L, n + k, k), (L, k, k)
        F = jnp.einsum("lmk,lmp->lkp", Q, B)
        f = jnp.einsum("lmk,lm->lk", Q, b)
        E = B - jnp.einsum("lmk,lkp->lmp", Q, F)
        e = b - jnp.einsum("lmk,lk->lm", Q, f)
    else:
        E, e = S, r
    if P:
        M = jnp.concatenate([E.reshape(-1, P), s * jnp.eye(P, dtype=dtype)], axis=0)
        v = jnp.concatenate([e.reshape(-1), jnp.zeros(P, dtype)])
        Qg, Rg = jnp.linalg.qr(M)
        d_shared = jsl.solve_triangular(Rg, Qg.T @ v, lower=False)
    else:
        d_shared = jnp.zeros((0,), dtype)
    if k:
        rhs = f - jnp.einsum("lkp,p->lk", F, d_shared)
        d_local = jax.vmap(lambda R_, x: jsl.solve_triangular(R_, x, lower=False))(R, rhs)
        d_local = jnp.where(jnp.asarray(used), d_local, 0.0)
    else:
        d_local = jnp.zeros((L, 0), dtype)
    return d_shared, d_local


class BlockLevenbergMarquardt(optx.AbstractGaussNewton):
    """`optx.LevenbergMarquardt` (same loop, trust region and termination) with the damped
    step solved block by block (`BlockDampedNewtonDescent`): linear in the number of logs.
    `layout`: `Layout.of(problem)`."""

    rtol: float
    atol: float
    norm: Callable = eqx.field(static=True)
    descent: BlockDampedNewtonDescent
    search: optx.ClassicalTrustRegion
    verbose: Callable = eqx.field(static=True)

    def __init__(self, rtol: float, atol: float, layout: Layout, norm: Callable = optx.max_norm):
        self.rtol, self.atol, self.norm = rtol, atol, norm
        self.descent = BlockDampedNewtonDescent(layout)
        self.search = optx.ClassicalTrustRegion()
        self.verbose = optx.LevenbergMarquardt(rtol, atol).verbose

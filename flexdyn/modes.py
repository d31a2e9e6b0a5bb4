"""Clamped-mass assumed modes of an Euler-Bernoulli link.

A flexible link is discretised by the eigenfunctions of a uniform beam that is
clamped at its root (the joint frame) and carries a rigid body at its tip: the
*clamped-mass* boundary conditions of paper 002 (eq. 16-18, 21-23) and paper 004
(eq. 27-31, 37-41). The tip body is described by its mass `M`, its first moment
`S` (mass times the distance of its centre of mass beyond the tip, along the
undeformed link axis) and its rotary inertia `J` about the tip point; it adds
the boundary conditions at `x = l`

    EI v'''(l) = -omega^2 (M v(l) + S v'(l))      (shear force)
    EI v''(l)  = +omega^2 (S v(l) + J v'(l))      (bending moment)

With `S = 0` these are paper 002 eq. (17)-(18); `S` is paper 004's `M_DE`
(offset distal mass). The frequency equation of paper 002 eq. (23) is the
special case `S = 0`; the tests check our determinant against it.

**Numerically stable form.** Instead of the textbook basis `cos, sin, cosh,
sinh` (whose cancellations lose about `0.43 * beta*l` digits, i.e. all of
them by the tenth mode) we use

    phi(xi) = a cos(lam xi) + b sin(lam xi) + c exp(-lam xi) + d exp(lam (xi - 1))

with `xi = x / l` and `lam = beta * l`. Every term is O(1) on [0, 1]. The two
root conditions eliminate `a, b`; the two tip conditions leave a 2x2 matrix
`G(lam)` whose determinant is the frequency equation (rows scaled by positive
factors, which does not move its roots).

**Roots** are bracketed by a sign scan on a fixed grid and refined by
bisection; all `n` lowest roots lie below the `n`-th clamped-free root
`(n - 1/2) pi` (adding tip mass and inertia only lowers them), so the scan
range is known in advance. The root is made differentiable with respect to
the tip-load ratios by the implicit-function theorem (one Newton step on a
`stop_gradient`-ed root carries `d lam / d p = -F_p / F_lam`), so mode shapes
follow payload, hub mass, `rho` under `jax.grad`. `EI` does not change the
shapes (only the frequencies, `omega = lam^2 / l^2 sqrt(EI / rho)`, eq. 41).

**Normalisation** (our choice, written down as the issue asks): each shape is
dimensionless with unit mean square over the link,

    (1/l) int_0^l phi_j(x)^2 dx = 1,      phi_j(l) > 0,

so the modal coordinate `q_j` is in metres (the RMS deflection of that mode)
and `rho int phi_j^2 dx = m` (the link mass). This is the dimensionally
consistent reading of paper 004 eq. (40) (`N_ij` such that the generalised
mass is the link mass), under which its eq. (46), `k_ij = omega_ij^2 m_i`,
holds exactly for a link without tip load.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

# Gauss-Legendre nodes/weights on [0, 1]; 96 points integrate products of two
# shapes exactly to double precision up to lam ~ 60 (about the 20th mode).
_GL_N = 96
_gl_x, _gl_w = np.polynomial.legendre.leggauss(_GL_N)
GAUSS_X = 0.5 * (_gl_x + 1.0)
GAUSS_W = 0.5 * _gl_w

MAX_MODES = 18


def _basis(lam, xi, k: int):
    """k-th derivative w.r.t. `xi` of the four basis functions, divided by lam^k.

    Returns an array of shape `xi.shape + (4,)`.
    """
    phase = lam * xi + 0.5 * np.pi * k
    return jnp.stack(
        [
            jnp.cos(phase),
            jnp.sin(phase),
            (-1.0) ** k * jnp.exp(-lam * xi),
            jnp.exp(lam * (xi - 1.0)),
        ],
        axis=-1,
    )


def _clamped_combinations(lam):
    """(2, 4) matrix mapping (c, d) to (a, b, c, d) with phi(0) = phi'(0) = 0."""
    e = jnp.exp(-lam)
    #   a = -c - d e,  b = c - d e
    return jnp.array([[-1.0, 1.0, 1.0, 0.0], [-e, -e, 0.0, 1.0]])


def _row_scales(lam, mu, sigma, iota, xp):
    """The positive (for physical tip loads) factors `_tip_rows` divides its shear and
    moment rows by."""
    return 1.0 + lam * mu + lam**2 * xp.abs(sigma), 1.0 + lam**2 * xp.abs(sigma) + lam**3 * iota


def _tip_rows(lam, mu, sigma, iota, xp):
    """Entries `(shear_c, shear_d, moment_c, moment_d)` of the 2x2 tip-boundary matrix
    G(lam) acting on (c, d), elementwise (works with NumPy or jax.numpy as `xp`).

    `mu = M / (rho l)`, `sigma = S / (rho l^2)`, `iota = J / (rho l^3)`. At `xi = 1` the
    clamped combinations `g1 = -cos + sin + exp(-lam xi)` and
    `g2 = -e cos - e sin + exp(lam (xi - 1))` (`e = exp(-lam)`) and their scaled
    derivatives `g^(k) / lam^k` are written out explicitly.
    """
    c, s, e = xp.cos(lam), xp.sin(lam), xp.exp(-lam)
    g1 = (-c + s + e, s + c - e, c - s + e, -s - c - e)
    g2 = (1.0 - e * (c + s), 1.0 + e * (s - c), 1.0 + e * (c + s), 1.0 + e * (c - s))
    shear_scale, moment_scale = _row_scales(lam, mu, sigma, iota, xp)

    def shear(g):
        return (g[3] + lam * mu * g[0] + lam**2 * sigma * g[1]) / shear_scale

    def moment(g):
        return (g[2] - lam**2 * sigma * g[0] - lam**3 * iota * g[1]) / moment_scale

    return shear(g1), shear(g2), moment(g1), moment(g2)


def frequency_function(lam, mu, sigma, iota, xp=jnp):
    """Scaled clamped-mass frequency equation F(lam) = det G(lam); its zeros are the
    `beta*l`. Without tip load `F = -2 (1 + cos lam cosh lam) / cosh-like scale`, the
    cantilever equation (a positive row scaling does not move the roots)."""
    s1, s2, m1, m2 = _tip_rows(lam, mu, sigma, iota, xp)
    return s1 * m2 - s2 * m1


def _scan_grid(n_modes: int) -> np.ndarray:
    top = (n_modes + 0.5) * np.pi
    return np.concatenate([np.geomspace(1e-3, 0.5, 200, endpoint=False), np.arange(0.5, top, 0.004)])


_SCAN_BLOCK = 128  # grid cells evaluated together in the bracketing scan
_BISECTIONS = 60  # halvings of a 0.004-wide bracket: far below one ulp, then Newton polishes


def _grid_terms(lam: np.ndarray) -> np.ndarray:
    """`(len(lam), 9)` columns `D` with `F(lam) * shear_scale * moment_scale = D @ [1, sigma,
    iota, mu, mu sigma, mu iota, sigma, sigma^2, sigma iota]`: the unscaled frequency
    equation is bilinear in `(1, mu, sigma)` (shear row) and `(1, sigma, iota)` (moment
    row), and its transcendental parts depend on `lam` only (`_tip_rows`), so on a fixed
    grid they are computed once, in NumPy."""
    c, s, e = np.cos(lam), np.sin(lam), np.exp(-lam)
    g1 = (-c + s + e, s + c - e, c - s + e, -s - c - e)
    g2 = (1.0 - e * (c + s), 1.0 + e * (s - c), 1.0 + e * (c + s), 1.0 + e * (c - s))

    def shear(g):  # coefficients of 1, mu, sigma
        return (g[3], lam * g[0], lam**2 * g[1])

    def moment(g):  # coefficients of 1, sigma, iota
        return (g[2], -(lam**2) * g[0], -(lam**3) * g[1])

    s1, s2, m1, m2 = shear(g1), shear(g2), moment(g1), moment(g2)
    return np.stack([s1[a] * m2[b] - s2[a] * m1[b] for a in range(3) for b in range(3)], axis=-1)


@functools.cache
def _grid_and_terms(n_modes: int) -> tuple[np.ndarray, np.ndarray]:
    grid = _scan_grid(n_modes)
    return grid, _grid_terms(grid)


def _scan_blocks(n_modes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scan grid as `(C, K + 1)` blocks of consecutive points (each block's last point
    is the next block's first), their `_grid_terms` `(C, K + 1, 9)`, and the `(C, K)` mask
    of real cells (the last block is padded by repeating the grid's last point)."""
    grid, terms = _grid_and_terms(n_modes)
    cells = grid.size - 1
    blocks = -(-cells // _SCAN_BLOCK)
    pad = blocks * _SCAN_BLOCK + 1 - grid.size
    padded = np.concatenate([grid, np.full(pad, grid[-1])])
    padded_terms = np.concatenate([terms, np.repeat(terms[-1:], pad, axis=0)])
    index = np.arange(blocks)[:, None] * _SCAN_BLOCK + np.arange(_SCAN_BLOCK + 1)[None, :]
    valid = (np.arange(blocks * _SCAN_BLOCK) < cells).reshape(blocks, _SCAN_BLOCK)
    return padded[index], padded_terms[index], valid


def _host_roots(n_modes: int, mu, sigma, iota) -> np.ndarray:
    """`_bracket_and_bisect` in NumPy on the host, vectorised over any batch of tip loads
    (called through `jax.pure_callback` on the CPU, where it compiles to a call instead of
    a loop). The same grid, the same sign rule, the same bisection."""
    mu, sigma, iota = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (mu, sigma, iota)))
    batch = mu.shape
    mu, sigma, iota = (v.reshape(-1) for v in (mu, sigma, iota))
    grid, terms = _grid_and_terms(n_modes)
    out = np.full((mu.size, n_modes), np.nan)
    for k in range(0, mu.size, 1024):  # rows per block: a (1024, grid) array at a time
        m, s, j = mu[k : k + 1024], sigma[k : k + 1024], iota[k : k + 1024]
        monomials = np.stack([np.ones_like(m), s, j, m, m * s, m * j, s, s**2, s * j], axis=1)
        with np.errstate(invalid="ignore", over="ignore"):
            f = monomials @ terms.T
            shear_scale, moment_scale = _row_scales(grid, m[:, None], s[:, None], j[:, None], np)
            f = f * np.sign(shear_scale * moment_scale)
        finite = np.all(np.isfinite(f), axis=1)
        change = np.sign(f[:, :-1]) * np.sign(f[:, 1:]) <= 0
        rank = np.cumsum(change, axis=1)
        ok = finite & (rank[:, -1] >= n_modes)
        first = np.stack([np.argmax(rank >= i, axis=1) for i in range(1, n_modes + 1)], axis=1)
        lo, hi = grid[first], grid[first + 1]
        args = (m[:, None], s[:, None], j[:, None])
        with np.errstate(invalid="ignore", over="ignore"):
            flo = frequency_function(lo, *args, xp=np)
            for _ in range(_BISECTIONS):
                mid = 0.5 * (lo + hi)
                fmid = frequency_function(mid, *args, xp=np)
                left = np.sign(fmid) * np.sign(flo) <= 0
                lo, hi, flo = np.where(left, lo, mid), np.where(left, mid, hi), np.where(left, flo, fmid)
        out[k : k + 1024] = np.where(ok[:, None], 0.5 * (lo + hi), np.nan)
    return out.reshape(batch + (n_modes,))


def _bracket_and_bisect(n_modes: int, mu, sigma, iota):
    """First `n_modes` roots of `frequency_function` for scalar tip-load ratios: the first
    `n_modes` sign changes on `_scan_grid`, each bisected `_BISECTIONS` times. NaN where
    fewer than `n_modes` changes are found or `F` is not finite on the grid.

    On the grid the sign of `F` is that of `_grid_terms @ monomials` times the sign of the
    (positive for physical loads) row scales: a matrix-vector product, no transcendental
    function per point. The grid is scanned in blocks of `_SCAN_BLOCK` cells (a
    `lax.scan`), so that under `vmap` the memory is `batch x _SCAN_BLOCK`, not `batch x
    grid`. The bisection evaluates `frequency_function` itself."""
    points, terms, valid = _scan_blocks(n_modes)
    slots = jnp.arange(1, n_modes + 1)  # change number k (from 1) brackets root k
    monomials = jnp.stack([1.0, sigma, iota, mu, mu * sigma, mu * iota, sigma, sigma**2, sigma * iota])

    def block(carry, x):
        count, lo, hi, finite = carry
        pts, D, ok = x
        shear_scale, moment_scale = _row_scales(pts, mu, sigma, iota, jnp)
        f = (D @ monomials) * jnp.sign(shear_scale * moment_scale)
        finite = finite & jnp.all(jnp.isfinite(f))
        change = (jnp.sign(f[:-1]) * jnp.sign(f[1:]) <= 0) & ok
        rank = count + jnp.cumsum(change)  # changes up to each cell, along the whole grid
        # The cell of change number k, if it is in this block; while change k is not
        # found, its bracket is overwritten by every block (it ends as the right one).
        first = jnp.minimum(jnp.sum(rank[None, :] < slots[:, None], axis=1), change.shape[0] - 1)
        open_ = count < slots
        lo = jnp.where(open_, pts[first], lo)
        hi = jnp.where(open_, pts[first + 1], hi)
        return (count + jnp.sum(change), lo, hi, finite), None

    zero = jnp.zeros(n_modes, dtype=mu.dtype)
    init = (jnp.zeros((), dtype=int), zero, zero, jnp.all(jnp.isfinite(monomials)))
    xs = (jnp.asarray(points), jnp.asarray(terms), jnp.asarray(valid))
    (count, lo, hi, finite), _ = jax.lax.scan(block, init, xs)

    def bisect(_, carry):
        lo, hi, flo = carry
        mid = 0.5 * (lo + hi)
        fmid = frequency_function(mid, mu, sigma, iota)
        left = jnp.sign(fmid) * jnp.sign(flo) <= 0
        return jnp.where(left, lo, mid), jnp.where(left, mid, hi), jnp.where(left, flo, fmid)

    flo = frequency_function(lo, mu, sigma, iota)
    lo, hi, _ = jax.lax.fori_loop(0, _BISECTIONS, bisect, (lo, hi, flo))
    return jnp.where((count >= n_modes) & finite, 0.5 * (lo + hi), jnp.nan)


def clamped_mass_roots(n_modes: int, mu, sigma=0.0, iota=0.0) -> Float[Array, " n_modes"]:
    """First `n_modes` roots `lam = beta*l` of the clamped-mass frequency equation.

    **Arguments:**
    - `mu`: tip mass / link mass, `M / (rho l)`.
    - `sigma`: tip first moment / (link mass * l), `S / (rho l^2)`.
    - `iota`: tip rotary inertia about the tip point / (link mass * l^2), `J / (rho l^3)`.

    The roots are bracketed by a sign scan on a fixed grid and bisected (on the CPU in
    NumPy through `jax.pure_callback`, vectorised over a `vmap`ped batch: a compiled
    scan costs ~0.4 s more compilation in every program that assembles a flexible link;
    on an accelerator in JAX, with no round trip to the host), then polished by Newton
    steps. The last
    Newton step carries the derivative `d lam / d p = -F_p / F_lam` (implicit-function
    theorem), so the roots are differentiable in `mu, sigma, iota`.
    """
    if not 1 <= n_modes <= MAX_MODES:
        raise ValueError(f"n_modes must be between 1 and {MAX_MODES}, got {n_modes}")
    mu, sigma, iota = (jnp.asarray(v, dtype=float) for v in (mu, sigma, iota))
    frozen = [jax.lax.stop_gradient(v) for v in (mu, sigma, iota)]
    if jax.default_backend() == "cpu":  # a host call: compiles in no time, vectorised over vmap
        shape = jax.ShapeDtypeStruct(jnp.broadcast_shapes(mu.shape, sigma.shape, iota.shape) + (n_modes,), mu.dtype)
        lam0 = jax.pure_callback(
            lambda m, s, j: _host_roots(n_modes, m, s, j).astype(shape.dtype), shape, *frozen, vmap_method="expand_dims"
        )
    else:  # on an accelerator: no round trip to the host
        lam0 = jnp.vectorize(lambda m, s, j: _bracket_and_bisect(n_modes, m, s, j), signature="(),(),()->(n)")(*frozen)
    lam0 = eqx.error_if(
        lam0,
        ~jnp.all(jnp.isfinite(lam0)),
        "clamped-mass frequency equation: fewer roots than modes were found "
        "(tip-load ratios not finite or not physical)",
    )
    fun = jax.vmap(frequency_function, in_axes=(0, None, None, None))
    dfun = jax.vmap(jax.grad(frequency_function), in_axes=(0, None, None, None))
    for _ in range(2):  # polish the bisection result to full precision
        lam0 = lam0 - fun(lam0, *frozen) / dfun(lam0, *frozen)
    lam0 = jax.lax.stop_gradient(lam0)
    # Newton step on the converged root: value ~ lam0, derivative -F_p / F_lam.
    return lam0 - fun(lam0, mu, sigma, iota) / dfun(lam0, *frozen)


def _shape_coefficients(lam, mu, sigma, iota):
    """Coefficients (a, b, c, d) of the un-normalised shape for one root."""
    s1, s2, m1, m2 = _tip_rows(lam, mu, sigma, iota, jnp)
    use_first = s1**2 + s2**2 >= m1**2 + m2**2
    row = jnp.where(use_first, jnp.stack([s1, s2]), jnp.stack([m1, m2]))
    cd = jnp.array([row[1], -row[0]])
    return cd @ _clamped_combinations(lam)


def mode_shapes(n_modes: int, mu, sigma=0.0, iota=0.0):
    """Roots and normalised shape coefficients of the first `n_modes` clamped-mass modes.

    Returns `(lam, coef)` with `lam` of shape `(n_modes,)` and `coef` of shape
    `(n_modes, 4)`: `phi_j(xi) = basis(lam_j, xi) @ coef_j` with the normalisation
    of the module docstring (unit mean square on [0, 1], positive at the tip).
    """
    lam = clamped_mass_roots(n_modes, mu, sigma, iota)
    coef = jax.vmap(_shape_coefficients, in_axes=(0, None, None, None))(lam, mu, sigma, iota)
    # Normalise: (int_0^1 phi^2 dxi) = 1 and phi(1) > 0.
    values = jax.vmap(lambda lm, c: _basis(lm, jnp.asarray(GAUSS_X), 0) @ c)(lam, coef)
    mean_square = values**2 @ jnp.asarray(GAUSS_W)
    tip = jax.vmap(lambda lm, c: _basis(lm, jnp.ones(()), 0) @ c)(lam, coef)
    scale = jnp.sign(tip) / jnp.sqrt(mean_square)
    return lam, coef * scale[:, None]


def evaluate_shapes(lam, coef, xi, derivative: int = 0):
    """`d^k phi_j / dxi^k` at the points `xi` (dimensionless), shape `xi.shape + (n_modes,)`.

    Divide by `l^k` for the derivative with respect to `x` in metres.
    """
    xi = jnp.asarray(xi, dtype=float)

    def one(lm, c):
        return lm**derivative * (_basis(lm, xi, derivative) @ c)

    return jnp.moveaxis(jax.vmap(one)(lam, coef), 0, -1)

"""Linearisation about an operating point and modal analysis.

`linearize` returns the state-space model `x_dot = A x + B u`, `y = C x + D u` of
the deviations `x = y - y0`, `u = torque - torque0` (exact Jacobians by forward-mode
autodiff). `modal_analysis` gives the undamped natural frequencies and mode shapes
from `K v = omega^2 M v` (with `K` the stiffness of the generalised forces at
rest, including gravity) and the damped frequencies and damping ratios from the
eigenvalues of `A`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .chain import AssembledChain, Chain, accelerations, assemble, generalised_forces, mass_matrix


class LinearModel(eqx.Module):
    """State-space model about an operating point (SI units).

    States `x = [Q, Q_dot] - y0` (names in `state_names`), inputs `u` = joint torques
    (N m) - `torque0`, outputs `y` = joint angles (rad) and tip deflections (m) of
    every link (names in `output_names`). `residual` is `Q_ddot` at the operating
    point (zero at an equilibrium; otherwise the model is affine).
    """

    A: Float[Array, "2n 2n"]
    B: Float[Array, "2n m"]
    C: Float[Array, "p 2n"]
    D: Float[Array, "p m"]
    y0: Float[Array, " 2n"]
    torque0: Float[Array, " m"]
    residual: Float[Array, " n"]
    state_names: tuple[str, ...] = eqx.field(static=True)
    output_names: tuple[str, ...] = eqx.field(static=True)

    def to_numpy(self) -> dict[str, np.ndarray]:
        """`{'A', 'B', 'C', 'D'}` as plain NumPy arrays (e.g. for `scipy.signal` or MATLAB)."""
        return {k: np.asarray(getattr(self, k)) for k in ("A", "B", "C", "D")}


def _output_map(asm: AssembledChain):
    lay = asm.layout
    n = lay.n_dof
    rows, names = [], []
    for i, lm in enumerate(asm.links):
        r = np.zeros(2 * n)
        r[lay.theta[i]] = 1.0
        rows.append(jnp.asarray(r))
        names.append(f"theta{i + 1}")
    for i, lm in enumerate(asm.links):
        if lay.modal[i]:
            idx = jnp.asarray(lay.modal[i])
            rows.append(jnp.zeros(2 * n).at[idx].set(lm.tip_shape))
            names.append(f"tip{i + 1}")
    return jnp.stack(rows), tuple(names)


@eqx.filter_jit
def linearize(chain: Chain | AssembledChain, y0=None, torque0=None) -> LinearModel:
    """Linearise the chain about the state `y0 = [Q, Q_dot]` (default: all zero) and
    torques `torque0` (default zero)."""
    asm = assemble(chain)
    lay = asm.layout
    n, m = lay.n_dof, len(lay.actuated)
    y0 = jnp.zeros(2 * n) if y0 is None else jnp.asarray(y0, dtype=float)
    torque0 = jnp.zeros(m) if torque0 is None else jnp.asarray(torque0, dtype=float)
    if y0.shape != (2 * n,):
        raise ValueError(f"linearize: y0 expected shape ({2 * n},), got {y0.shape}")

    def qdd(y, tau):
        return accelerations(asm, y[:n], y[n:], tau)

    Jy, Ju = jax.jacfwd(qdd, argnums=(0, 1))(y0, torque0)
    A = jnp.block([[jnp.zeros((n, n)), jnp.eye(n)], [Jy]])
    B = jnp.concatenate([jnp.zeros((n, m)), Ju])
    C, names = _output_map(asm)
    D = jnp.zeros((C.shape[0], m))
    state_names = tuple(lay.names) + tuple(f"d{k}" for k in lay.names)
    return LinearModel(A, B, C, D, y0, torque0, qdd(y0, torque0), state_names, names)


class Modes(eqx.Module):
    """Result of `modal_analysis` (ascending frequency).

    - `natural_frequency`: undamped, Hz, from `K v = omega^2 M v` (rigid-body modes
      of an unrestrained chain appear as exactly 0: omega^2 below the eigensolver's
      round-off, `n eps max omega^2`, counts as zero).
    - `shapes`: the corresponding generalised-coordinate vectors (columns),
      mass-normalised (`v^T M v = 1`).
    """

    natural_frequency: Array
    shapes: Array
    names: tuple[str, ...] = eqx.field(static=True)


@eqx.filter_jit
def stiffness_matrix(chain: Chain | AssembledChain, Q0) -> Float[Array, "n n"]:
    """Tangent stiffness `K = -d(F - dV/dQ)/dQ` at rest (bending, joint springs, gravity)."""
    asm = assemble(chain)
    n = asm.layout.n_dof
    zero_qd = jnp.zeros(n)
    zero_tau = jnp.zeros(len(asm.layout.actuated))
    return -jax.jacfwd(lambda Q: generalised_forces(asm, Q, zero_qd, zero_tau))(jnp.asarray(Q0, dtype=float))


@eqx.filter_jit
def modal_analysis(chain: Chain | AssembledChain, Q0=None) -> Modes:
    """Undamped natural frequencies and mode shapes about the configuration `Q0`
    (default zero; it should be an equilibrium at rest). Pure JAX: jit- and grad-able.
    About a steady motion (a link spinning at a constant rate), use the eigenvalues of
    `linearize(chain, y0).A` with the rates in `y0` instead: they carry the centrifugal
    and gyroscopic terms (and, with `FlexibleLink(geometric_stiffening=True)`, the
    centrifugal stiffening; `notebooks/geometric_stiffening.ipynb`)."""
    asm = assemble(chain)
    n = asm.layout.n_dof
    Q0 = jnp.zeros(n) if Q0 is None else jnp.asarray(Q0, dtype=float)
    M = mass_matrix(asm, Q0)
    K = stiffness_matrix(asm, Q0)
    K = 0.5 * (K + K.T)
    L = jnp.linalg.cholesky(M)
    Linv = jax.scipy.linalg.solve_triangular(L, jnp.eye(n), lower=True)
    w2, V = jnp.linalg.eigh(Linv @ K @ Linv.T)
    # A rigid-body mode's omega^2 is zero only up to the eigensolver's round-off, about
    # n eps max|omega^2| (it came out as ~3e-6 Hz); below that it is reported as exactly 0.
    tol = n * jnp.finfo(w2.dtype).eps * jnp.max(jnp.abs(w2))
    positive = w2 > tol
    # sqrt with a finite derivative at rigid-body (zero) modes
    natural = jnp.where(positive, jnp.sqrt(jnp.where(positive, w2, 1.0)), 0.0) / (2 * jnp.pi)
    return Modes(natural, Linv.T @ V, asm.layout.names)


def damped_modes(model: LinearModel) -> tuple[np.ndarray, np.ndarray]:
    """Damped natural frequencies (Hz) and damping ratios from the eigenvalues of
    `model.A`, one per complex pair or real eigenvalue, ascending by |eigenvalue|.
    Host-side NumPy (not jittable)."""
    ev = np.linalg.eigvals(np.asarray(model.A))
    ev = ev[np.imag(ev) >= 0]
    mag = np.abs(ev)
    order = np.argsort(mag)
    ev, mag = ev[order], mag[order]
    safe = np.where(mag > 0, mag, 1.0)
    zeta = np.where(mag > 0, -np.real(ev) / safe, 0.0)
    return np.abs(np.imag(ev)) / (2 * np.pi), zeta

"""Linearisation about an operating point and modal analysis.

`linearize` returns the state-space model `x_dot = A x + B u`, `y = C x + D u` of
the deviations `x = y - y0`, `u = torque - torque0` (exact Jacobians by forward-mode
autodiff). `modal_analysis` gives the undamped natural frequencies and mode shapes
from `K v = omega^2 M v` (with `K` the stiffness of the generalised forces at
rest, including gravity) and the damped frequencies and damping ratios from the
eigenvalues of `A`.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._checks import warn_if_single_precision
from .chain import AssembledChain, Chain, accelerations, assemble, check_coordinates, generalised_forces, mass_matrix


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
      round-off, `n eps max omega^2`, counts as zero). **Negative for an unstable mode**
      (omega^2 < 0: the configuration is not a stable equilibrium, e.g. a pendulum
      upright, or a slender link hanging under gravity without
      `geometric_stiffening`): `-sqrt(-omega^2) / (2 pi)`, the mode growing as
      `exp(2 pi |f| t)` (the convention of finite-element codes), not 0 Hz like a free
      rotation. `unstable` says whether any is.
    - `shapes`: the corresponding generalised-coordinate vectors (columns),
      mass-normalised (`v^T M v = 1`).
    """

    natural_frequency: Array
    shapes: Array
    names: tuple[str, ...] = eqx.field(static=True)

    @property
    def unstable(self) -> Array:
        """Whether any mode is unstable (negative `natural_frequency`): the configuration
        analysed is not a stable equilibrium."""
        return jnp.any(self.natural_frequency < 0)


#: `symmetric_eigh`: eigenvalues closer than this many `n eps max|lambda|` count as one
#: (degenerate) in the derivative
DEGENERATE_ROUNDOFF = 100.0


@jax.custom_jvp
def symmetric_eigh(A):
    """`jnp.linalg.eigh` of a symmetric matrix, with a derivative that stays finite where
    eigenvalues coincide.

    The derivative of an eigenvector, `dv_i = sum_{j != i} v_j (v_j^T dA v_i) / (lambda_i
    - lambda_j)` (first-order perturbation theory), is undefined inside a degenerate
    eigenspace, where any rotation of the basis is an eigenbasis: JAX's own rule divides
    by zero there, and a reverse pass multiplies the resulting inf by a zero cotangent,
    which makes the gradient of every shape NaN, not only the degenerate ones (seen: an
    arm with two free joints has two rigid-body modes at omega^2 = 0, and the gradient
    of its flexible mode's tip deflection w.r.t. the payload came out NaN; the finite
    difference is -2.58). Here the pairs closer than `DEGENERATE_ROUNDOFF n eps
    max|lambda|` get no mixing term: a vector outside the degenerate space has its exact
    derivative; one inside it, the derivative of one admissible choice of basis."""
    w, V = jnp.linalg.eigh(A)
    return w, V


@symmetric_eigh.defjvp
def _symmetric_eigh_jvp(primals, tangents):
    (A,), (dA,) = primals, tangents
    w, V = jnp.linalg.eigh(A)
    n = w.shape[-1]
    dA = 0.5 * (dA + dA.T)
    X = V.T @ dA @ V
    gap = w[None, :] - w[:, None]  # gap[i, j] = lambda_j - lambda_i
    tol = DEGENERATE_ROUNDOFF * n * jnp.finfo(w.dtype).eps * jnp.max(jnp.abs(w))
    apart = jnp.abs(gap) > tol
    F = jnp.where(apart, 1.0 / jnp.where(apart, gap, 1.0), 0.0)
    return (w, V), (jnp.diagonal(X), V @ (F * X))


@eqx.filter_jit
def stiffness_matrix(chain: Chain | AssembledChain, Q0) -> Float[Array, "n n"]:
    """Tangent stiffness `K = -d(F - dV/dQ)/dQ` at rest (bending, joint springs, gravity)."""
    asm = assemble(chain)
    n = asm.layout.n_dof
    check_coordinates(asm.layout, Q0, "stiffness_matrix")
    zero_qd = jnp.zeros(n)
    zero_tau = jnp.zeros(len(asm.layout.actuated))
    return -jax.jacfwd(lambda Q: generalised_forces(asm, Q, zero_qd, zero_tau))(jnp.asarray(Q0, dtype=float))


def modal_analysis(chain: Chain | AssembledChain, Q0=None) -> Modes:
    """Undamped natural frequencies and mode shapes about the configuration `Q0`
    (default zero; it should be an equilibrium at rest). Pure JAX: jit- and grad-able.
    About a steady motion (a link spinning at a constant rate), use the eigenvalues of
    `linearize(chain, y0).A` with the rates in `y0` instead: they carry the centrifugal
    and gyroscopic terms (and, with `FlexibleLink(geometric_stiffening=True)`, the
    centrifugal stiffening; `notebooks/geometric_stiffening.ipynb`).

    In single precision (`jax_enable_x64` off) it warns: the mode shapes, `M`, `K` and
    the eigenproblem in float32 give frequencies with relative errors ~1e-4 (paper 004's
    arm: up to 2.2e-4)."""
    warn_if_single_precision(
        "modal_analysis",
        "the frequencies carry relative errors of ~1e-4 (paper 004's arm: up to 2.2e-4), "
        "from the mode shapes, M, K and the eigenproblem in float32",
        stacklevel=3,
    )
    modes, force, K = _modal_analysis(chain, Q0)
    if not isinstance(force, jax.core.Tracer):
        _warn_if_not_at_rest(modes.names, np.asarray(force), np.asarray(K))
    return modes


def _warn_if_not_at_rest(names, force: np.ndarray, K: np.ndarray) -> None:
    """Warn when `Q0` is not (near) an equilibrium at rest: the generalised force there
    `force` (gravity, springs, bending) pushes along a direction without restoring
    stiffness (`force` not in the range of `K`), or the equilibrium its linearisation
    predicts, `Q0 + K^+ force`, is more than `REST_ANGLE` away in an angle (a pendulum
    under gravity analysed horizontal would give `[0.]`, which reads as a free rotation). Modal
    coordinates off their rest value leave the linear model's `K` as it is, and a
    simulation's final state, still ringing by a fraction of a millimetre, is no mistake."""
    scale = float(np.max(np.abs(K), initial=0.0))
    worst = int(np.argmax(np.abs(force)))
    if not abs(float(force[worst])) > 1e-6 * scale:
        return
    delta = np.linalg.lstsq(K, force, rcond=1e-12)[0]
    unbalanced = force - K @ delta
    angles = [i for i, n in enumerate(names) if not n.startswith("q")]
    far = [i for i in angles if abs(delta[i]) > REST_ANGLE]
    if np.max(np.abs(unbalanced)) > 1e-6 * abs(float(force[worst])):
        why = "along a direction without restoring stiffness"
    elif far:
        worst = max(far, key=lambda i: abs(delta[i]))
        why = f"whose rest, to first order, is {np.degrees(delta[worst]):+.3g} deg away in {names[worst]}"
    else:
        return
    warnings.warn(
        f"modal_analysis: Q0 is not an equilibrium at rest: the generalised force there is "
        f"{float(force[worst]):.3g} on {names[worst]}, {why} (gravity on a link not hanging, ...), so the "
        "frequencies are those of a linearisation about a point the system accelerates away from; pass the "
        "rest configuration (under gravity (0, -g) a pendulum hangs at theta1 = -pi/2), or use "
        "linearize(chain, y0) about a steady motion",
        stacklevel=3,
    )


#: `modal_analysis` warns when the rest predicted from `Q0` is further than this in an
#: angle (rad)
REST_ANGLE = 1e-2


@eqx.filter_jit
def _modal_analysis(chain: Chain | AssembledChain, Q0) -> tuple[Modes, jax.Array, jax.Array]:
    """The modes, the generalised force at rest at `Q0` and the stiffness `K` there."""
    asm = assemble(chain)
    n = asm.layout.n_dof
    Q0 = jnp.zeros(n) if Q0 is None else jnp.asarray(Q0, dtype=float)
    if Q0.shape != (n,):
        raise ValueError(
            f"modal_analysis: Q0 expected shape ({n},), the coordinates {list(asm.layout.names)} only "
            f"(not the state [Q, Q_dot]: pass y0[:{n}]), got {Q0.shape}"
        )
    M = mass_matrix(asm, Q0)
    forces = lambda Q: generalised_forces(asm, Q, jnp.zeros(n), jnp.zeros(len(asm.layout.actuated)))  # noqa: E731
    force, jvp = jax.linearize(forces, Q0)
    K = -jax.vmap(jvp)(jnp.eye(n)).T  # stiffness_matrix's -dF/dQ, with F itself
    K = 0.5 * (K + K.T)
    L = jnp.linalg.cholesky(M)
    Linv = jax.scipy.linalg.solve_triangular(L, jnp.eye(n), lower=True)
    w2, V = symmetric_eigh(Linv @ K @ Linv.T)
    # A rigid-body mode's omega^2 is zero only up to the eigensolver's round-off, about
    # n eps max|omega^2| (it came out as ~3e-6 Hz); below that it is reported as exactly 0.
    tol = n * jnp.finfo(w2.dtype).eps * jnp.max(jnp.abs(w2))
    nonzero = jnp.abs(w2) > tol
    # sqrt with a finite derivative at rigid-body (zero) modes; signed: negative omega^2
    # (an unstable mode) gives a negative frequency (`Modes`)
    root = jnp.sqrt(jnp.where(nonzero, jnp.abs(w2), 1.0))
    natural = jnp.where(nonzero, jnp.sign(w2) * root, 0.0) / (2 * jnp.pi)
    return Modes(natural, Linv.T @ V, asm.layout.names), force, K


#: `damped_modes`: eigenvalues below this many `sqrt(eps) max|lambda|` count as zero
ZERO_EIGENVALUE = 10.0


def damped_modes(model: LinearModel) -> tuple[np.ndarray, np.ndarray]:
    """Damped natural frequencies (Hz) and damping ratios from the eigenvalues of
    `model.A`, one per complex pair or real eigenvalue, ascending by |eigenvalue|.
    Host-side NumPy (not jittable).

    A real eigenvalue has frequency 0 and damping ratio +1 (decaying) or -1 (growing: an
    unstable equilibrium). A rigid-body mode (a free joint: a double zero eigenvalue,
    whose computed pair splits by about `sqrt(eps |A|)`) counts as exactly zero when
    `|lambda| < ZERO_EIGENVALUE * sqrt(eps) max |lambda|`: frequency 0, damping ratio 0,
    one entry per zero eigenvalue (two per undamped free joint), so that a free rigid
    rotation does not read as damping ratios -1 and +1 (an instability)."""
    ev = np.linalg.eigvals(np.asarray(model.A))
    tol = ZERO_EIGENVALUE * np.sqrt(np.finfo(float).eps) * (np.max(np.abs(ev)) if ev.size else 0.0)
    ev = np.where(np.abs(ev) < tol, 0.0, ev)  # (before the pairs are halved: one entry per zero eigenvalue)
    ev = ev[np.imag(ev) >= 0]
    mag = np.abs(ev)
    order = np.argsort(mag)
    ev, mag = ev[order], mag[order]
    safe = np.where(mag > 0, mag, 1.0)
    zeta = np.where(mag > 0, -np.real(ev) / safe, 0.0)
    return np.abs(np.imag(ev)) / (2 * np.pi), zeta


def _stability_function(solver: str):
    """`R(z) = 1 + z b^T (I - z A)^{-1} 1` of an explicit Runge-Kutta method (Hairer &
    Wanner, "Solving ODEs II", sec. IV.2), vectorised over `z`, from diffrax's tableau:
    the factor by which one step multiplies a mode `y' = lam y` with `z = h lam`."""
    import diffrax

    from .solvers import RK4

    tableaus = {"tsit5": diffrax.Tsit5.tableau, "rk4": RK4.tableau}
    if solver not in tableaus:
        raise ValueError(f"stable_step: solver expected one of {sorted(tableaus)}, got {solver!r}")
    tab = tableaus[solver]
    s = len(tab.a_lower) + 1
    a = np.zeros((s, s))
    for i, row in enumerate(tab.a_lower):
        a[i + 1, : len(row)] = np.asarray(row, dtype=float)
    b = np.asarray(tab.b_sol, dtype=float)

    def R(z):
        z = np.asarray(z, dtype=complex)
        g = []  # (I - z A)^{-1} 1 by forward substitution (A is strictly lower triangular)
        for i in range(s):
            g.append(1.0 + z * sum(a[i, j] * g[j] for j in range(i)))
        return 1.0 + z * sum(b[i] * g[i] for i in range(s))

    return R


def stable_step(
    chain: Chain | AssembledChain, y0=None, torque0=None, *, solver: str = "tsit5", safety: float = 0.9
) -> float:
    r"""The largest step, s, with which `solver` (`"tsit5"`, `"rk4"`) integrates the
    chain's linearisation about `y0` (`linearize`) stably, times `safety`.

    For every eigenvalue `lam` of `A`, the largest `h` such that `|R(h' lam)| <= max(1,
    |exp(h' lam)|)` for all `h' <= h` (`R` the method's stability function: no mode grows
    faster than it does physically); the smallest over the eigenvalues. Found on a fine
    grid of `h |lam|` and refined by bisection. Host-side NumPy (not jittable).

    Use it as `simulate(..., dtmax=stable_step(chain, y0))` (or `tsit5_trajectory`'s) for
    derivatives of a trajectory that starts at rest (see `simulate`'s `dtmax`). It is a
    property of the linearisation at `y0`: the stiffness moves with the configuration, so
    `safety` leaves room.
    """
    if not 0 < safety <= 1:
        raise ValueError(f"stable_step: safety expected a factor in (0, 1], got {safety!r}")
    R = _stability_function(solver)
    lam = np.linalg.eigvals(np.asarray(linearize(chain, y0, torque0).A))
    scale = np.abs(lam)
    lam, scale = (
        lam[scale > 1e-12 * max(float(np.max(scale, initial=0.0)), 1e-300)],
        scale[scale > 1e-12 * max(float(np.max(scale, initial=0.0)), 1e-300)],
    )
    if lam.size == 0:
        return float("inf")
    direction = lam / scale

    def unstable(x):  # x = h |lam|, per eigenvalue (broadcast)
        z = x * direction[..., None] if np.ndim(x) > 1 else x * direction
        return np.abs(R(z)) > np.maximum(1.0, np.abs(np.exp(z))) * (1 + 1e-12)

    grid = np.geomspace(1e-4, 50.0, 4000)
    bad = unstable(np.broadcast_to(grid, (lam.size, grid.size)))
    first = np.argmax(bad, axis=1)
    never = ~bad.any(axis=1)
    lo = np.where(first > 0, grid[np.maximum(first - 1, 0)], 0.0)
    hi = grid[first]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        worse = unstable(mid)
        lo, hi = np.where(worse, lo, mid), np.where(worse, mid, hi)
    h = np.where(never, np.inf, lo / scale)
    return float(safety * np.min(h))


#: `check_rk4_step` reports a fixed step above RK4's stability limit by more than this
#: factor: `rk4_growth`'s limit is within 1 % of `stable_step`'s on the papers' rigs
#: (paper 004's arm, its damping not proportional, 0.990x; paper 002's, 1.00x).
RK4_MARGIN = 1.02


def check_rk4_step(chain: Chain | AssembledChain, y0, torque0, dt, caller: str):
    """`y0`, with a run-time error (`eqx.error_if`) if the fixed step `dt` is above RK4's
    stability limit for the chain's linearisation about `y0` by more than `RK4_MARGIN`
    (`rk4_growth`). Above it, a mode that the motion barely excites grows from round-off
    and the run ends finite but wrong (16 % above the limit on paper 004's arm, a hub
    angle of 6.16 rad where the adaptive solve gives 0.107) or with an error that blames
    `max_steps`."""
    # no derivative flows through the check (design_move's forward-mode Jacobians would
    # push every tangent through its eigendecomposition)
    frozen = jax.tree.map(lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, (chain, y0, torque0))
    unstable = rk4_growth(*frozen, dt / RK4_MARGIN) > 1.0 + 1e-9
    return eqx.error_if(
        y0,
        unstable,
        f"{caller}: the fixed step dt"
        + ("" if isinstance(dt, jax.core.Tracer) else f" = {float(dt):g} s")
        + " is above RK4's stability limit for the chain's stiffest mode at y0 "
        "(fd.stable_step(chain, y0, solver='rk4', safety=1.0) gives the limit; its default safety, 90 % of it): "
        "a mode would grow from round-off and "
        "the result be wrong; reduce dt or use the adaptive solver (dt=None)",
    )


def rk4_growth(chain: Chain | AssembledChain, y0, torque0, dt):
    """The largest factor by which one RK4 step of `dt` s multiplies a mode of the chain's
    linearisation about `y0` beyond the mode's own physical decay or growth: above 1, the
    fixed step is unstable. Jittable (runs on GPU: `eigh`, no general eigensolver).

    Each undamped mode `v_j` (mass-normalised, `K v = omega^2 M v` with `K = -dF/dQ`, `F`
    the generalised forces (`generalised_forces`: springs, bending, gravity, damping),
    and `M` at `y0`, symmetrised) is taken with its modal damping `c_j = v_j^T D v_j`
    (`D = -dF/dQdot`; the velocity terms of the kinetic energy, which vanish at rest, are
    left out): the roots `lam` of `lam^2 + c_j lam + omega_j^2 = 0`, and
    the factor `|R(dt lam)| / max(1, |exp(dt lam)|)` with RK4's stability function `R(z) =
    1 + z + z^2/2 + z^3/6 + z^4/24`. Exact for proportional damping (the modes of the
    damped system are then these); otherwise it neglects the modes' coupling through `D`.
    `stable_step(solver="rk4")` is the host-side step limit from the eigenvalues of the
    full `A`."""
    asm = assemble(chain)
    n = asm.layout.n_dof
    y0 = jnp.asarray(y0, dtype=float)
    Q0, Qd0 = y0[:n], y0[n:]
    K, D = jax.jacfwd(lambda Q, Qd: -generalised_forces(asm, Q, Qd, torque0), argnums=(0, 1))(Q0, Qd0)
    M = mass_matrix(asm, Q0)
    L = jnp.linalg.cholesky(M)
    Linv = jax.scipy.linalg.solve_triangular(L, jnp.eye(n), lower=True)
    w2, V = jnp.linalg.eigh(Linv @ (0.5 * (K + K.T)) @ Linv.T)
    c = jnp.einsum("ij,ik,kj->j", V, Linv @ (0.5 * (D + D.T)) @ Linv.T, V)
    c, w2 = c.astype(complex), w2.astype(complex)
    root = jnp.sqrt(c**2 - 4.0 * w2)
    z = jnp.asarray(dt).astype(complex) * jnp.concatenate([(-c + root) / 2, (-c - root) / 2])
    R = 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24
    return jnp.max(jnp.abs(R) / jnp.maximum(1.0, jnp.abs(jnp.exp(z))))


def modal_configuration(chain: Chain) -> tuple[np.ndarray, str]:
    """The configuration to analyse the fitted chain about: hanging along gravity (first
    joint angle `atan2(g_y, g_x)`, i.e. -pi/2 for gravity pointing down, the others 0,
    rotor angles with their links, undeformed) under gravity, else all zero. Returns
    `(Q0, where)`: the configuration (rad, m) and a phrase naming it."""
    lay = chain.layout
    Q0 = np.zeros(lay.n_dof)
    g = np.asarray(chain.gravity, float) if getattr(chain, "gravity", None) is not None else np.zeros(2)
    if np.linalg.norm(g) > 0:
        angle = float(np.arctan2(g[1], g[0]))
        Q0[lay.theta[0]] = angle
        if lay.rotor[0] is not None:
            Q0[lay.rotor[0]] = angle
        where = f"hanging equilibrium, theta1 = {np.degrees(angle):.4g} deg"
    else:
        where = "zero configuration"
    return Q0, where


def natural_frequencies(chain: Chain) -> tuple[list[float], str]:
    """Undamped natural frequencies (Hz) of `chain` about `modal_configuration(chain)`,
    and the phrase naming that configuration."""
    Q0, where = modal_configuration(chain)
    modes = modal_analysis(chain, Q0)
    return [float(f) for f in np.asarray(modes.natural_frequency)], where

r"""Composite (slow + fast) control of a chain with flexible links and elastic joints:
paper 004's singular-perturbation controller (section 4-5, eq. 56-70).

Coordinates
===========

Split the generalised coordinates `Q = [alpha, theta, q]` (rotor angles of the
elastic joints, link angles, modal coordinates; the order of
`chain.coordinate_names()`) into

- the **slow** coordinates `theta` (one link angle per joint), and
- the **fast** coordinates `z = [q, delta]`: every modal coordinate of every link
  (m), then the joint deflections `delta_i = alpha_i - theta_i` of the elastic
  joints (rad), paper 004 eq. (56). `fast_names(chain)` lists them, e.g.
  `('q1_1', 'q1_2', 'q2_1', 'q2_2', 'delta1', 'delta2')`.

With the constant matrices `P` (`Q = P theta` is the rigid configuration:
`alpha_i = theta_i`, `q = 0`) and `E` (`z` enters `Q` as `q` and as `alpha_i =
theta_i + delta_i`), `Q = P theta + E z = T [theta; z]` exactly, and the kinetic
and potential energies in `(theta, z)` have mass matrix `M' = T^T M T`,
stiffness `K' = T^T K T` and input matrix `T^T B`. For a horizontal arm
`K' = diag(0, K_z)` with `K_z = blockdiag(K_w, K_s)` (bending stiffness of the
links, joint-spring stiffnesses), because a rigid motion strains nothing.

Two-time-scale model (paper 004 eq. 61-67)
==========================================

Scaling: `k_c = min(diag K_z)` (paper: the smallest of the stiffness constants
`k_ij`, `k_si`), `mu = 1/k_c`, `xi = k_c z` (paper's `xi_q`, `xi_delta`),
`epsilon = sqrt(mu)`, fast time `t_f = t / epsilon`. Setting `mu = 0`:

- **Slow subsystem** (eq. 66): the rigid arm, `z = 0`, `alpha = theta`:

      M_s(theta) theta_ddot + h_s(theta, theta_dot) = tau_bar,
      M_s = P^T M(P theta) P            (= M_11 + J of the paper),
      h_s = P^T [h + dV/dQ + dR/dQ_dot] at (P theta, P theta_dot)   (paper's f_1),

  (`slow_model`). Since `P` is constant, these are exactly Lagrange's equations of
  `T(P theta, P theta_dot)`: the arm with rigid links and locked joint springs,
  rotors included (the tests compare with a `Chain` of `RigidLink`s).

- **Quasi-steady fast variables** (eq. 64-65): with `z_ddot = z_dot = 0` along the
  slow motion, the z-rows of the equations of motion in `(theta, z)` give

      K_z z_bar = E^T [B tau_bar - G],   G = M P theta_ddot + h + dV/dQ + dR/dQ_dot,

  i.e. `K_s delta_bar = tau_bar - J theta_ddot` (eq. 64) and `K_w q_bar = -f_2 -
  M_21 theta_ddot` (eq. 65 after eliminating `H = M^-1`) (`quasi_static`).

- **Fast subsystem** (eq. 67): with `theta` frozen on the fast time scale and the
  velocity terms neglected, the z-rows of `M' x_ddot + K' x = T^T B tau` give
  `z_ddot = A_z z + B_z tau`, `A_z = -[M'^-1 K']_zz`, `B_z = [M'^-1 T^T B]_z`
  (`= [0; J^-1]`). In the scaled variables `x_f = [eta^1, eta^2] = [xi - xi_bar,
  d xi / d t_f]` (`eta^2 = epsilon xi_dot`, paper's definitions),

      d x_f / d t_f = A_f x_f + B_f tau_f,
      A_f = [[0, I], [mu A_z, 0]],    B_f = [[0], [B_z]]     (`fast_subsystem`).

  `mu A_z = -N K_z / k_c` with `N = (M'^-1)_zz`; in blocks of `(q, delta)`,
  `N = [[H_22, -H_21], [-H_12, J^-1 + H_11]]`.

What was not taken literally from the OCR'd paper (derived here instead, and why):

- eq. (57) writes `+K_s delta` in the theta-rows with `delta = alpha - theta`; the
  spring pulls the link towards the rotor, so it is `-K_s delta` (eq. 58 has the
  right sign, `+H_11 K_s delta`).
- eq. (67)'s `A_f` has three block columns for a state of four blocks, the
  `delta`-row reads `+J^-1 K_s` and lacks the link's reaction `theta_ddot =
  H_11 K_s delta - H_12 K_w q` that eq. (63) contains. We use the derivation above,
  which keeps it: the fast subsystem is then exactly the flexible part of the
  linearised arm (its natural frequencies equal the non-zero ones of
  `fd.modal_analysis`, which the tests check).
- `B_f = [0; J^-1 K_s]` (OCR) has the wrong units for a torque input; `B_f = [0;
  B_z]`, `B_z = [0; J^-1]`.
- eq. (69) has no velocity term; computed torque (feedback linearisation) needs
  `f_1`, so `tau_bar = M_s v + h_s` (exact on the rigid arm: the tests check that
  the tracking error then obeys `e_ddot + K_vs e_dot + K_ps e = 0`).
- the paper's `eta^2 = epsilon xi_dot` drops the rate of the quasi-steady part,
  `xi_bar_dot`, valid when the time scales are far apart. On paper 004's arm they are
  not (lowest fast mode 2.2 Hz against a 2 s manoeuvre), and feeding back
  `xi_dot` damps the slow motion itself: in our simulations the composite
  controller then tracks worse than the slow control alone. By default we use
  `eta^2 = epsilon (xi_dot - xi_bar_dot)`, with `xi_bar_dot` the derivative of
  `xi_bar` along the commanded slow motion (one forward-mode pass);
  `rate_correction=False` gives the paper's literal `eta^2`.
- eq. (70) `tau_f = K_pf x_f + K_vf dx_f/dt_f` with `K_pf`, `K_vf` 2 x 6 is read as
  `tau_f = -(K_pf eta^1 + K_vf eta^2)` (our sign convention `tau_f = -K_f x_f`,
  `K_f = [K_pf, K_vf]`), with `K_f` from our own LQR (`lqr`, `solve_care`), not the
  paper's printed numbers.

Controller (paper 004 eq. 68-70)
================================

`tau = tau_bar + tau_f` (eq. 68), with the computed-torque slow control (eq. 69)

    v = theta_d_ddot + K_ps (theta_d - theta) + K_vs (theta_d_dot - theta_dot),
    tau_bar = M_s(theta) v + h_s(theta, theta_dot),

on the measured link angles `theta` (the slow variable, `theta = theta_bar +
O(epsilon)`), and the fast LQR state feedback (eq. 70)

    tau_f = -K_f x_f,   x_f = [k_c (z - z_bar), epsilon k_c (z_dot - z_bar_dot)],

`z_bar = quasi_static(...)` at the commanded slow acceleration `v` and torque
`tau_bar`, `z_bar_dot` its rate along the commanded slow motion (`theta_ddot = v`;
see above). `K_f = R^-1 B_f^T X` with `X` the stabilising solution of the
Riccati equation of `(A_f, B_f, Q_f, R_f)` for the cost `int x_f^T Q_f x_f +
tau_f^T R_f tau_f dt_f`. The gain is designed once, at one configuration
(`design_angles`; the fast subsystem depends on the distal link angles), as the
paper's constant `K_pf`, `K_vf`.

Gravity enters the slow model exactly; for a vertical arm the fast subsystem
takes gravity's stiffness from `fd.stiffness_matrix` at the design configuration.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .chain import AssembledChain, Chain, assemble, input_matrix, inverse_dynamics, mass_matrix
from .inputs import AbstractInput, QuinticReference
from .linear import stiffness_matrix

# ---------------------------------------------------------------------------
# Structure: slow/fast coordinates
# ---------------------------------------------------------------------------


def _layout(chain):
    model = chain.chain if isinstance(chain, AssembledChain) else chain
    if isinstance(model, Chain) and any(m is not None for m in model.motors):
        # (the slow/fast split and the controller's torques assume torque inputs)
        raise ValueError(
            "Chain.motors: the composite controller (paper 004) commands joint torques; a chain with DC motors "
            "(flexdyn.motor) is not supported"
        )
    return chain.layout if isinstance(chain, (Chain, AssembledChain)) else chain


def rigid_embedding(chain: Chain | AssembledChain) -> np.ndarray:
    """`P` (n_dof x n_joints): `Q = P theta` is the rigid configuration (rotor angle =
    link angle, no bending). `P^T B = I` for the joint-torque input matrix `B`."""
    lay = _layout(chain)
    P = np.zeros((lay.n_dof, len(lay.theta)))
    for i, (k_theta, k_rotor) in enumerate(zip(lay.theta, lay.rotor)):
        P[k_theta, i] = 1.0
        if k_rotor is not None:
            P[k_rotor, i] = 1.0
    return P


def fast_embedding(chain: Chain | AssembledChain) -> np.ndarray:
    """`E` (n_dof x n_fast): how the fast coordinates `z = [q, delta]` enter `Q`
    (`Q = P theta + E z`): `q` as itself, `delta_i` as the rotor angle
    `alpha_i = theta_i + delta_i`."""
    lay = _layout(chain)
    modal = [k for m in lay.modal for k in m]
    rotors = [k for k in lay.rotor if k is not None]
    E = np.zeros((lay.n_dof, len(modal) + len(rotors)))
    for j, k in enumerate(modal + rotors):
        E[k, j] = 1.0
    return E


def fast_names(chain: Chain | AssembledChain) -> tuple[str, ...]:
    """Names of the fast coordinates `z = [q, delta]`, e.g. `('q1_1', ..., 'delta2')`."""
    lay = _layout(chain)
    modal = tuple(lay.names[k] for m in lay.modal for k in m)
    deltas = tuple(f"delta{i + 1}" for i, k in enumerate(lay.rotor) if k is not None)
    return modal + deltas


def fast_coordinates(chain: Chain | AssembledChain, Q) -> Float[Array, "... n_fast"]:
    """`z = [q, delta]` (m, rad) of `Q` (or of rates `Q_dot`: `[q_dot, delta_dot]`), any
    leading batch shape. `delta_i = alpha_i - theta_i`."""
    lay = _layout(chain)
    modal = [k for m in lay.modal for k in m]
    rotor = [k for k in lay.rotor if k is not None]
    link = [t for t, r in zip(lay.theta, lay.rotor) if r is not None]
    Q = jnp.asarray(Q)
    return jnp.concatenate([Q[..., modal], Q[..., rotor] - Q[..., link]], axis=-1)


def _transform(lay) -> np.ndarray:
    """`T = [P, E]`: `Q = T [theta; z]` (square and invertible)."""
    return np.concatenate([rigid_embedding(lay), fast_embedding(lay)], axis=1)


# ---------------------------------------------------------------------------
# Slow subsystem, quasi-steady fast variables, fast subsystem
# ---------------------------------------------------------------------------


def slow_model(chain: Chain | AssembledChain, theta, theta_dot) -> tuple[Float[Array, "m m"], Float[Array, " m"]]:
    """The slow (rigid-arm) subsystem, paper 004 eq. (66): `(M_s, h_s)` with

        M_s(theta) theta_ddot + h_s(theta, theta_dot) = tau_bar,
        M_s = P^T M(P theta) P,  h_s = P^T [h + dV/dQ + dR/dQ_dot](P theta, P theta_dot),

    (`M_s` = the paper's `M_11 + J`, `h_s` its `f_1`; joint viscous damping and
    gravity, if any, are in `h_s`). Units: kg m^2, N m."""
    asm = assemble(chain)
    P = jnp.asarray(rigid_embedding(asm))
    Q, Qd = P @ theta, P @ theta_dot
    M = mass_matrix(asm, Q)
    G = inverse_dynamics(asm, Q, Qd, jnp.zeros_like(Q))
    return P.T @ M @ P, P.T @ G


def quasi_static(
    chain: Chain | AssembledChain, theta, theta_dot, theta_ddot, torque, fast_stiffness=None
) -> Float[Array, " n_fast"]:
    """Quasi-steady fast coordinates `z_bar = [q_bar, delta_bar]` (m, rad) along a slow
    motion `(theta, theta_dot, theta_ddot)` under the joint torques `torque` (N m),
    paper 004 eq. (64)-(65):

        K_z z_bar = E^T [B tau - M P theta_ddot - h - dV/dQ - dR/dQ_dot]  at (P theta, P theta_dot),

    i.e. `K_s delta_bar = tau - J theta_ddot`, `K_w q_bar = -f_2 - M_21 theta_ddot`.
    `fast_stiffness` is `K_z` (default: from `fd.stiffness_matrix` at `P theta`)."""
    asm = assemble(chain)
    P, E = jnp.asarray(rigid_embedding(asm)), jnp.asarray(fast_embedding(asm))
    if E.shape[1] == 0:
        return jnp.zeros((0,))
    G = inverse_dynamics(asm, P @ theta, P @ theta_dot, P @ theta_ddot)
    if fast_stiffness is None:
        fast_stiffness = E.T @ stiffness_matrix(asm, P @ theta) @ E
    return jnp.linalg.solve(fast_stiffness, E.T @ (input_matrix(asm) @ torque - G))


class FastSubsystem(eqx.Module):
    """The fast subsystem of paper 004 eq. (67) at one configuration.

    - `A`, `B`: `d x_f / d t_f = A x_f + B tau_f` in the fast time `t_f = t / epsilon`,
      `x_f = [k_c (z - z_bar), epsilon k_c z_dot]` (`A` is 2 n_fast square, `B` is
      2 n_fast x n_joints).
    - `stiffness`: `K_z = (T^T K T)_zz` (N/m for modes, N m/rad for joints, mixed
      blocks N/rad), `mass_inverse`: `N = (M'^-1)_zz`.
    - `scale`: `k_c = min(diag K_z)`; `epsilon = 1/sqrt(k_c)`.
    - `names`: the fast coordinates `z`.

    In physical time, `z_ddot = -N K_z z + B_z tau`; `physical_A` / `physical_B`
    give that model for the state `[z, z_dot]`.
    """

    A: Float[Array, "2f 2f"]
    B: Float[Array, "2f m"]
    stiffness: Float[Array, "f f"]
    mass_inverse: Float[Array, "f f"]
    input_map: Float[Array, "f m"]
    scale: Float[Array, ""]
    names: tuple[str, ...] = eqx.field(static=True)

    @property
    def epsilon(self):
        return 1.0 / jnp.sqrt(self.scale)

    @property
    def physical_A(self):
        f = len(self.names)
        return jnp.block([[jnp.zeros((f, f)), jnp.eye(f)], [-self.mass_inverse @ self.stiffness, jnp.zeros((f, f))]])

    @property
    def physical_B(self):
        return jnp.concatenate([jnp.zeros_like(self.input_map), self.input_map])


@eqx.filter_jit
def fast_subsystem(chain: Chain | AssembledChain, theta=None) -> FastSubsystem:
    """The fast subsystem (paper 004 eq. 67) about the rigid configuration `P theta`
    (default: all link angles zero), from the library's mass and stiffness matrices
    (module docstring: `A_f = [[0, I], [-N K_z / k_c, 0]]`, `B_f = [0; B_z]`)."""
    asm = assemble(chain)
    lay = asm.layout
    n_joints = len(lay.theta)
    theta = jnp.zeros(n_joints) if theta is None else jnp.asarray(theta, dtype=float)
    P, E, T = (jnp.asarray(a) for a in (rigid_embedding(lay), fast_embedding(lay), _transform(lay)))
    f = E.shape[1]
    if f == 0:
        raise ValueError("fast_subsystem: the chain has no flexible links and no elastic joints (no fast coordinates)")
    Q0 = P @ theta
    M_prime = T.T @ mass_matrix(asm, Q0) @ T
    K_prime = T.T @ stiffness_matrix(asm, Q0) @ T
    M_inv = jnp.linalg.inv(M_prime)
    fast = slice(n_joints, None)
    A_z = -(M_inv @ K_prime)[fast, fast]
    B_z = (M_inv @ T.T @ input_matrix(asm))[fast]
    K_z = K_prime[fast, fast]
    k_c = jnp.min(jnp.diag(K_z))
    A = jnp.block([[jnp.zeros((f, f)), jnp.eye(f)], [A_z / k_c, jnp.zeros((f, f))]])
    B = jnp.concatenate([jnp.zeros((f, n_joints)), B_z])
    return FastSubsystem(A, B, K_z, M_inv[fast, fast], B_z, k_c, fast_names(lay))


# ---------------------------------------------------------------------------
# Continuous algebraic Riccati equation and LQR
# ---------------------------------------------------------------------------


def _lyapunov(Ac, C):
    """Solve `Ac^T X + X Ac + C = 0` (Kronecker form; small systems)."""
    n = Ac.shape[0]
    eye = jnp.eye(n, dtype=Ac.dtype)
    L = jnp.kron(Ac.T, eye) + jnp.kron(eye, Ac.T)
    X = jnp.linalg.solve(L, -C.reshape(-1)).reshape(n, n)
    return 0.5 * (X + X.T)


def _matrix_sign(H, max_iter, tol):
    """Sign function of `H` by Newton's iteration with determinant scaling (Byers 1987):
    `Z <- (Z / c + c Z^-1) / 2`, `c = |det Z|^(1 / dim)`."""
    dim = H.shape[0]

    def step(carry):
        Z, _, k = carry
        _, logdet = jnp.linalg.slogdet(Z)
        c = jnp.exp(logdet / dim)
        Z_new = 0.5 * (Z / c + c * jnp.linalg.inv(Z))
        change = jnp.sum(jnp.abs(Z_new - Z)) / jnp.sum(jnp.abs(Z_new))
        return Z_new, change, k + 1

    def more(carry):
        _, change, k = carry
        return (change > tol) & (k < max_iter)

    Z, change, _ = jax.lax.while_loop(more, step, (H, jnp.asarray(jnp.inf, H.dtype), 0))
    return Z, change


@jax.custom_jvp
def _care(A, B, Q, R):
    n = A.shape[0]
    G = B @ jnp.linalg.solve(R, B.T)
    H = jnp.block([[A, -G], [-Q, -A.T]])
    W, change = _matrix_sign(H, 100, 1e-13)
    # The stable invariant subspace [I; X] of H is the null space of W + I.
    lhs = jnp.concatenate([W[:n, n:], W[n:, n:] + jnp.eye(n)])
    rhs = -jnp.concatenate([W[:n, :n] + jnp.eye(n), W[n:, :n]])
    X = jnp.linalg.lstsq(lhs, rhs)[0]
    X = 0.5 * (X + X.T)
    # One Newton-Kleinman step from a near-solution: quadratic convergence restores the
    # digits the sign iteration loses on an ill-conditioned Hamiltonian.
    X = _lyapunov(A - G @ X, Q + X @ G @ X)
    bad = ~jnp.all(jnp.isfinite(X)) | ~(change < 1e-8)
    return eqx.error_if(
        X,
        bad,
        "solve_care: no stabilising solution (the Hamiltonian has eigenvalues on or near the imaginary axis: "
        "is (A, B) stabilisable and (A, Q) detectable, and R positive definite?)",
    )


@_care.defjvp
def _care_jvp(primals, tangents):
    A, B, Q, R = primals
    dA, dB, dQ, dR = tangents
    X = _care(A, B, Q, R)
    R_inv_Bt = jnp.linalg.solve(R, B.T)
    G = B @ R_inv_Bt
    dG = dB @ R_inv_Bt + R_inv_Bt.T @ dB.T - R_inv_Bt.T @ dR @ R_inv_Bt
    # Differentiate A^T X + X A - X G X + Q = 0: (A - G X)^T dX + dX (A - G X) + C = 0.
    C = dA.T @ X + X @ dA - X @ dG @ X + dQ
    return X, _lyapunov(A - G @ X, C)


@jax.jit
def solve_care(A, B, Q, R) -> Float[Array, "n n"]:
    """Stabilising solution `X = X^T >= 0` of the continuous algebraic Riccati equation

        A^T X + X A - X B R^-1 B^T X + Q = 0,

    by the matrix sign function of the Hamiltonian `H = [[A, -B R^-1 B^T], [-Q, -A^T]]`
    (Newton iteration with determinant scaling; the stable invariant subspace `[I; X]`
    is the null space of `sign(H) + I`), polished by one Newton-Kleinman step. Pure JAX:
    jit-, vmap- and differentiable (forward and reverse mode, by implicit
    differentiation: `dX` solves a Lyapunov equation with `A - B R^-1 B^T X`). `Q` and
    `R` are symmetrised. Raises (via `eqx.error_if`) when there is no stabilising solution.
    """
    A, B, Q, R = (jnp.asarray(x, dtype=float) for x in (A, B, Q, R))
    n, m = B.shape
    if A.shape != (n, n) or Q.shape != (n, n) or R.shape != (m, m):
        raise ValueError(
            f"solve_care: expected A (n, n), B (n, m), Q (n, n), R (m, m); got {A.shape}, {B.shape}, "
            f"{Q.shape}, {R.shape}"
        )
    return _care(A, B, 0.5 * (Q + Q.T), 0.5 * (R + R.T))


@jax.jit
def lqr(A, B, Q, R) -> tuple[Float[Array, "m n"], Float[Array, "n n"]]:
    """Continuous-time LQR: the gain `K = R^-1 B^T X` of `u = -K x` minimising
    `int x^T Q x + u^T R u dt` for `x_dot = A x + B u`, and the Riccati solution `X`
    (`solve_care`)."""
    X = solve_care(A, B, Q, R)
    R = jnp.asarray(R, dtype=float)
    return jnp.linalg.solve(0.5 * (R + R.T), jnp.asarray(B, dtype=float).T @ X), X


# ---------------------------------------------------------------------------
# The composite controller
# ---------------------------------------------------------------------------


class CompositeController(AbstractInput):
    """Paper 004's composite controller, eq. (68)-(70): `tau = tau_bar + tau_f`,

        tau_bar = M_s(theta) v + h_s(theta, theta_dot),                       (69)
        v = theta_d_ddot + K_ps (theta_d - theta) + K_vs (theta_d_dot - theta_dot),
        tau_f = -K_f [k_c (z - z_bar), epsilon k_c (z_dot - z_bar_dot)],      (70)

    with `z = [q, delta]` the fast coordinates of the state and `z_bar` their
    quasi-steady values under `(theta, theta_dot, v, tau_bar)` (eq. 64-65). See the
    module docstring for the derivation. Build it with `composite_controller`.

    **Fields:** `model` (the controller's own model of the arm, an `AssembledChain`; it
    may differ from the simulated plant), `reference` (`position`, `velocity`,
    `acceleration` of `t`, rad), `kp` (K_ps, 1/s^2), `kd` (K_vs, 1/s), `fast_gain` (K_f,
    n_joints x 2 n_fast, on the scaled fast state, N m per N), `fast_stiffness` (K_z),
    `scale` (k_c), `rate_correction` (static; True: `z_bar_dot` in the fast state, False:
    the paper's `eta^2 = epsilon k_c z_dot`). A zero `fast_gain` gives the slow
    (computed-torque) control alone.
    """

    model: AssembledChain
    reference: QuinticReference
    kp: Float[Array, " m"]
    kd: Float[Array, " m"]
    fast_gain: Float[Array, "m 2f"]
    fast_stiffness: Float[Array, "f f"]
    scale: Float[Array, ""]
    rate_correction: bool = True

    def _split(self, y):
        lay = self.model.layout
        n = lay.n_dof
        idx = jnp.asarray(lay.theta)
        return y[:n], y[n:], y[idx], y[n + idx]

    def commanded_acceleration(self, t, theta, theta_dot):
        """`v = theta_d_ddot + K_ps (theta_d - theta) + K_vs (theta_d_dot - theta_dot)`, rad/s^2 (eq. 69)."""
        ref = self.reference
        return ref.acceleration(t) + self.kp * (ref.position(t) - theta) + self.kd * (ref.velocity(t) - theta_dot)

    def slow_torque(self, t, y):
        """`(tau_bar, v, z_bar)`: slow torque (N m), commanded slow acceleration (rad/s^2)
        and quasi-steady fast coordinates, eq. (64), (65), (69)."""
        asm = self.model
        _, _, theta, theta_dot = self._split(y)
        v = self.commanded_acceleration(t, theta, theta_dot)
        P, E = jnp.asarray(rigid_embedding(asm)), jnp.asarray(fast_embedding(asm))
        G = inverse_dynamics(asm, P @ theta, P @ theta_dot, P @ v)
        tau_bar = P.T @ G
        if E.shape[1] == 0:
            return tau_bar, v, jnp.zeros((0,))
        z_bar = jnp.linalg.solve(self.fast_stiffness, E.T @ (input_matrix(asm) @ tau_bar - G))
        return tau_bar, v, z_bar

    def fast_state(self, t, y):
        """The scaled fast state `x_f = [k_c (z - z_bar), epsilon k_c (z_dot - z_bar_dot)]` of
        eq. (67), and the slow torque: `(x_f, tau_bar)`."""
        asm = self.model
        Q, Qd, theta, theta_dot = self._split(y)
        z, z_dot = fast_coordinates(asm, Q), fast_coordinates(asm, Qd)
        lay = asm.layout
        n = lay.n_dof
        idx = jnp.asarray(lay.theta)

        def slow_part(t_, theta_, theta_dot_):
            yy = y.at[idx].set(theta_).at[n + idx].set(theta_dot_)
            tau_bar, v, z_bar = self.slow_torque(t_, yy)
            return z_bar, (tau_bar, v)

        if self.rate_correction:
            # z_bar_dot along the slow motion (theta_ddot = v): one forward-mode pass
            t = jnp.asarray(t, dtype=float)
            v = self.commanded_acceleration(t, theta, theta_dot)
            z_bar, z_bar_dot, (tau_bar, _) = jax.jvp(
                slow_part, (t, theta, theta_dot), (jnp.ones_like(t), theta_dot, v), has_aux=True
            )
        else:
            (z_bar, (tau_bar, _)), z_bar_dot = slow_part(t, theta, theta_dot), jnp.zeros_like(z)
        return jnp.concatenate([self.scale * (z - z_bar), jnp.sqrt(self.scale) * (z_dot - z_bar_dot)]), tau_bar

    def __call__(self, t, y):
        if self.fast_gain.shape[1] == 0:
            return self.slow_torque(t, y)[0]
        x_f, tau_bar = self.fast_state(t, y)
        return tau_bar - self.fast_gain @ x_f


@eqx.filter_jit
def composite_controller(
    chain: Chain | AssembledChain,
    reference: QuinticReference,
    kp,
    kd,
    *,
    fast_state_weight=None,
    fast_input_weight=None,
    design_angles=None,
    fast: bool = True,
    rate_correction: bool = True,
) -> CompositeController:
    """Design paper 004's composite controller (eq. 68-70) for `chain`.

    **Arguments:**
    - `chain`: the controller's model of the arm.
    - `reference`: the link-angle reference (`fd.QuinticReference`, eq. 71).
    - `kp`, `kd`: slow gains `K_ps` (1/s^2), `K_vs` (1/s), one per joint (paper: 5, 2).
    - `fast_state_weight`: `Q_f` (2 n_fast square, or a vector for its diagonal) of the
      fast LQR cost `int x_f^T Q_f x_f + tau_f^T R_f tau_f dt_f`; default identity.
    - `fast_input_weight`: `R_f` (n_joints square, or its diagonal); default identity.
    - `design_angles`: link angles of the configuration the fast subsystem is
      linearised about (default zero: the straight arm).
    - `fast`: False gives the slow computed-torque control alone (`fast_gain = 0`,
      same structure, so it reuses the compiled simulation).
    - `rate_correction`: see `CompositeController` (default True; False is the paper's
      literal fast state).

    The fast gain is `K_f = R_f^-1 B_f^T X` from `solve_care` (our own Riccati solve).
    Jitted; differentiable with respect to every array leaf of the arguments.
    """
    asm = assemble(chain)
    lay = asm.layout
    n_joints = len(lay.theta)
    kp = jnp.broadcast_to(jnp.asarray(kp, dtype=float), (n_joints,))
    kd = jnp.broadcast_to(jnp.asarray(kd, dtype=float), (n_joints,))
    f = fast_embedding(lay).shape[1]
    if f == 0:
        return CompositeController(
            asm, reference, kp, kd, jnp.zeros((n_joints, 0)), jnp.zeros((0, 0)), jnp.ones(()), rate_correction
        )
    sub = fast_subsystem(asm, design_angles)

    def weight(w, size):
        if w is None:
            return jnp.eye(size)
        w = jnp.asarray(w, dtype=float)
        return jnp.diag(w) if w.ndim == 1 else w

    if fast:
        gain, _ = lqr(sub.A, sub.B, weight(fast_state_weight, 2 * f), weight(fast_input_weight, n_joints))
    else:
        gain = jnp.zeros((n_joints, 2 * f))
    return CompositeController(asm, reference, kp, kd, gain, sub.stiffness, sub.scale, rate_correction)

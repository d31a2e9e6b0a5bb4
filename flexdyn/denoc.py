r"""Paper 000's DeNOC formulation: the equations of motion of the chain built from the
Newton-Euler side, as a second formulation independent of `flexdyn.chain`.

`flexdyn.chain` forms `M(Q)` and the velocity terms by automatic differentiation of
the kinetic energy. Here nothing is differentiated automatically: every body's
inertia, velocity-product ("gyroscopic/convective") and gravity terms are written
by hand from its mass distribution, the bodies' twists are propagated down the
chain with hand-derived "shift" blocks (the decoupled natural orthogonal
complement, DeNOC, of paper 000 eq. 3 and its ref. [2]), and the equations are

    N^T (M_b t_dot + w_b - gamma_b) = tau_joint,        t = N(Q) Q_dot,  N = N_l N_d,

    =>  M(Q) = N^T M_b N,      h(Q, Q_dot) = N^T (M_b N_dot Q_dot + w_b),
        F = tau_joint + N^T gamma_b,                    M Q_ddot + h = F.

Only the shape integrals of `fd.assemble(chain)` are shared with the core (`m, c1,
c2, a, b, Mq, K, D, tip_shape, tip_slope`), so what is checked is the equations, not
the mode shapes. The kinematics is the core's (module docstring of `flexdyn.chain`).

Derivation
==========

Notation: `S = [[0, -1], [1, 0]]` (planar cross product `omega x r = omega S r`),
`R(a)` the rotation by `a`, `x` the distance along the undeformed link, `phi(x)` the
mode shapes (row), `v(x) = phi(x) q` the deflection.

**Twist of a body.** Link i (with hub i and rotor i, "body i" below) has the twist,
expressed in its own root frame (angle `phi_i`, origin `o_i`),

    t_i = [u_i (2), omega_i, q_dot_i (m_i), Omega_i],
    u_i = R(phi_i)^T o_dot_i,  omega_i = phi_dot_i,  Omega_i = rotor i's absolute rate.

Hub i (point mass at `o_i`, inertia turning with `phi_i`) moves with link i's root
frame, so it is lumped into body i. Rotor i sits on its carrier (the tip frame of
link i-1, angle `psi_{i-1}`; the ground for i = 1) and turns at `Omega_i =
psi_dot_{i-1} + G s_dot_i` (`Omega_i = G s_dot_i` with `spong_approximation`); it is
grouped with body i because its rate involves joint i's rate. The payload has
`t_p = [u_p, omega_p]` in the tip frame of link n (angle `psi_n`).
A material point `p(x) = [x, v(x)]` of the link has body-frame velocity

    c_dot(x) = u + omega S p(x) + [0, phi(x) q_dot] = B(x) t,
    B(x) = [[1, 0, -v(x), 0, 0], [0, 1, x, phi(x), 0]]

(paper 000's `r_dot` with `r = x + u`; `phi` is its `lambda`).

**Body inertia** `M_b = int rho B^T B dx` (+ hub, + rotor), exactly:

    [[m,    0,    -a.q,            0,    0  ],
     [0,    m,     c1,             a^T,  0  ],
     [-a.q, c1,    c2 + q^T Mq q,  b^T,  0  ],
     [0,    a,     b,              Mq,   0  ],
     [0,    0,     0,              0,    I_r]]

with `m` the link mass plus the hub mass `m_h` (a point mass at `o_i`), `c2` plus
the hub inertia `J_h`. The configuration-dependent entries are `-a.q` (the deflected
link's centre of mass is off the axis) and `q^T Mq q` (paper 000's `S1 b^2`).
A rigid link is the case `m_i = 0`, `c1 = m com`, `c2 = I_c + m com^2`.
The payload: `M_p = diag(M_p, M_p, I_p)`.

**Velocity products from the body's Newton-Euler equations.** The absolute
acceleration of a material point, in the body frame, is (`r = o + R p`)

    a(x) = B(x) t_dot + kappa(x),
    kappa = omega S u + 2 omega S [0, phi q_dot] - omega^2 p(x)
          = [-omega u_y - 2 omega phi q_dot - omega^2 x,  omega u_x - omega^2 v(x)]

(transport, Coriolis and centripetal accelerations; paper 000's eq. (8) `r_ddot =
omega_dot x r + 2 omega x u_dot + lambda u_ddot + omega x (omega x r)`; note that
`omega x (omega x r) = -omega^2 r` is *not* zero in planar motion, as paper 000 says
after eq. 4 and eq. 8; it does not matter for the rigid pendulum's moment, it is
the whole centrifugal term of the flexible one). The body's generalised inertia
force is `int rho B^T a dx` (resultant, moment about `o_i`, modal projection
`int rho phi^T a_y`: exactly paper 000's `w_hat` of eq. 4 and 8), i.e.
`M_b t_dot + w_b` with

    w_b = int rho B^T kappa dx =
      [ -m omega u_y - 2 omega a.q_dot - omega^2 c1,
         m omega u_x - omega^2 a.q,
         omega u_x c1 + omega u_y a.q + 2 omega q^T Mq q_dot,
         omega u_x a - omega^2 Mq q,
         0 ]

(`m` including the hub; the rotor spins about a fixed axis of its carrier and has
no velocity product; the payload: `[-M_p omega u_y, M_p omega u_x, 0]`). This is
the Euler-Poincare form `M_dot t + [omega S p_u; u x p_u; -dT/dq]` of the same body,
`p = M_b t`, which the tests check.

**Twist propagation (N_l, N_d).** With `beta_i = phi_i - phi_{i-1} = tip_slope_{i-1}
q_{i-1} + theta_i`, `d = tip_shape_{i-1} q_{i-1}` (tip deflection of link i-1, length
`l = l_{i-1}`), the joint of link i is at `o_i = o_{i-1} + R(phi_{i-1}) [l, d]`, so

    t_i = A_i t_{i-1} + P_i Q_dot_i

    A_i = [[R(beta_i)^T [I2 | S[l, d]^T | [0; tip_shape^T] | 0]],  (u rows)
           [ 0 0 1 tip_slope^T 0 ],                                  (omega: psi_dot_{i-1})
           [ 0 ... 0 ],                                              (modal rows)
           [ 0 0 1 tip_slope^T 0 ]  or 0 with spong_approximation]   (rotor: its carrier)

and `P_i` (constant, joint-motion propagation) puts `theta_dot_i` on `omega_i`,
`q_dot_i` on the modal rows and `G s_dot_i` on `Omega_i` (`s = alpha_i` for an elastic
joint, `theta_i` for a rigid one). The payload is `t_p = A_p t_n` with `beta = tip_slope_n
q_n` (no joint). Stacking, `t = N_l N_d Q_dot` with `N_l` block lower-triangular,
`N_l[i, i] = I`, `N_l[i, j] = A_i A_{i-1} ... A_{j+1}` (paper 000's `N_l`, the "shift"
blocks now including the elastic tip deflection `d` and slope, and expressed in the
body frames, whence the `R(beta)^T`) and `N_d = blockdiag(P_1, ..., P_n, [])`
(paper 000's `N_d`, for one flexible link the 7x2 "joint cum flexibility propagation
matrix" `[[0 e 0], [0 0 1]]^T`).

**N_dot Q_dot** (the twist-rate bias, `zeta = N_dot Q_dot`) follows from
`t_dot_i = A_i t_dot_{i-1} + A_dot_i t_{i-1} + P_i Q_ddot_i`; the only rows of `A_i`
that vary are the `u` rows, so, by hand,

    A_dot_i t_{i-1} = [-beta_dot_i S u_i + R(beta_i)^T [-omega_{i-1} d_dot, 0], 0, 0, 0],
    zeta_i = A_i zeta_{i-1} + A_dot_i t_{i-1}.

**Forces.** Gravity is a body wrench, `gamma_b = int rho B^T R(phi)^T g dx =
[m g_b, c1 g_by - (a.q) g_bx, a g_by, 0]` (`g_b = R(phi_i)^T g`; payload `[M_p
R(psi_n)^T g, 0]`), projected by `N^T`; the bending force `-K q - D q_dot` acts on the
modal rows of the body (projected by `N^T`, whose modal rows are unit vectors).
Joint torques, joint springs `k_s (alpha - theta)` and the joint and spring dampers
act across joints: their power is force times relative joint rate, so they enter
directly as the right-hand side `tau` of paper 000's eq. (3) (after `N_d^T`).

Why this equals Lagrange's equations: `t = N Q_dot` are quasi-velocities with
partial velocities `N`; Kane's equations (or the principle of virtual power with the
body equations above) give `sum_b N_b^T (int rho B^T a - gamma_b) = tau`; this is
paper 000's eq. (3), `N_d^T N_l^T w_hat = tau`, and paper 000 (via its ref. [6])
and the tests here show it is Lagrange's eq. (2).

Correspondence with paper 000
=============================

- eq. (1)-(2) (energy, Lagrange) is `flexdyn.chain`; eq. (3) is the line above.
- eq. (4)-(6), rigid pendulum: one rigid body, `N_l = I`, `N_d = [0 0 1]^T` (our
  planar twist `[u_x, u_y, omega]`; the paper's 6-vector `[0^T e^T]^T`), `w_hat =
  [M_b t_dot + w_b]`, `N_d^T w_hat = c2 theta_ddot = rho l^3/3 theta_ddot` (the OCR
  "rho p theta_ddot / 3" is `rho l^3 / 3`).
- eq. (7): adding hub and payload, `(rho l^3/3 + m_p l^2 + I_h) theta_ddot + xi
  theta_dot = -(rho l^2/2 + m_p l) g cos(theta)` for `theta` counter-clockwise from
  the horizontal with gravity `(0, -g)`; paper 000 prints `rho l^2 g cos theta`
  (missing 1/2) and a stray `theta_ddot` inside the bracket; with `theta` measured
  downward the moment is `+(rho l^2/2 + m_p l) g cos(theta)`.
- eq. (8)-(9): the 7-dimensional `w_hat` is our `int rho B^T a` for one mode; the
  7x2 `N_d` is our `P_1` (without the rotor row).
- eq. (10), one mode `s(x)`, `S1 = int s^2`, `S2 = int x s`, `S3 = s(l)`, payload
  point mass `m_p`, hub `I_h`; our equations give
      M11 = rho l^3/3 + rho S1 b^2 + m_p (l^2 + S3^2 b^2) + I_h      (confirmed; the
            paper's rho multiplies the whole bracket, a typo)
      M12 = rho S2 + m_p l S3,  M22 = rho S1 + m_p S3^2              (confirmed)
      h1  = 2 (rho S1 + m_p S3^2) b theta_dot b_dot                  (paper: 2(S1 + S3^2), m_p and rho lost)
      h2  = -(rho S1 + m_p S3^2) b theta_dot^2                       (paper: -(2 S1 + m_p S3^2): factor 2 wrong,
            also in its un-numbered equation above eq. 10)
      gravity (theta ccw from horizontal, g = (0, -g), S0 = int s):
      F1  = -(rho l^2/2 + m_p l) g cos(theta) + (rho S0 + m_p S3) g b sin(theta)
      F2  = -(rho S0 + m_p S3) g cos(theta) - K b - zeta_m b_dot
      (paper: F1 = rho l^2 g cos(theta) - m_p g l cos(theta): 1/2 missing, payload
      sign inconsistent, b-term dropped; F2 = 0: gravity on the beam dropped and the
      bending stiffness `K b` missing, without which no 35 Hz vibration exists).
      The damping terms `zeta theta_dot`, `zeta_m b_dot` are confirmed.

Functions: `denoc_matrices` (N_l, N_d, M_b, body wrenches), `denoc_equations` (M, h,
F in one pass), `denoc_mass_matrix`, `denoc_velocity_terms`, `denoc_generalised_forces`,
`denoc_accelerations` (dense: `M` and Cholesky, O(n^3)), and
`denoc_forward_dynamics_recursive` (articulated-body recursion on the same blocks,
O(n); `benchmarks/bench_denoc_recursive.py` times it against the dense solves). All
take `asm = fd.assemble(chain)` (or a `Chain`) and are jit/vmap-compatible. Tests:
`tests/flexdyn/test_denoc.py` (equal to the core's `mass_matrix`, `velocity_terms`,
generalised forces and `accelerations` to 1e-10 relative at random states of random
chains; eq. 7 and 10 as above).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from .chain import AssembledChain, Chain, assemble

__all__ = [
    "DenocMatrices",
    "denoc_matrices",
    "denoc_equations",
    "denoc_mass_matrix",
    "denoc_velocity_terms",
    "denoc_generalised_forces",
    "denoc_accelerations",
    "denoc_forward_dynamics_recursive",
]

_S = jnp.array([[0.0, -1.0], [1.0, 0.0]])


def _rot(angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.array([[c, -s], [s, c]])


# ---------------------------------------------------------------------------
# Static structure: coordinates of each joint and body dimensions
# ---------------------------------------------------------------------------


def _joint_slice(lay, i):
    """Q indices of joint i (rotor, theta, modal: contiguous in the layout)."""
    start = lay.rotor[i] if lay.rotor[i] is not None else lay.theta[i]
    stop = lay.theta[i] + 1 + len(lay.modal[i])
    return start, stop


def _dim(lm) -> int:
    """Twist dimension of body i: [u_x, u_y, omega, q_dot (m), Omega_rotor]."""
    return 4 + lm.a.shape[0]


# ---------------------------------------------------------------------------
# Per-body quantities (hand-derived; see the module docstring)
# ---------------------------------------------------------------------------


class _Body(NamedTuple):
    Mb: jnp.ndarray  # body inertia in its twist coordinates
    gamma: jnp.ndarray  # applied body wrench (gravity, bending, modal damping)


def _joint_motion(asm, i):
    """P_i: joint rates Q_dot_i -> twist of body i (constant)."""
    lay, joint, lm = asm.layout, asm.chain.joints[i], asm.links[i]
    m, d = lm.a.shape[0], _dim(lm)
    start, stop = _joint_slice(lay, i)
    ones = np.zeros((d, stop - start))  # unit entries
    gear = np.zeros((d, stop - start))  # entries equal to the gear ratio G
    col = 0
    if joint.elastic:
        gear[d - 1, col] = 1.0  # alpha_dot drives the rotor
        col += 1
    ones[2, col] = 1.0  # theta_dot
    if not joint.elastic:
        gear[d - 1, col] = 1.0  # rigid joint: the rotor turns with theta
    col += 1
    ones[3 : 3 + m, col : col + m] = np.eye(m)
    return jnp.asarray(ones) + joint.gear_ratio * jnp.asarray(gear)


def _psi_row(lm):
    """[0 0 1 tip_slope^T 0]: the rate of the tip frame of a body (its rotor column is 0)."""
    return jnp.concatenate([jnp.array([0.0, 0.0, 1.0]), lm.tip_slope, jnp.zeros(1)])


def _shift(lm_parent, q_parent, beta, rows_child: int, rotor_row: bool):
    """A_i: twist of the parent body (dim 4 + m_parent) -> twist of the child (rows_child).

    Rows u: R(beta)^T [I2 | S [l, d]^T | [0; tip_shape^T] | 0]; row omega and (if
    `rotor_row`) the last row: [0 0 1 tip_slope^T 0] (the carrier's rate psi_dot)."""
    m = lm_parent.a.shape[0]
    d = lm_parent.tip_shape @ q_parent
    U = jnp.concatenate(
        [
            jnp.eye(2),
            jnp.stack([-d, lm_parent.length])[:, None],
            jnp.stack([jnp.zeros(m), lm_parent.tip_shape]),
            jnp.zeros((2, 1)),
        ],
        axis=1,
    )
    psi = _psi_row(lm_parent)[None]
    rows = [_rot(beta).T @ U, psi]
    if rows_child > 3:
        rows.append(jnp.zeros((rows_child - 4, 4 + m)))
        rows.append(psi if rotor_row else jnp.zeros_like(psi))
    return jnp.concatenate(rows, axis=0)


def _shift_bias(lm_parent, qd_parent, beta, beta_dot, t_parent, u_child, rows_child):
    """A_dot_i t_{i-1}: only the u rows vary: -beta_dot S u_i + R(beta)^T [-omega d_dot, 0]."""
    d_dot = lm_parent.tip_shape @ qd_parent
    omega = t_parent[2]
    zu = -beta_dot * (_S @ u_child) + _rot(beta).T @ jnp.stack([-omega * d_dot, jnp.zeros_like(d_dot)])
    return jnp.concatenate([zu, jnp.zeros(rows_child - 2)])


def _link_body(asm, i, Q, Qd, phi):
    """M_b and gamma_b (gravity, bending, modal damping) of body i (link i + hub i +
    rotor i); the velocity products are `_link_velocity_products`."""
    chain, lay, lm = asm.chain, asm.layout, asm.links[i]
    hub, joint = chain.hubs[i], chain.joints[i]
    m = lm.a.shape[0]
    q, qd = _modal(lay, Q, i), _modal(lay, Qd, i)
    mt = lm.mass + hub.mass
    aq = lm.a @ q
    zero = jnp.zeros(())
    top = jnp.array([[mt, zero, -aq], [zero, mt, lm.c1], [-aq, lm.c1, lm.c2 + q @ lm.modal_mass @ q + hub.inertia]])
    coupling = jnp.stack([jnp.zeros(m), lm.a, lm.b])  # (3, m)
    Mb = jnp.block(
        [
            [top, coupling, jnp.zeros((3, 1))],
            [coupling.T, lm.modal_mass, jnp.zeros((m, 1))],
            [jnp.zeros((1, 3 + m)), jnp.reshape(joint.rotor_inertia, (1, 1))],
        ]
    )
    gb = _rot(phi).T @ chain.gravity
    gamma = jnp.concatenate(
        [
            mt * gb,
            jnp.stack([lm.c1 * gb[1] - aq * gb[0]]),
            lm.a * gb[1] - lm.stiffness @ q - lm.damping @ qd,
            jnp.zeros(1),
        ]
    )
    return _Body(Mb, gamma)


def _link_velocity_products(asm, i, Q, t):
    """w_b = int rho B^T kappa dx (+ hub): the body's own Coriolis/centripetal terms."""
    lay, lm, hub = asm.layout, asm.links[i], asm.chain.hubs[i]
    m = lm.a.shape[0]
    q = _modal(lay, Q, i)
    ux, uy, om = t[0], t[1], t[2]
    qd = t[3 : 3 + m]
    mt = lm.mass + hub.mass
    aq, aqd = lm.a @ q, lm.a @ qd
    Mq_q = lm.modal_mass @ q
    return jnp.concatenate(
        [
            jnp.stack(
                [
                    -mt * om * uy - 2.0 * om * aqd - om**2 * lm.c1,
                    mt * om * ux - om**2 * aq,
                    om * ux * lm.c1 + om * uy * aq + 2.0 * om * (Mq_q @ qd),
                ]
            ),
            om * ux * lm.a - om**2 * Mq_q,
            jnp.zeros(1),
        ]
    )


def _payload_body(asm, psi):
    p, g = asm.chain.payload, asm.chain.gravity
    Mb = jnp.diag(jnp.stack([p.mass, p.mass, p.inertia]))
    gb = _rot(psi).T @ g
    gamma = jnp.concatenate([p.mass * gb, jnp.zeros((1,))])
    return _Body(Mb, gamma)


def _payload_velocity_products(asm, t):
    mp = asm.chain.payload.mass
    return jnp.stack([-mp * t[2] * t[1], mp * t[2] * t[0], jnp.zeros_like(t[0])])


def _modal(lay, Q, i):
    idx = lay.modal[i]
    return Q[idx[0] : idx[-1] + 1] if idx else jnp.zeros((0,), Q.dtype)


# ---------------------------------------------------------------------------
# Recursion over the chain: shifts, twists, twist-rate bias
# ---------------------------------------------------------------------------


class _Recursion(NamedTuple):
    A: list  # A[i]: shift from body i-1 to body i (None for i = 0); A[n]: to the payload
    P: list  # P[i]: joint-motion propagation of joint i (payload: None)
    bodies: list  # _Body per body (n links, then the payload)
    t: list  # twists (None when no rates were given)
    zeta: list  # N_dot Q_dot per body
    local: list  # A_dot_i t_{i-1}: the part of zeta_i created at joint i
    w: list  # velocity products per body


def _recursion(asm, Q, Qd=None):
    lay, chain = asm.layout, asm.chain
    if any(m is not None for m in chain.motors):
        raise ValueError(
            "Chain.motors: DC motors (flexdyn.motor) are not in the DeNOC formulation (its inputs are joint "
            "torques); use flexdyn.accelerations, or a chain without motors"
        )
    for i, link in enumerate(chain.links, start=1):
        if getattr(link, "geometric_stiffening", False):
            raise ValueError(
                f"Chain.links[{i - 1}] (link{i}): geometric_stiffening=True is not in the DeNOC formulation "
                "(paper 000's linear kinematics); use flexdyn.accelerations, or a link without it"
            )
    n = chain.n_links
    A, P, bodies, ts, zetas, locs, ws = [], [], [], [], [], [], []
    phi_parent = jnp.zeros(())
    for i in range(n + 1):
        last = i == n
        rows = 3 if last else _dim(asm.links[i])
        if i == 0:
            A.append(None)
            beta = Q[lay.theta[0]]
            beta_dot = None if Qd is None else Qd[lay.theta[0]]
        else:
            lp = asm.links[i - 1]
            qp = _modal(lay, Q, i - 1)
            slope = lp.tip_slope @ qp
            beta = slope + (0.0 if last else Q[lay.theta[i]])
            rotor_row = (not last) and not chain.joints[i].spong_approximation
            A.append(_shift(lp, qp, beta, rows, rotor_row))
            if Qd is not None:
                qdp = _modal(lay, Qd, i - 1)
                beta_dot = lp.tip_slope @ qdp + (0.0 if last else Qd[lay.theta[i]])
        phi = phi_parent + beta
        if last:
            P.append(None)
            bodies.append(_payload_body(asm, phi))
        else:
            P.append(_joint_motion(asm, i))
            bodies.append(_link_body(asm, i, Q, Qd if Qd is not None else jnp.zeros_like(Q), phi))
        if Qd is not None:
            if i == 0:
                s, e = _joint_slice(lay, 0)
                t = P[0] @ Qd[s:e]
                loc = zeta = jnp.zeros((rows,))
            else:
                t = A[i] @ ts[i - 1]
                if not last:
                    s, e = _joint_slice(lay, i)
                    t = t + P[i] @ Qd[s:e]
                loc = _shift_bias(asm.links[i - 1], _modal(lay, Qd, i - 1), beta, beta_dot, ts[i - 1], t[0:2], rows)
                zeta = A[i] @ zetas[i - 1] + loc
            ts.append(t)
            locs.append(loc)
            zetas.append(zeta)
            ws.append(_payload_velocity_products(asm, t) if last else _link_velocity_products(asm, i, Q, t))
        phi_parent = phi
    return _Recursion(A, P, bodies, ts, zetas, locs, ws)


# ---------------------------------------------------------------------------
# Dense DeNOC matrices and the equations of motion
# ---------------------------------------------------------------------------


class DenocMatrices(NamedTuple):
    """`N_l` (block lower-triangular twist propagation), `N_d` (block-diagonal joint-motion
    propagation) and `M_b` (block-diagonal body inertia), so that the stacked twists are
    `t = N_l N_d Q_dot` and `M = N_d^T N_l^T M_b N_l N_d`. Bodies: link i with its hub
    and rotor (twist `[u_x, u_y, omega, q_dot_i, Omega_i]`), then the payload
    (`[u_x, u_y, omega]`)."""

    N_l: jnp.ndarray
    N_d: jnp.ndarray
    M_b: jnp.ndarray
    gamma: jnp.ndarray  # stacked body wrenches (gravity, bending, modal damping)


def _offsets(asm):
    dims = [_dim(lm) for lm in asm.links] + [3]
    offs = [0]
    for d in dims:
        offs.append(offs[-1] + d)
    return dims, offs


def _matrices(asm, rec):
    lay = asm.layout
    n = asm.chain.n_links
    dims, _ = _offsets(asm)
    rows = []
    for i in range(n + 1):
        blocks = [None] * (n + 1)
        blocks[i] = jnp.eye(dims[i])
        for j in range(i - 1, -1, -1):  # N_l[i, j] = A_i N_l[i-1, j]
            blocks[j] = rec.A[i] @ rows[i - 1][j]
        for j in range(i + 1, n + 1):
            blocks[j] = jnp.zeros((dims[i], dims[j]))
        rows.append(blocks)
    N_l = jnp.block(rows)
    N_d = jnp.concatenate([jsl.block_diag(*rec.P[:n]), jnp.zeros((3, lay.n_dof))], axis=0)
    M_b = jsl.block_diag(*[b.Mb for b in rec.bodies])
    gamma = jnp.concatenate([b.gamma for b in rec.bodies])
    return DenocMatrices(N_l, N_d, M_b, gamma)


def denoc_matrices(asm: AssembledChain | Chain, Q, Qd=None) -> DenocMatrices:
    """The DeNOC matrices `N_l(Q)`, `N_d`, body inertia `M_b(Q)` and body wrenches (the
    modal damping part of the wrenches needs `Qd`; zero rates if omitted)."""
    asm = assemble(asm)
    return _matrices(asm, _recursion(asm, Q, Qd))


def _joint_forces(asm, Q, Qd, torque):
    """Forces acting across joints (torque, joint springs and dampers): power = force x
    relative joint rate, so they are generalised forces as they stand (paper 000's tau)."""
    lay, chain = asm.layout, asm.chain
    F = jnp.zeros((lay.n_dof,))
    torque = jnp.asarray(torque)
    for i, joint in enumerate(chain.joints):
        k = lay.actuated[i]
        F = F.at[k].add(torque[i] - joint.damping * Qd[k])
        if joint.elastic:
            r, th = lay.rotor[i], lay.theta[i]
            f = joint.stiffness * (Q[r] - Q[th]) + joint.spring_damping * (Qd[r] - Qd[th])
            F = F.at[r].add(-f).at[th].add(f)
    return F


def denoc_equations(asm: AssembledChain | Chain, Q, Qd, torque):
    """`(M, h, F)` from one pass: `M = N^T M_b N`, `h = N^T (M_b N_dot Q_dot + w_b)`,
    `F = tau_joint + N^T gamma_b` (`N = N_l N_d`), so that `M Q_ddot + h = F`."""
    asm = assemble(asm)
    rec = _recursion(asm, Q, Qd)
    mats = _matrices(asm, rec)
    N = mats.N_l @ mats.N_d
    M = N.T @ mats.M_b @ N
    h = N.T @ (mats.M_b @ jnp.concatenate(rec.zeta) + jnp.concatenate(rec.w))
    F = _joint_forces(asm, Q, Qd, torque) + N.T @ mats.gamma
    return M, h, F


def denoc_mass_matrix(asm: AssembledChain | Chain, Q):
    """M(Q) = N^T M_b N, N = N_l N_d."""
    asm = assemble(asm)
    mats = denoc_matrices(asm, Q)
    N = mats.N_l @ mats.N_d
    return N.T @ mats.M_b @ N


def denoc_velocity_terms(asm: AssembledChain | Chain, Q, Qd):
    """h(Q, Q_dot) = N^T (M_b N_dot Q_dot + w_b)."""
    return denoc_equations(asm, Q, Qd, jnp.zeros(assemble(asm).chain.n_links))[1]


def denoc_generalised_forces(asm: AssembledChain | Chain, Q, Qd, torque):
    """F = tau_joint + N^T gamma_b (gravity, bending and modal damping as body wrenches)."""
    return denoc_equations(asm, Q, Qd, torque)[2]


def denoc_accelerations(asm: AssembledChain | Chain, Q, Qd, torque):
    """Forward dynamics by the dense DeNOC equations: Q_ddot = M^-1 (F - h), Cholesky."""
    M, h, F = denoc_equations(asm, Q, Qd, torque)
    return jsl.cho_solve(jsl.cho_factor(M), F - h)


# ---------------------------------------------------------------------------
# O(n) recursive forward dynamics (articulated-body recursion on the DeNOC blocks)
# ---------------------------------------------------------------------------


def denoc_forward_dynamics_recursive(asm: AssembledChain | Chain, Q, Qd, torque):
    r"""Forward dynamics in O(n) operations, from the same blocks `A_i`, `P_i`, `M_b`,
    `w_b`, `zeta` (articulated-body inertia recursion).

    The force transmitted into body i from everything outboard, in body i's twist
    coordinates, is `F_i = M_i t_dot_i + w_i - gamma_i + sum_c A_c^T F_c`, and joint i's
    equation is `P_i^T F_i = tau_i` (the rows of `N^T (...) = tau`). Writing `F_i =
    I_i t_dot_i + p_i` (articulated inertia and bias), a child c with `t_dot_c = A_c
    t_dot_i + P_c Q_ddot_c + zeta'_c` (`zeta'_c = A_dot_c t_i`) gives, with `U = I_c
    P_c`, `D = P_c^T U`,

        Q_ddot_c = D^-1 (tau_c - U^T (A_c t_dot_i + zeta'_c) - P_c^T p_c),
        I_i += A_c^T (I_c - U D^-1 U^T) A_c,
        p_i += A_c^T ((I_c - U D^-1 U^T) zeta'_c + p_c + U D^-1 (tau_c - P_c^T p_c)).

    Backward pass from the payload to body 1, then a forward pass from the fixed base
    (`t_dot_0 = 0`). The joint-level forces `tau_i` are `_joint_forces`; per body the
    work is a few (4 + m)-square products and one (1 or 2 + m)-square solve.
    """
    asm = assemble(asm)
    lay, n = asm.layout, asm.chain.n_links
    rec = _recursion(asm, Q, Qd)
    tau = _joint_forces(asm, Q, Qd, torque)
    local = rec.local  # zeta'_i = A_dot_i t_{i-1}
    # payload: no joint of its own, folds rigidly into body n
    Ip = rec.bodies[n].Mb
    pp = rec.w[n] - rec.bodies[n].gamma + Ip @ local[n]
    I_art = [None] * n
    p_art = [None] * n
    D_fac = [None] * n
    U_ = [None] * n
    u_ = [None] * n
    child_I = rec.A[n].T @ Ip @ rec.A[n]
    child_p = rec.A[n].T @ pp
    for i in range(n - 1, -1, -1):
        I_i = rec.bodies[i].Mb + child_I
        p_i = rec.w[i] - rec.bodies[i].gamma + child_p
        s, e = _joint_slice(lay, i)
        P = rec.P[i]
        U = I_i @ P
        D = P.T @ U
        fac = jsl.cho_factor(D)
        u = tau[s:e] - P.T @ p_i
        I_art[i], p_art[i], D_fac[i], U_[i], u_[i] = I_i, p_i, fac, U, u
        if i > 0:
            Ia = I_i - U @ jsl.cho_solve(fac, U.T)
            pa = Ia @ local[i] + p_i + U @ jsl.cho_solve(fac, u)
            child_I = rec.A[i].T @ Ia @ rec.A[i]
            child_p = rec.A[i].T @ pa
    Qdd = []
    t_dot_parent = None
    for i in range(n):
        a = local[i] if i == 0 else rec.A[i] @ t_dot_parent + local[i]
        qdd = jsl.cho_solve(D_fac[i], u_[i] - U_[i].T @ a)
        Qdd.append(qdd)
        t_dot_parent = a + rec.P[i] @ qdd
    return jnp.concatenate(Qdd)

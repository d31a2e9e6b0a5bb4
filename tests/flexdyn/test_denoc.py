"""Paper 000's DeNOC formulation (flexdyn.denoc) against the Lagrangian core (flexdyn.chain).

The two are independent: the core differentiates the kinetic energy automatically, the DeNOC
side builds body inertias, velocity products and twist propagation by hand. Checked here:

1. the body pieces: M_b = int rho B^T B and w_b = int rho B^T kappa (paper 000's w_hat, eq. 4/8)
   by direct quadrature of the mode shapes; w_b = the Euler-Poincare form of the same body;
2. the twists t = N_l N_d Q_dot and the bias N_dot Q_dot against the core's kinematics (`frames`)
   differentiated by AD (tests may use AD);
3. at random states of random chains (1-4 links, rigid/flexible with 1-3 modes, rigid/elastic
   joints, with and without the Spong approximation, gear ratios, hubs, payload with inertia,
   gravity in any direction, joint/spring/modal damping): M, h, F and the accelerations (dense
   and the O(n) recursion) equal fd.mass_matrix, fd.velocity_terms, the core's generalised
   forces and fd.accelerations to 1e-10 relative;
4. paper 000's eq. (7) (rigid pendulum, corrected gravity moment) and eq. (10) (one-mode
   flexible pendulum, corrected terms; see the flexdyn.denoc docstring).

Each structure is jit-compiled once (`eqx.filter_jit`, chain parameters traced, states vmapped).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
from flexdyn import denoc as dn
from flexdyn.chain import generalised_forces
from flexdyn.kinematics import frames
from flexdyn.modes import GAUSS_W, GAUSS_X, evaluate_shapes

RTOL = 1e-10
_assemble = eqx.filter_jit(fd.assemble)  # eager assembly (mode-shape roots) is slow


def _rel_err(x, y, scale=None):
    """max |x - y| / scale per leading (state) index, then the worst; scale defaults to max |y|."""
    x, y = np.asarray(x), np.asarray(y)
    axes = tuple(range(1, x.ndim))
    scale = np.max(np.abs(y), axis=axes) if scale is None else np.asarray(scale)
    return float(np.max(np.max(np.abs(x - y), axis=axes) / scale))


# ---------------------------------------------------------------------------
# Random chains and states
# ---------------------------------------------------------------------------

# Structure: per link (n_modes or 0 for rigid, joint kind), joint kind in
# {"rigid", "rigid-spong", "elastic", "elastic-spong"}.
STRUCTURES = {
    # a flexible link on an elastic joint and a rigid link on a geared joint with its rotor: the
    # smallest chain with flexible and rigid links, elastic and rigid joints and rotors (CI runs
    # the derivative test on it alone; the Spong variants are in the four-link chain)
    "flex2-elastic+rigid-rotor": [(2, "elastic"), (0, "rigid")],
    "flex2-elastic+rigid-rotor+flex3": [(2, "elastic"), (0, "rigid"), (3, "rigid")],
    "rigid+flex3-elastic-spong+flex1-rigid-spong+rigid-elastic": [
        (0, "rigid"),
        (3, "elastic-spong"),
        (1, "rigid-spong"),
        (0, "elastic"),
    ],
}


def _random_chain(structure, rng):
    links, joints, hubs = [], [], []
    for n_modes, kind in structure:
        length = rng.uniform(0.2, 0.8)
        if n_modes:
            links.append(
                fd.FlexibleLink(
                    length,
                    rho=rng.uniform(0.1, 1.0),
                    EI=rng.uniform(0.5, 5.0),
                    n_modes=n_modes,
                    damping_ratio=rng.uniform(0.0, 0.05, n_modes),
                    sqrt_stiffness_damping=rng.uniform(0.0, 0.1),
                )
            )
        else:
            links.append(
                fd.RigidLink(
                    length,
                    rng.uniform(0.2, 2.0),
                    com=rng.uniform(-0.2, 1.0) * length,
                    inertia=rng.uniform(0.001, 0.05),
                )
            )
        spong = kind.endswith("spong")
        if kind.startswith("elastic"):
            joints.append(
                fd.ElasticJoint(
                    stiffness=rng.uniform(20.0, 200.0),
                    rotor_inertia=rng.uniform(1e-4, 1e-2),
                    gear_ratio=rng.uniform(1.0, 50.0),
                    damping=rng.uniform(0.0, 0.05),
                    spring_damping=rng.uniform(0.0, 0.05),
                    spong_approximation=spong,
                )
            )
        else:
            joints.append(
                fd.RigidJoint(
                    damping=rng.uniform(0.0, 0.05),
                    rotor_inertia=rng.uniform(0.0, 1e-3),
                    gear_ratio=rng.uniform(1.0, 30.0),
                    spong_approximation=spong,
                )
            )
        hubs.append(fd.Hub(mass=rng.uniform(0.0, 1.0), inertia=rng.uniform(0.0, 0.02)))
    angle = rng.uniform(-math.pi, math.pi)
    gravity = rng.uniform(0.0, 15.0) * np.array([math.cos(angle), math.sin(angle)])
    payload = fd.Payload(rng.uniform(0.0, 0.5), rng.uniform(0.0, 0.01))
    return fd.Chain(links, joints, hubs, payload, gravity=tuple(gravity))


def _random_states(chain, rng, n_states):
    lay = chain.layout
    n = lay.n_dof
    Q = rng.uniform(-math.pi, math.pi, (n_states, n))
    Qd = rng.normal(0.0, 2.0, (n_states, n))
    for i, idx in enumerate(lay.modal):
        length = float(chain.links[i].length)
        for k in idx:
            Q[:, k] = rng.normal(0.0, 0.05 * length, n_states)  # deflections of a few % of l
            Qd[:, k] = rng.normal(0.0, 0.5 * length, n_states)
    torque = rng.normal(0.0, 1.0, (n_states, chain.n_links))
    return jnp.asarray(Q), jnp.asarray(Qd), jnp.asarray(torque)


@eqx.filter_jit
def _both(chain, Q, Qd, torque):
    """DeNOC and core quantities, vmapped over states; one compilation per structure."""
    asm = fd.assemble(chain)

    def one(Q, Qd, tau):
        M, h, F = dn.denoc_equations(asm, Q, Qd, tau)
        M_core, h_core = fd.mass_and_velocity_terms(asm, Q, Qd)
        Qdd_core = fd.accelerations(asm, Q, Qd, tau)
        return {
            "M": (M, M_core),
            "h": (h, h_core),
            "F": (F, generalised_forces(asm, Q, Qd, tau)),
            "Qdd": (dn.denoc_accelerations(asm, Q, Qd, tau), Qdd_core),
            "Qdd_recursive": (dn.denoc_forward_dynamics_recursive(asm, Q, Qd, tau), Qdd_core),
            # inverse dynamics (formed without M in the core) at an arbitrary Q_ddot (here tau
            # reused as a scale): DeNOC's M Q_ddot + h - F(torque = 0)
            "inverse_dynamics": (
                M @ (Qd * tau[0]) + h - dn.denoc_equations(asm, Q, Qd, jnp.zeros_like(tau))[2],
                fd.inverse_dynamics(asm, Q, Qd, Qd * tau[0]),
            ),
        }

    return jax.vmap(one)(Q, Qd, torque)


def _compare(out, Qd):
    """Worst relative error per quantity. h is scaled by max(|h|, |M| |Q_dot|^2) (its natural
    size: a rigid link on a fixed base has h = 0 exactly here, round-off in the core)."""
    M = np.asarray(out["M"][1])
    errs = {}
    for key, (ours, core) in out.items():
        scale = None
        if key == "h":
            natural = np.max(np.abs(M), axis=(1, 2)) * np.max(np.abs(np.asarray(Qd)), axis=1) ** 2
            scale = np.maximum(np.max(np.abs(np.asarray(core)), axis=1), natural)
        errs[key] = _rel_err(ours, core, scale)
    return errs


# ---------------------------------------------------------------------------
# 1. Body pieces: quadrature of paper 000's w_hat, and the Euler-Poincare form
# ---------------------------------------------------------------------------


def _flexible_body(rng, n_modes=3):
    chain = fd.Chain(
        [fd.FlexibleLink(0.6, 0.4, 2.0, n_modes=n_modes)],
        hubs=[fd.Hub(mass=0.3, inertia=0.01)],
        payload=fd.Payload(0.2, 0.003),
        gravity=(2.0, -9.0),
    )
    asm = _assemble(chain)
    Q, Qd, _ = _random_states(chain, rng, 1)
    Q, Qd = Q[0], Qd[0]
    t = jnp.asarray(rng.normal(size=4 + n_modes))  # any twist [u_x, u_y, omega, q_dot, Omega]
    return chain, asm, Q, Qd, t


def test_body_inertia_and_velocity_products_by_quadrature(rng):
    """M_b = int rho B^T B dx and w_b = int rho B^T kappa dx (+ hub point mass and inertia),
    kappa = omega S u + 2 omega S [0, v_dot] - omega^2 [x, v]: paper 000's w_hat (eq. 8) with
    t_dot = 0, by quadrature of the mode shapes at the Gauss points (1e-13 rel)."""
    chain, asm, Q, Qd, t = _flexible_body(rng)
    lm, link, hub = asm.links[0], chain.links[0], chain.hubs[0]
    m = link.n_modes
    q = np.asarray(Q[1:])
    l, rho = float(link.length), float(link.rho)
    xi = np.asarray(GAUSS_X)
    x, w = xi * l, np.asarray(GAUSS_W) * l
    phi = np.asarray(evaluate_shapes(lm.lam, lm.coef, jnp.asarray(xi)))  # (G, m)
    v = phi @ q
    ux, uy, om, qd = (float(t[0]), float(t[1]), float(t[2]), np.asarray(t[3 : 3 + m]))
    Mb_quad = np.zeros((4 + m, 4 + m))
    w_quad = np.zeros(4 + m)
    for xk, wk, vk, phik in zip(x, w, v, phi):
        B = np.zeros((2, 4 + m))
        B[0, 0], B[1, 1], B[0, 2], B[1, 2], B[1, 3 : 3 + m] = 1.0, 1.0, -vk, xk, phik
        kappa = np.array([-om * uy - 2 * om * (phik @ qd) - om**2 * xk, om * ux - om**2 * vk])
        Mb_quad += rho * wk * B.T @ B
        w_quad += rho * wk * B.T @ kappa
    mh, Jh = float(hub.mass), float(hub.inertia)
    Mb_quad[0, 0] += mh
    Mb_quad[1, 1] += mh
    Mb_quad[2, 2] += Jh
    Mb_quad[-1, -1] += float(chain.joints[0].rotor_inertia)
    w_quad[0] += -mh * om * uy
    w_quad[1] += mh * om * ux
    body = dn._link_body(asm, 0, Q, Qd, jnp.asarray(0.3))
    w_b = dn._link_velocity_products(asm, 0, Q, t)
    assert _rel_err(body.Mb[None], Mb_quad[None]) < 1e-13
    assert _rel_err(w_b[None], w_quad[None]) < 1e-13
    # gravity wrench: int rho B^T g_b dx (+ hub)
    g_b = np.array([-1.3, 4.0])
    gam_quad = sum(
        rho * wk * np.array([g_b[0], g_b[1], -vk * g_b[0] + xk * g_b[1], *(phik * g_b[1])])
        for xk, wk, vk, phik in zip(x, w, v, phi)
    )
    gam_quad[:2] += mh * g_b
    angle = math.atan2(float(chain.gravity[1]), float(chain.gravity[0])) - math.atan2(g_b[1], g_b[0])
    scale = float(jnp.linalg.norm(chain.gravity)) / np.linalg.norm(g_b)
    gam = dn._link_body(asm, 0, Q, jnp.zeros_like(Qd), jnp.asarray(angle)).gamma
    elastic = np.concatenate([np.zeros(3), -np.asarray(lm.stiffness) @ q, [0.0]])
    assert _rel_err(((gam - elastic) / scale)[None], np.concatenate([gam_quad, [0.0]])[None]) < 1e-12


def test_velocity_products_are_euler_poincare(rng):
    """w_b = M_dot_b t + [omega S p_u, u x p_u, -dT_b/dq, 0] with p = M_b t, T_b = t^T M_b t / 2
    (M_dot and dT/dq by AD here, in the test)."""
    chain, asm, Q, Qd, t = _flexible_body(rng)
    m = chain.links[0].n_modes
    qdot = t[3 : 3 + m]

    def Mb_of(q):
        return dn._link_body(asm, 0, Q.at[1:].set(q), jnp.zeros_like(Qd), jnp.asarray(0.0)).Mb

    q = Q[1:]
    Mb = Mb_of(q)
    _, Mdot = jax.jvp(Mb_of, (q,), (qdot,))
    p = Mb @ t
    dT_dq = jax.grad(lambda q_: 0.5 * t @ Mb_of(q_) @ t)(q)
    ux, uy, om = t[0], t[1], t[2]
    conv = jnp.concatenate([om * jnp.stack([-p[1], p[0]]), jnp.stack([ux * p[1] - uy * p[0]]), -dT_dq, jnp.zeros(1)])
    assert _rel_err(dn._link_velocity_products(asm, 0, Q, t)[None], (Mdot @ t + conv)[None]) < 1e-13


# ---------------------------------------------------------------------------
# 2. Twist propagation against the core's kinematics
# ---------------------------------------------------------------------------


@eqx.filter_jit
def _twists(asm, Q, Qd):
    lay, chain = asm.layout, asm.chain
    f, fdot = jax.jvp(lambda Q_: frames(asm, Q_), (Q,), (Qd,))
    expected = []
    for i, lm in enumerate(asm.links):
        R = dn._rot(f.angle[i])
        joint = chain.joints[i]
        s_dot = Qd[lay.actuated[i]]
        carrier = jnp.zeros(()) if joint.spong_approximation else fdot.rotor_carrier[i]
        qd = Qd[lay.modal[i][0] : lay.modal[i][-1] + 1] if lay.modal[i] else jnp.zeros(0)
        expected.append(R.T @ fdot.origin[i])
        expected.append(jnp.stack([fdot.angle[i]]))
        expected.append(qd)
        expected.append(jnp.stack([carrier + joint.gear_ratio * s_dot]))
    expected.append(dn._rot(f.tip_angle[-1]).T @ fdot.end)
    expected.append(jnp.stack([fdot.tip_angle[-1]]))
    mats = dn.denoc_matrices(asm, Q)
    N = mats.N_l @ mats.N_d
    rec = dn._recursion(asm, Q, Qd)
    _, Ndot = jax.jvp(lambda Q_: (lambda m_: m_.N_l @ m_.N_d)(dn.denoc_matrices(asm, Q_)), (Q,), (Qd,))
    return mats, N @ Qd, jnp.concatenate(rec.t), jnp.concatenate(rec.zeta), Ndot @ Qd, jnp.concatenate(expected)


def test_twists_and_bias_match_kinematics(rng):
    """t = N_l N_d Q_dot reproduces (u_i = R(phi_i)^T o_dot_i, phi_dot_i, q_dot_i, rotor rate) and
    the payload's (R(psi_n)^T o_dot_end, psi_dot_n) from `flexdyn.kinematics.frames` (AD here);
    N_dot Q_dot (hand recursion) = d/dt(N) Q_dot (AD); N_l is block lower-triangular with
    identity diagonal blocks; N_d is block-diagonal."""
    chain = _random_chain([(1, "elastic-spong"), (2, "rigid")], rng)
    asm = _assemble(chain)
    lay = asm.layout
    Q, Qd, _ = _random_states(chain, rng, 1)
    mats, t_N, t_rec, zeta, zeta_ad, expected = _twists(asm, Q[0], Qd[0])
    assert _rel_err(t_N[None], expected[None]) < 1e-13
    assert _rel_err(t_rec[None], expected[None]) < 1e-13
    assert _rel_err(zeta[None], zeta_ad[None]) < 1e-12

    dims, offs = dn._offsets(asm)
    N_l, N_d = np.asarray(mats.N_l), np.asarray(mats.N_d)
    for i in range(len(dims)):
        rows = slice(offs[i], offs[i + 1])
        assert np.array_equal(N_l[rows, offs[i] : offs[i + 1]], np.eye(dims[i]))
        assert not np.any(N_l[rows, offs[i + 1] :])
    block = np.zeros_like(N_d, dtype=bool)
    for i in range(chain.n_links):
        s, e = dn._joint_slice(lay, i)
        block[offs[i] : offs[i + 1], s:e] = True
    assert not np.any(N_d[~block])


# ---------------------------------------------------------------------------
# 3. DeNOC = Lagrange at random states of random chains
# ---------------------------------------------------------------------------


# The three-link structure runs with the slow tests (CI time: 25 s in a 2-worker run): its kinds
# of link and joint are in the two-link one and in the four-link one.
@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=pytest.mark.slow) if n == "flex2-elastic+rigid-rotor+flex3" else n for n in STRUCTURES],
)
def test_denoc_equals_lagrange(name, rng):
    """M, h, F, Q_ddot (dense and recursive) and the inverse dynamics of the DeNOC
    formulation equal the core's to 1e-10 relative (of the largest entry, per state): 2
    random parameter sets x 6 random states per structure."""
    worst = {}
    for _ in range(2):
        chain = _random_chain(STRUCTURES[name], rng)
        Q, Qd, torque = _random_states(chain, rng, 6)
        for key, err in _compare(_both(chain, Q, Qd, torque), Qd).items():
            worst[key] = max(worst.get(key, 0.0), err)
    assert all(v < RTOL for v in worst.values()), worst


def test_single_link_cases_equal_lagrange(rng):
    """1-link chain (rigid link, elastic joint with rotor) at random states (the one-mode
    flexible link on its own: `test_flexible_pendulum_eq10`)."""
    for structure in ([(0, "elastic")],):
        chain = _random_chain(structure, rng)
        Q, Qd, torque = _random_states(chain, rng, 6)
        errs = _compare(_both(chain, Q, Qd, torque), Qd)
        assert all(v < RTOL for v in errs.values()), (structure, errs)


# ---------------------------------------------------------------------------
# 4. Paper 000's pendulums, eq. (7) and eq. (10)
# ---------------------------------------------------------------------------

G = fd.rigs.STANDARD_GRAVITY


@eqx.filter_jit
def _denoc_terms(chain, Q, Qd):
    asm = fd.assemble(chain)
    tau = jnp.zeros(chain.n_links)
    return jax.vmap(
        lambda Q_, Qd_: (
            dn.denoc_mass_matrix(asm, Q_),
            dn.denoc_velocity_terms(asm, Q_, Qd_),
            dn.denoc_generalised_forces(asm, Q_, Qd_, tau),
            dn.denoc_accelerations(asm, Q_, Qd_, tau),
            fd.accelerations(asm, Q_, Qd_, tau),
        )
    )(Q, Qd)


def test_rigid_pendulum_eq7(rng):
    """Paper 000 eq. (7), gravity moment corrected: (rho l^3/3 + m_p l^2 + I_h) theta'' +
    xi theta' = -(rho l^2/2 + m_p l) g cos(theta), theta counter-clockwise from the
    horizontal (g = (0, -g)); with the paper's printed rho l^2 g cos(theta) (no 1/2) the
    acceleration would be wrong by the rod's whole gravity moment."""
    rho_l, l, m_p, I_h, xi = 0.180, 0.30, 0.020, 2e-5, 1.9e-3
    chain = fd.rigs.rigid_pendulum(joint_damping=xi, payload_mass=m_p, hub_inertia=I_h)
    theta = jnp.asarray(rng.uniform(-math.pi, math.pi, (8, 1)))
    rate = jnp.asarray(rng.uniform(-5, 5, (8, 1)))
    M, h, F, Qdd, Qdd_core = _denoc_terms(chain, theta, rate)
    rho = rho_l / l
    I = rho * l**3 / 3 + m_p * l**2 + I_h
    moment = -(rho * l**2 / 2 + m_p * l) * G * np.cos(np.asarray(theta[:, 0]))
    np.testing.assert_allclose(np.asarray(M[:, 0, 0]), I, rtol=1e-13)
    assert float(jnp.max(jnp.abs(h))) == 0.0
    np.testing.assert_allclose(np.asarray(F[:, 0]), moment - xi * np.asarray(rate[:, 0]), rtol=1e-13, atol=0)
    expected = (moment - xi * np.asarray(rate[:, 0])) / I
    np.testing.assert_allclose(np.asarray(Qdd[:, 0]), expected, rtol=1e-12, atol=1e-12 * np.max(np.abs(expected)))
    np.testing.assert_allclose(np.asarray(Qdd_core[:, 0]), expected, rtol=1e-12, atol=1e-12 * np.max(np.abs(expected)))
    printed = rho * l**2 * G * np.cos(np.asarray(theta[:, 0]))  # the paper's tau, no 1/2
    assert np.max(np.abs(np.abs(printed) - np.abs(moment))) > 0.1 * np.max(np.abs(moment))


def test_flexible_pendulum_eq10(rng):
    """Paper 000 eq. (10), one mode s(x), S0 = int s, S1 = int s^2, S2 = int x s, S3 = s(l),
    payload point mass m_p, hub I_h, joint damping zeta, modal damping zeta_m, bending K:

        M11 = rho l^3/3 + rho S1 b^2 + m_p (l^2 + S3^2 b^2) + I_h
        M12 = rho S2 + m_p l S3,      M22 = rho S1 + m_p S3^2
        h1  = 2 (rho S1 + m_p S3^2) b theta' b'
        h2  = -(rho S1 + m_p S3^2) b theta'^2          (printed: -(2 S1 + m_p S3^2))
        F1  = -(rho l^2/2 + m_p l) g cos(theta) + (rho S0 + m_p S3) g b sin(theta) - zeta theta'
        F2  = -(rho S0 + m_p S3) g cos(theta) - K b - zeta_m b'     (printed: 0)

    (S_k from `fd.assemble`: the check is on the equations, not the shape). DeNOC and core
    agree with these to 1e-12; the printed centrifugal coefficient 2 S1 does not."""
    m_p, I_h, zeta = 0.03, 2e-5, 1.9e-3
    chain = fd.rigs.flexible_pendulum(
        n_modes=1, joint_damping=zeta, damping_ratio=0.01, hub_inertia=I_h, payload_mass=m_p
    )
    asm = _assemble(chain)
    lm = asm.links[0]
    rho, l = float(chain.links[0].rho), float(chain.links[0].length)
    S0, S1, S2 = float(lm.a[0]) / rho, float(lm.modal_mass[0, 0]) / rho, float(lm.b[0]) / rho
    S3, K, zeta_m = float(lm.tip_shape[0]), float(lm.stiffness[0, 0]), float(lm.damping[0, 0])
    n = 8
    Q = np.column_stack([rng.uniform(-math.pi, math.pi, n), rng.normal(0, 0.01, n)])
    Qd = np.column_stack([rng.normal(0, 3, n), rng.normal(0, 0.5, n)])
    M, h, F, Qdd, Qdd_core = (np.asarray(a) for a in _denoc_terms(chain, jnp.asarray(Q), jnp.asarray(Qd)))
    th, b = Q[:, 0], Q[:, 1]
    thd, bd = Qd[:, 0], Qd[:, 1]
    M11 = rho * l**3 / 3 + rho * S1 * b**2 + m_p * (l**2 + S3**2 * b**2) + I_h
    M12 = np.full(n, rho * S2 + m_p * l * S3)
    M22 = np.full(n, rho * S1 + m_p * S3**2)
    h1 = 2 * (rho * S1 + m_p * S3**2) * b * thd * bd
    h2 = -(rho * S1 + m_p * S3**2) * b * thd**2
    F1 = -(rho * l**2 / 2 + m_p * l) * G * np.cos(th) + (rho * S0 + m_p * S3) * G * b * np.sin(th) - zeta * thd
    F2 = -(rho * S0 + m_p * S3) * G * np.cos(th) - K * b - zeta_m * bd
    M_ref = np.stack([np.stack([M11, M12], -1), np.stack([M12, M22], -1)], -2)
    assert _rel_err(M, M_ref) < 1e-12
    assert _rel_err(h, np.stack([h1, h2], -1)) < 1e-12
    assert _rel_err(F, np.stack([F1, F2], -1)) < 1e-12
    Qdd_ref = np.linalg.solve(M_ref, np.stack([F1 - h1, F2 - h2], -1)[..., None])[..., 0]
    assert _rel_err(Qdd, Qdd_ref) < 1e-10
    assert _rel_err(Qdd_core, Qdd_ref) < 1e-10
    printed_h2 = -(2 * rho * S1 + m_p * S3**2) * b * thd**2
    assert np.max(np.abs(printed_h2 - h[:, 1])) > 0.25 * np.max(np.abs(h[:, 1]))


# ---------------------------------------------------------------------------
# 5. Derivatives of the core's forward dynamics (the implicit-function rule of
#    `flexdyn.chain.accelerations`) = automatic differentiation through DeNOC's
#    hand-written equations
# ---------------------------------------------------------------------------


def _scaled_jacobians(jac, dyn):
    """Derivatives w.r.t. (parameters, Q, Q_dot, torque) as one flat array per state, the
    parameter columns multiplied by the parameter (d Q_ddot / d log p), so that every
    column is on the scale of Q_ddot itself. The derivative w.r.t. a symmetric matrix
    (modal mass, stiffness, damping) is symmetrised: only symmetric perturbations are
    defined, and a formula may read either triangle."""
    d_dyn, d_Q, d_Qd, d_tau = jac
    cols = []
    for g, p in zip(jax.tree_util.tree_leaves(d_dyn), jax.tree_util.tree_leaves(dyn)):
        g, p = np.asarray(g), np.asarray(p)
        if p.ndim == 2 and p.shape[0] == p.shape[1] and np.allclose(p, p.T, rtol=1e-12, atol=0.0):
            g = 0.5 * (g + np.swapaxes(g, -1, -2))
        cols.append((g * p).reshape(g.shape[0], g.shape[1], -1))
    return np.concatenate([np.asarray(c) for c in (*cols, d_Q, d_Qd, d_tau)], axis=-1)


def _core_and_denoc(name, rng, n_states):
    """Q_ddot of the core and of DeNOC as functions of (the assembled chain's arrays, Q,
    Q_dot, torque): the shape integrals and every physical parameter are differentiated,
    the mode-shape computation is not (it is the same for both)."""
    chain = _random_chain(STRUCTURES[name], rng)
    dyn, static = eqx.partition(fd.assemble(chain), eqx.is_inexact_array)

    def core(dyn, Q, Qd, tau):
        return fd.accelerations(eqx.combine(dyn, static), Q, Qd, tau)

    def denoc(dyn, Q, Qd, tau):
        return dn.denoc_accelerations(eqx.combine(dyn, static), Q, Qd, tau)

    return core, denoc, (dyn, *_random_states(chain, rng, n_states))


STRUCTURE_NAMES = list(STRUCTURES)


@pytest.mark.parametrize(
    "name", [STRUCTURE_NAMES[0], *(pytest.param(n, marks=pytest.mark.slow) for n in STRUCTURE_NAMES[1:])]
)
@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_forward_dynamics_derivatives_equal_denoc(name, rng):
    """`fd.accelerations` is differentiated by its own rule (the Lagrange residual at fixed
    Q_ddot, solved with M's factor), not through the construction of `M`. Its Jacobian
    w.r.t. every array of the assembled chain (physical parameters and shape integrals),
    Q, Q_dot and the torque, forward (`jacfwd`, also with `vmap` inside the
    differentiation, where the rule sees a batched primal) and reverse (`jacrev`, the rule
    transposed), equals AD through DeNOC's hand-written M, h and F to 1e-8 of the largest
    entry, at 3 random states. (The larger structures are slow tests: 109 s for the three-link
    one in a 2-worker run, ~35 s of compilation for the four-link one.)"""
    core, denoc, args = _core_and_denoc(name, rng, 3)
    dyn, Q, Qd, torque = args
    axes, every = (None, 0, 0, 0), (0, 1, 2, 3)
    expected = _scaled_jacobians(jax.jit(jax.vmap(jax.jacfwd(denoc, every), axes))(*args), dyn)
    scale = np.max(np.abs(expected))
    forward = _scaled_jacobians(jax.jit(jax.vmap(jax.jacfwd(core, every), axes))(*args), dyn)
    reverse = _scaled_jacobians(jax.jit(jax.vmap(jax.jacrev(core, every), axes))(*args), dyn)
    assert np.max(np.abs(forward - expected)) < 1e-8 * scale
    assert np.max(np.abs(reverse - expected)) < 1e-8 * scale

    # vmap inside the differentiation: d Q_ddot / d Q_dot of the batch
    batched = jax.jit(jax.jacfwd(lambda Qd_: jax.vmap(core, axes)(dyn, Q, Qd_, torque)))(Qd)
    diag = np.stack([np.asarray(batched)[k, :, k, :] for k in range(Q.shape[0])])
    d_Qd = np.asarray(jax.vmap(jax.jacfwd(denoc, 2), axes)(*args))
    assert np.max(np.abs(diag - d_Qd)) < 1e-8 * np.max(np.abs(d_Qd))


@pytest.mark.slow
def test_forward_dynamics_second_derivatives_equal_denoc(rng):
    """Second derivatives through the rule (it is itself differentiable): d^2 Q_ddot / dQ^2
    by `jacfwd` of `jacrev` of the core equals `jacfwd` of `jacfwd` through DeNOC to 1e-7."""
    core, denoc, (dyn, Q, Qd, torque) = _core_and_denoc(STRUCTURE_NAMES[0], rng, 1)
    second = jax.jit(jax.jacfwd(jax.jacrev(core, 1), 1))(dyn, Q[0], Qd[0], torque[0])
    second_ref = jax.jit(jax.jacfwd(jax.jacfwd(denoc, 1), 1))(dyn, Q[0], Qd[0], torque[0])
    assert np.max(np.abs(second - second_ref)) < 1e-7 * np.max(np.abs(second_ref))

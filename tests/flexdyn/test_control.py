"""flexdyn.control (paper 004's composite controller) against independent references:
SciPy's Riccati solver, the library's modal analysis, an arm built of rigid links, and the
closed-form error dynamics of exact feedback linearisation."""

import logging

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla

import flexdyn as fd
from flexdyn import control

jax.config.update("jax_enable_x64", True)


def riccati_residual(A, B, Q, R, X):
    return A.T @ X + X @ A - X @ B @ np.linalg.solve(R, B.T) @ X + Q


def random_stabilisable(rng, n, m):
    # dense random systems with unstable modes; random (A, B) is controllable with probability 1
    A = rng.normal(size=(n, n))
    B = rng.normal(size=(n, m))
    L = rng.normal(size=(n, n))
    Q = L @ L.T / n + 0.1 * np.eye(n)
    S = rng.normal(size=(m, m))
    R = S @ S.T + np.eye(m)
    return A, B, Q, R


PAPER_REFERENCE = fd.QuinticReference([0.0, 0.0], [np.pi / 2, np.pi / 6], 2.0)  # eq. (71)


@pytest.fixture(scope="module")
def arm():
    return fd.rigs.flexible_link_joint_arm()


@pytest.fixture(scope="module")
def design(arm):
    """The composite controller of the paper's arm with the paper's slow gains."""
    return control.composite_controller(arm, PAPER_REFERENCE, 5.0, 2.0, fast_input_weight=jnp.array([100.0, 100.0]))


# ---------------------------------------------------------------------------
# Riccati equation / LQR
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("n, m", [(4, 1), (12, 2)])
def test_care_matches_scipy(rng, n, m):
    for _ in range(5):
        A, B, Q, R = random_stabilisable(rng, n, m)
        X = np.asarray(control.solve_care(A, B, Q, R))
        X_ref = sla.solve_continuous_are(A, B, Q, R)
        scale = np.abs(X_ref).max()
        np.testing.assert_allclose(X, X.T, rtol=0, atol=1e-12 * scale)
        # backward error: at least as small as SciPy's (Schur method) own
        res, res_ref = (np.abs(riccati_residual(A, B, Q, R, Y)).max() / scale for Y in (X, X_ref))
        assert res <= max(10 * res_ref, 1e-13)
        # forward error: to 1e-9 where the problem is well conditioned (some random draws give
        # |X| ~ 1e7, nearly uncontrollable; there both solvers' answers differ at ~1e-7)
        if scale < 1e4:
            np.testing.assert_allclose(X, X_ref, rtol=1e-9, atol=1e-9 * scale)
            K = np.asarray(control.lqr(A, B, Q, R)[0])
            np.testing.assert_allclose(K, np.linalg.solve(R, B.T @ X_ref), rtol=1e-8, atol=1e-9 * np.abs(K).max())
        # closed loop of our gain: stable
        K = np.asarray(control.lqr(A, B, Q, R)[0])
        assert np.linalg.eigvals(A - B @ K).real.max() < 0


def test_care_fast_subsystem_of_paper004_arm(arm):
    sub = control.fast_subsystem(arm, jnp.zeros(2))
    A, B = np.asarray(sub.A), np.asarray(sub.B)
    # open loop: undamped, eigenvalues on the imaginary axis (what LQR has to move)
    assert np.abs(np.linalg.eigvals(A).real).max() < 1e-6
    for Q, R in [(np.eye(12), np.eye(2)), (np.diag(np.r_[np.ones(6), 0.01 * np.ones(6)]), 100 * np.eye(2))]:
        X = np.asarray(control.solve_care(A, B, Q, R))
        X_ref = sla.solve_continuous_are(A, B, Q, R)
        np.testing.assert_allclose(X, X_ref, rtol=1e-8, atol=1e-9 * np.abs(X_ref).max())
        assert np.abs(riccati_residual(A, B, Q, R, X)).max() <= 1e-9 * np.abs(X).max()
        K = np.linalg.solve(R, B.T @ X)
        assert np.linalg.eigvals(A - B @ K).real.max() < -1e-3


def test_care_without_stabilising_solution_raises():
    # undamped oscillator with no input: the Hamiltonian has eigenvalues +-1j
    A = np.array([[0.0, 1.0], [-1.0, 0.0]])
    with pytest.raises(Exception, match="no stabilising solution"):
        jax.block_until_ready(control.solve_care(A, np.zeros((2, 1)), np.eye(2), np.eye(1)))


def test_care_derivative_matches_finite_differences_of_scipy(rng):
    A, B, Q, R = random_stabilisable(rng, 4, 2)
    W = rng.normal(size=(4, 4))
    dA, dB = rng.normal(size=A.shape), rng.normal(size=B.shape)
    dQ = rng.normal(size=Q.shape)
    dQ = dQ + dQ.T
    dR = np.diag([0.3, -0.2])

    def scalar_scipy(s):
        X = sla.solve_continuous_are(A + s * dA, B + s * dB, Q + s * dQ, R + s * dR)
        return np.sum(W * X)

    h = 1e-5
    fd_deriv = (scalar_scipy(h) - scalar_scipy(-h)) / (2 * h)

    def scalar(s):
        X = control.solve_care(A + s * dA, B + s * dB, Q + s * dQ, R + s * dR)
        return jnp.sum(W * X)

    fwd = jax.jacfwd(scalar)(0.0)
    rev = jax.grad(scalar)(0.0)
    np.testing.assert_allclose(float(fwd), fd_deriv, rtol=1e-6)
    np.testing.assert_allclose(float(rev), fd_deriv, rtol=1e-6)


# ---------------------------------------------------------------------------
# Slow / fast decomposition
# ---------------------------------------------------------------------------


def test_fast_coordinates_and_embeddings(arm):
    assert arm.coordinate_names() == ["alpha1", "theta1", "q1_1", "q1_2", "alpha2", "theta2", "q2_1", "q2_2"]
    assert control.fast_names(arm) == ("q1_1", "q1_2", "q2_1", "q2_2", "delta1", "delta2")
    Q = np.arange(1.0, 9.0)
    z = np.asarray(control.fast_coordinates(arm, Q))
    np.testing.assert_array_equal(z, [3, 4, 7, 8, 1 - 2, 5 - 6])
    P, E = control.rigid_embedding(arm), control.fast_embedding(arm)
    theta = np.array([Q[1], Q[5]])
    np.testing.assert_allclose(P @ theta + E @ z, Q)
    np.testing.assert_array_equal(P.T @ np.asarray(fd.input_matrix(arm)), np.eye(2))


@pytest.mark.parametrize("theta2", [0.0, np.pi / 6])
def test_fast_subsystem_is_the_flexible_part_of_the_arm(arm, theta2):
    """The fast subsystem's natural frequencies are the non-zero ones of the whole arm
    (`fd.modal_analysis`, K v = w^2 M v in the original coordinates): in a horizontal arm
    the rigid-body motion has no stiffness, so the z-dynamics are exact in the linear model."""
    theta = jnp.array([0.3, theta2])
    sub = control.fast_subsystem(arm, theta)
    Q0 = control.rigid_embedding(arm) @ np.asarray(theta)
    ref = np.asarray(fd.modal_analysis(arm, Q0).natural_frequency)
    assert np.all(ref[:2] == 0.0) and np.all(ref[2:] > 1.0)  # two rigid-body modes
    w2 = np.linalg.eigvals(-np.asarray(sub.mass_inverse @ sub.stiffness))
    hz = np.sort(np.sqrt(-w2.real)) / (2 * np.pi)
    np.testing.assert_allclose(hz, ref[2:], rtol=1e-9)
    # scaled form (eq. 67): the same frequencies in the fast time t_f = t / epsilon
    ev = np.linalg.eigvals(np.asarray(sub.A))
    np.testing.assert_allclose(np.sort(np.abs(ev.imag))[::2] / float(sub.epsilon) / (2 * np.pi), ref[2:], rtol=1e-9)
    # input: the torque drives only the joint deflections, through the rotor inertia (B_z = [0; J^-1])
    J = 0.02  # Table 1 rotor inertia, gear ratio 1
    B_ref = np.zeros((6, 2))
    B_ref[4:, :] = np.eye(2) / J
    np.testing.assert_allclose(np.asarray(sub.input_map), B_ref, rtol=0, atol=1e-9 / J)
    # stiffness: link bending blocks and the joint springs, k_c = the smallest diagonal entry
    asm = fd.assemble(arm)
    K_ref = sla.block_diag(asm.links[0].stiffness, asm.links[1].stiffness, 100.0 * np.eye(2))
    np.testing.assert_allclose(np.asarray(sub.stiffness), K_ref, rtol=1e-12, atol=1e-9)
    assert float(sub.scale) == pytest.approx(np.diag(K_ref).min(), rel=1e-12)


def rigid_twin(flexible: fd.Chain, spong: bool) -> fd.Chain:
    """The arm with rigid links (uniform rods of the same mass and length) and rigid
    joints carrying the same rotors: the mu -> 0 limit, built independently."""
    links = [fd.RigidLink(length=link.length, mass=link.rho * link.length) for link in flexible.links]
    joints = [
        fd.RigidJoint(rotor_inertia=j.rotor_inertia, gear_ratio=j.gear_ratio, spong_approximation=spong)
        for j in flexible.joints
    ]
    return fd.Chain(links, joints, flexible.hubs, flexible.payload, gravity=flexible.gravity)


def flexible_arm(spong: bool, gravity=(0.0, 0.0)) -> fd.Chain:
    link = fd.FlexibleLink(length=0.5, rho=0.2, EI=1.0, n_modes=2, sqrt_stiffness_damping=0.1)
    joints = [fd.ElasticJoint(stiffness=100.0, rotor_inertia=0.02, spong_approximation=spong) for _ in range(2)]
    return fd.Chain(
        [link, link], joints, [fd.Hub(), fd.Hub(mass=0.3)], fd.Payload(mass=0.1, inertia=0.005), gravity=gravity
    )


@pytest.mark.parametrize(
    "spong, gravity", [(True, (0.0, 0.0)), pytest.param(False, (0.0, -9.81), marks=pytest.mark.slow)]
)
def test_slow_model_is_the_rigid_arm(rng, spong, gravity):
    flexible = flexible_arm(spong, gravity)
    rigid = rigid_twin(flexible, spong)
    slow = jax.jit(lambda th, thd: control.slow_model(flexible, th, thd))
    rigid_model = jax.jit(lambda th, thd: (fd.mass_matrix(rigid, th), fd.inverse_dynamics(rigid, th, thd, 0 * th)))
    for _ in range(3):
        theta, theta_dot = rng.uniform(-2, 2, size=2), rng.uniform(-3, 3, size=2)
        M_s, h_s = slow(theta, theta_dot)
        M_ref, h_ref = rigid_model(theta, theta_dot)
        np.testing.assert_allclose(np.asarray(M_s), np.asarray(M_ref), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(np.asarray(h_s), np.asarray(h_ref), rtol=1e-11, atol=1e-13)


def test_quasi_static_deflections_hold_the_arm_on_the_slow_motion(rng):
    """At z = z_bar (eq. 64-65) and z_dot = 0, the full arm's accelerations are exactly
    the slow ones, theta_ddot = M_s^-1 (tau - h_s), alpha_ddot = theta_ddot, q_ddot = 0,
    up to the O(z_bar) change of M and h: the mismatch is second order in the load."""
    arm = flexible_arm(True)
    asm = fd.assemble(arm)
    P, E = control.rigid_embedding(arm), control.fast_embedding(arm)
    theta, theta_dot = rng.uniform(-1, 1, size=2), rng.uniform(-1, 1, size=2)

    @jax.jit
    def mismatch(scale):
        tau = scale * jnp.array([0.3, -0.1])
        M_s, h_s = control.slow_model(asm, theta, scale * theta_dot)
        theta_ddot = jnp.linalg.solve(M_s, tau - h_s)
        z_bar = control.quasi_static(asm, theta, scale * theta_dot, theta_ddot, tau)
        Q = P @ theta + E @ z_bar
        Qdd = fd.accelerations(asm, Q, P @ (scale * theta_dot), tau)
        return Qdd - P @ theta_ddot

    small, smaller = np.abs(np.asarray(mismatch(1e-2))).max(), np.abs(np.asarray(mismatch(1e-3))).max()
    # second order in the load (a first-order error would give a ratio of 10)
    assert 80 < small / smaller < 120


# ---------------------------------------------------------------------------
# The controller
# ---------------------------------------------------------------------------


def test_computed_torque_is_exact_on_the_rigid_arm():
    """On the exactly-rigid arm the slow control is exact feedback linearisation: the
    tracking error obeys e_ddot + K_vs e_dot + K_ps e = 0 (closed form below) to solver
    precision, whatever the reference does."""
    rigid = rigid_twin(fd.rigs.flexible_link_joint_arm(), spong=True)
    ref = fd.QuinticReference([0.0, 0.0], [np.pi / 2, np.pi / 6], 2.0)
    ctrl = control.composite_controller(rigid, ref, 5.0, 2.0)
    assert ctrl.fast_gain.shape == (2, 0)
    e0, ed0 = np.array([0.1, -0.05]), np.array([0.0, 0.2])
    y0 = fd.initial_state(rigid, joint_angles=e0, joint_rates=ed0)
    ts = jnp.linspace(0.0, 3.0, 31)
    traj = fd.simulate(rigid, y0, ts, ctrl, rtol=1e-11, atol=1e-12)
    e = np.asarray(traj.Q) - np.asarray(jax.vmap(ref.position)(ts))
    t = np.asarray(ts)[:, None]
    # K_ps = 5, K_vs = 2: roots -1 +- 2j
    e_ref = np.exp(-t) * (e0 * np.cos(2 * t) + (ed0 + e0) / 2 * np.sin(2 * t))
    np.testing.assert_allclose(e, e_ref, rtol=0, atol=1e-8)


def test_composite_stabilises_the_fast_subsystem_over_the_workspace(arm, design):
    K = np.asarray(design.fast_gain)
    for theta2 in np.linspace(0.0, np.pi / 6, 3):
        sub = control.fast_subsystem(arm, jnp.array([0.0, theta2]))
        ev = np.linalg.eigvals(np.asarray(sub.A) - np.asarray(sub.B) @ K)
        assert ev.real.max() < -1e-2
    # the slow-only controller has no fast gain at all
    slow = control.composite_controller(arm, PAPER_REFERENCE, 5.0, 2.0, fast=False)
    assert np.all(np.asarray(slow.fast_gain) == 0.0)


@pytest.mark.slow
def test_composite_torque_at_rest_on_the_reference_is_zero(arm, design):
    # same controller, a constant reference (new array values: no new compilation of the design)
    ctrl = eqx.tree_at(lambda c: c.reference, design, fd.QuinticReference([0.2, -0.1], [0.2, -0.1], 1.0))
    torque = eqx.filter_jit(lambda c, t, y: c(t, y))
    y = fd.initial_state(arm, joint_angles=[0.2, -0.1])
    tau = np.asarray(torque(ctrl, jnp.asarray(0.5), y))
    assert tau.shape == (2,)
    np.testing.assert_allclose(tau, 0.0, atol=1e-12)
    # the rotor of joint 1 ahead of its link: the fast part pulls it back (tau_1 < 0)
    y_def = fd.initial_state(arm, joint_angles=[0.2, -0.1], rotor_angles=[0.21, -0.1])
    assert float(torque(ctrl, jnp.asarray(0.5), y_def)[0]) < 0.0


@pytest.mark.slow
def test_fast_state_rate_is_the_rate_of_the_quasi_steady_deflection(arm, design, rng):
    """x_f's second half is sqrt(k_c) (z_dot - z_bar_dot), z_bar_dot along the commanded slow
    motion (theta_dot, theta_ddot = v): compared with a central difference of z_bar."""
    lay = arm.layout
    idx = np.asarray(lay.theta)
    y = np.array(fd.initial_state(arm, joint_angles=[0.4, 0.2], joint_rates=[0.8, -0.3]))
    y[8:] += 0.01 * rng.normal(size=8)
    t = jnp.asarray(0.7)
    parts = eqx.filter_jit(lambda c, t, y: (c.fast_state(t, y)[0], c.slow_torque(t, y)))
    x_f, (_, v, _) = parts(design, t, jnp.asarray(y))

    def z_bar_at(s):
        yy = y.copy()
        yy[idx] += s * y[8 + idx]
        yy[8 + idx] += s * np.asarray(v)
        return np.asarray(parts(design, t + s, jnp.asarray(yy))[1][2])

    h = 1e-5
    z_bar_dot = (z_bar_at(h) - z_bar_at(-h)) / (2 * h)
    z_dot = np.asarray(control.fast_coordinates(arm, y[8:]))
    expected = np.sqrt(float(design.scale)) * (z_dot - z_bar_dot)
    np.testing.assert_allclose(np.asarray(x_f)[6:], expected, rtol=1e-6, atol=1e-8 * np.abs(expected).max())


class _LogCounter(logging.Handler):
    def __init__(self):
        super().__init__(level=logging.DEBUG)
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def _arm_with_joint_stiffness(k_s):
    arm = fd.rigs.flexible_link_joint_arm()
    k_s = jnp.asarray(k_s, dtype=float)  # not weakly typed, as the rig's own values
    return eqx.tree_at(lambda c: (c.joints[0].stiffness, c.joints[1].stiffness), arm, (k_s, k_s))


def _gain_entry(k_s):
    ctrl = control.composite_controller(
        _arm_with_joint_stiffness(k_s), PAPER_REFERENCE, 5.0, 2.0, fast_input_weight=jnp.array([100.0, 100.0])
    )
    return ctrl.fast_gain[0, 4] + 0.3 * ctrl.fast_gain[1, 11]


def test_gain_design_does_not_recompile(design):
    """New parameter values reuse the compiled design (the `design` fixture compiled it)."""
    handler = _LogCounter()
    logger = logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles():
            a = _gain_entry(jnp.asarray(120.0))
            b = _gain_entry(jnp.asarray(80.0))
    finally:
        logger.removeHandler(handler)
    compiled = [m for m in handler.messages if "composite_controller" in m]
    assert compiled == []
    assert float(a) != float(b)


@pytest.mark.slow
def test_gain_design_forward_derivative_matches_finite_differences():
    k0 = jnp.asarray(100.0)
    h = 1e-3
    g_fd = (_gain_entry(k0 + h) - _gain_entry(k0 - h)) / (2 * h)
    g_fwd = jax.jacfwd(_gain_entry)(k0)
    assert abs(float(g_fd)) > 1e-4  # the gain does depend on the joint stiffness
    np.testing.assert_allclose(float(g_fwd), float(g_fd), rtol=1e-5)


@pytest.mark.slow
def test_gain_design_reverse_derivative_matches_finite_differences():
    k0 = jnp.asarray(100.0)
    h = 1e-3
    g_fd = (_gain_entry(k0 + h) - _gain_entry(k0 - h)) / (2 * h)
    np.testing.assert_allclose(float(jax.grad(_gain_entry)(k0)), float(g_fd), rtol=1e-5)

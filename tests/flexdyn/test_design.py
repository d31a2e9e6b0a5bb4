"""flexdyn.design: the B-spline torque (fast, no ODE solves), the move residuals' derivatives and their elastic-joint
blocks (slow)."""

import re
import warnings

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import flexdyn as fd
from flexdyn import design

T = 1.0  # s


def test_cubic_bspline_closed_form_and_partition_of_unity():
    x = jnp.linspace(-3.0, 3.0, 601)
    b = design.cubic_bspline(x)
    # integral 1, value 2/3 at 0, 1/6 at +-1, zero outside [-2, 2]
    assert float(jnp.sum(b) * (x[1] - x[0])) == pytest.approx(1.0, abs=1e-6)
    assert float(design.cubic_bspline(jnp.asarray(0.0))) == pytest.approx(2 / 3, abs=1e-15)
    assert float(design.cubic_bspline(jnp.asarray(1.0))) == pytest.approx(1 / 6, abs=1e-15)
    assert float(jnp.max(jnp.abs(jnp.where(jnp.abs(x) >= 2, b, 0.0)))) == 0.0
    # the basis sums to one where it is complete: t in [3h, n h], h = T / (n + 3)
    n = 8
    h = T / (n + 3)
    t = jnp.linspace(3 * h, n * h, 50)
    np.testing.assert_allclose(np.asarray(jnp.sum(design.bspline_basis(t, n, T), axis=1)), 1.0, atol=1e-14)


def test_torque_starts_and_ends_smoothly_at_zero(rng):
    torque = design.BSplineTorque(rng.normal(size=(8, 2)) * 0.3, T, 0.4)

    def tau(t):
        return torque(t)

    d1 = jax.jacfwd(tau)
    d2 = jax.jacfwd(d1)
    ends = jnp.asarray([0.0, T])
    for f in (tau, d1, d2):
        np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(f))(ends)), 0.0, atol=1e-12)
    outside = jax.vmap(tau)(jnp.asarray([-0.5, 1.2, 3.0]))
    assert float(jnp.max(jnp.abs(outside))) == 0.0
    assert float(jnp.max(jnp.abs(jax.vmap(tau)(jnp.linspace(0.0, T, 101))))) > 0.05


def test_torque_limit_holds_for_any_control_points(rng):
    torque = design.BSplineTorque(rng.normal(size=(8, 2)) * 50.0, T, jnp.asarray([0.4, 0.25]))
    tau = jax.vmap(torque)(jnp.linspace(0.0, T, 2001))
    assert np.all(np.abs(np.asarray(tau)) <= np.asarray([0.4, 0.25]))
    # the spline itself goes far beyond: the saturation is what holds the limit
    assert float(jnp.max(jnp.abs(jax.vmap(torque.spline)(jnp.linspace(0.0, T, 2001))))) > 10.0
    with pytest.raises(ValueError, match="tau_max"):
        design.BSplineTorque(np.zeros((8, 2)), T, -1.0)


def test_fit_recovers_a_spline_torque(rng):
    true = design.BSplineTorque(rng.normal(size=(6, 2)) * 0.1, T, 0.4)
    ts = jnp.linspace(0.0, T, 301)
    fitted = design.BSplineTorque.fit(np.asarray(ts), np.asarray(jax.vmap(true)(ts)), 6, T, 0.4)
    np.testing.assert_allclose(np.asarray(fitted.control_points), np.asarray(true.control_points), atol=1e-10)


def test_move_rejects_wrong_number_of_angles():
    with pytest.raises(ValueError, match="2 start and goal angles"):
        design.RestToRestMove(fd.rigs.two_link_flexible_arm(), [0.0], [0.1, 0.2], T, 0.4)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"goal_angles": [float("nan"), 0.0]}, r"RestToRestMove.goal_angles: expected a finite number, got \[nan"),
        ({"duration": -0.8}, r"RestToRestMove.duration: expected a value > 0, got -0.8"),
        ({"duration": 0.0}, r"RestToRestMove.duration: expected a value > 0, got 0"),
        ({"settle": 0.0}, r"RestToRestMove.settle: expected a value > 0, got 0"),
        ({"tau_max": [1.0, 1.0, 1.0]}, r"RestToRestMove.tau_max: expected a scalar or one limit per joint"),
        ({"tau_max": 0.0}, r"RestToRestMove.tau_max: expected a value > 0"),
        ({"n_window": 1}, r"RestToRestMove.n_window: expected an integer >= 2"),
        ({"dt": 0.0}, r"RestToRestMove.dt: expected a value > 0"),
        ({"dt": 0.5}, r"RestToRestMove.dt: expected a step shorter than the move's duration 0.5 s, got 0.5 s"),
    ],
)
def test_move_rejects_bad_arguments_naming_them(change, message):
    """Found in a new-user review: these were accepted, and the design's cost or the move's
    metrics came out NaN or meaningless (a negative duration, a one-sample window), or
    the error came from deep inside (`simulate: ts expected ...`, a broadcasting error)."""
    kwargs = {"start_angles": [0.0, 0.0], "goal_angles": [0.1, 0.5], "duration": 0.5, "tau_max": 0.4, **change}
    with pytest.raises(ValueError, match=message):
        design.RestToRestMove(fd.rigs.two_link_flexible_arm(), **kwargs)


def test_spline_and_payload_arguments_checked_when_given():
    """Review: NaN control points or limits, and a NaN or negative payload, were accepted
    and failed later inside an equinox traceback; samples after `duration` were dropped
    from a fit without a word."""
    with pytest.raises(ValueError, match=r"BSplineTorque.control_points: expected a finite number"):
        design.BSplineTorque(jnp.full((4, 1), jnp.nan), T, 0.4)
    with pytest.raises(ValueError, match=r"BSplineTorque.tau_max: expected a finite number"):
        design.BSplineTorque(jnp.zeros((4, 1)), T, float("nan"))
    with pytest.raises(ValueError, match=r"BSplineTorque.fit.tau_max: expected a finite number"):
        design.BSplineTorque.fit(np.linspace(0, T, 11), np.zeros((11, 1)), 4, T, float("nan"))
    with pytest.warns(UserWarning, match=r"4 of the 15 samples lie after duration = 0.5 s"):
        design.BSplineTorque.fit(np.linspace(0, 0.7, 15), np.zeros((15, 1)), 4, 0.5, 0.4)
    move = design.RestToRestMove(fd.rigs.two_link_flexible_arm(), [0.0, 0.0], [0.1, 0.5], 0.5, 0.4, n_window=5)
    for bad in (float("nan"), -1.0):
        with pytest.raises(ValueError, match=r"RestToRestMove.with_payload.payload_mass: expected"):
            move.with_payload(bad)


def test_move_warns_when_gravity_would_pull_the_arm_off_its_goal():
    """Review: a vertical pendulum's move from hanging to 0.5 rad off was designed without
    a word; the torque is zero after T, so the arm swung back (2 rad from the goal). Oracle:
    the warning reports the uniform strip's static moment, rho L g (L / 2) cos(theta)."""
    chain = fd.rigs.flexible_pendulum()
    hang = -np.pi / 2
    with pytest.warns(UserWarning, match=r"goal angles are not an equilibrium .* gravity exerts ([0-9.]+) N m") as w:
        design.RestToRestMove(chain, [hang], [hang + 0.5], 1.0, 0.3, n_window=5)
    assert len(w) == 1
    stated = float(re.search(r"gravity exerts ([0-9.eE+-]+) N m", str(w[0].message)).group(1))
    link = chain.links[0]
    moment = float(link.rho) * float(link.length) * 9.81 * float(link.length) / 2 * np.cos(hang + 0.5)
    assert float(chain.payload.mass) == 0.0 and stated == pytest.approx(abs(moment), rel=2e-3)
    # hanging to upright: both equilibria, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        design.RestToRestMove(chain, [hang], [np.pi / 2], 1.0, 0.3, n_window=5)


def test_move_warns_of_a_duration_in_milliseconds():
    with pytest.warns(UserWarning, match=r"duration = 800 s is over a minute.*pass 0.8"):
        design.RestToRestMove(fd.rigs.two_link_flexible_arm(), [0.0, 0.0], [0.1, 0.5], 800.0, 0.4)


def test_design_rejects_an_initial_torque_that_does_not_fit_the_move():
    """The design uses the move's duration and limits: an initial spline over another
    duration, other limits or another number of joints is refused, as are payload masses
    that are not a 1-D array of masses (review: a raw vmap rank error)."""
    move = design.RestToRestMove(fd.rigs.two_link_flexible_arm(), [0.0, 0.0], [0.1, 0.5], 0.5, 0.4, n_window=5)
    for initial, message in [
        (design.BSplineTorque(jnp.zeros((4, 2)), 1.2, 0.4), r"initial.duration = 1.2 differs from the move's 0.5"),
        (design.BSplineTorque(jnp.zeros((4, 2)), 0.5, 0.3), r"initial.tau_max = \[0.3 0.3\] differs"),
        (design.BSplineTorque(jnp.zeros((4, 3)), 0.5, 0.4), r"initial has 3 joint columns, the move's arm 2"),
    ]:
        with pytest.raises(ValueError, match=message):
            design.design_move(move, initial)
    with pytest.raises(TypeError, match="initial expected a BSplineTorque"):
        design.design_move(move, fd.BangBang([0.4, 0.4], 0.25))
    for masses, message in [(0.2, r"payload_masses: expected a 1-D array"), ([-0.1, 0.2], r"payload_masses.*>= 0")]:
        with pytest.raises(ValueError, match=message):
            design.design_move(move, move.torque(jnp.zeros((4, 2))), payload_masses=masses)
    with pytest.raises(ValueError, match=r"BSplineTorque.tau_max: expected a scalar or one limit per joint"):
        design.BSplineTorque(jnp.zeros((4, 2)), 0.5, [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r"BSplineTorque.duration: expected a value > 0"):
        design.BSplineTorque(jnp.zeros((4, 2)), -0.5, 0.4)


@pytest.mark.parametrize("weight", [0.0, -1.0, float("nan"), [1.0, 2.0]])
def test_design_rejects_bad_payload_weight(weight):
    move = design.RestToRestMove(fd.rigs.two_link_flexible_arm(), [0.0, 0.0], [0.1, 0.5], 0.5, 0.4, n_window=5)
    initial = move.torque(jnp.zeros((4, 2)))
    with pytest.raises(ValueError, match="payload_weight: expected one number > 0"):
        design.design_move(move, initial, payload_masses=[0.0, 0.1], payload_weight=weight)


@pytest.mark.slow
def test_residual_jacobian_matches_finite_differences(rng):
    # forward-mode derivative through the RK4 solve vs central differences (float64)
    move = design.RestToRestMove(
        fd.rigs.two_link_flexible_arm(), [0.0, 0.0], [0.1, 0.5], 0.5, 0.4, settle=0.2, n_window=11, dt=2e-3
    )
    cp = jnp.asarray(rng.normal(size=(5, 2)) * 0.1)
    direction = jnp.asarray(rng.normal(size=(5, 2)))
    _, jvp = jax.jvp(lambda c: design.move_residuals(c, move), (cp,), (direction,))
    eps = 1e-6
    fd_jvp = (design.move_residuals(cp + eps * direction, move) - design.move_residuals(cp - eps * direction, move)) / (
        2 * eps
    )
    np.testing.assert_allclose(np.asarray(jvp), np.asarray(fd_jvp), rtol=1e-6, atol=1e-9)
    # the robust residuals: the nominal ones, then the at-rest ones of each payload
    rob = design.robust_residuals(cp, move, jnp.asarray([0.03]))
    nom = design.move_residuals(cp, move)
    rest = design.move_residuals(cp, move.with_payload(0.03), at_goal=False)
    np.testing.assert_allclose(np.asarray(rob), np.concatenate([nom, rest]), rtol=1e-12, atol=1e-15)
    # payload_weight scales only the payloads' block
    weighted = design.robust_residuals(cp, move, jnp.asarray([0.03]), payload_weight=2.5)
    np.testing.assert_allclose(np.asarray(weighted), np.concatenate([nom, 2.5 * rest]), rtol=1e-12, atol=1e-15)
    # at rest wherever it stopped: the goal-angle block (the first n_window x n_joints entries) is left out
    full = design.move_residuals(cp, move.with_payload(0.03))
    np.testing.assert_allclose(np.asarray(rest), np.asarray(full)[11 * 2 :], rtol=1e-12, atol=1e-15)


@pytest.mark.slow
def test_elastic_joint_residuals_include_joint_deflections_and_rotor_rates(rng):
    # paper 004's arm: the torque acts on the rotors, the goal is on the link angles; at rest the joint springs must be
    # unloaded (alpha = theta) and the rotors still, so those are residuals too (read here from the raw state)
    arm = fd.rigs.flexible_link_joint_arm()
    move = design.RestToRestMove(arm, [0.0, 0.0], [0.02, 0.05], 0.3, 0.4, settle=0.1, n_window=6, dt=1e-3)
    cp = jnp.asarray(rng.normal(size=(4, 2)) * 0.2)
    r = np.asarray(design.move_residuals(cp, move))
    K, n = 6, 2
    assert r.shape == (K * (n + n) + n + K * n + n,)
    traj = fd.simulate(arm, move.initial_state(), move.output_times(), move.torque(cp), dt=1e-3)
    Q, Qd = np.asarray(traj.Q), np.asarray(traj.Qd)
    alpha, theta = np.asarray(arm.layout.rotor), np.asarray(arm.layout.theta)
    deflection = (Q[1:, alpha] - Q[1:, theta]) / np.sqrt(K)
    np.testing.assert_allclose(r[K * 2 * n + n : -n], deflection.ravel(), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(r[-n:], Qd[1, alpha] * 0.1, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(r[K * 2 * n : K * 2 * n + n], Qd[1, theta] * 0.1, rtol=1e-10, atol=1e-14)
    # not a copy of the link rates: the rotors and links move differently at T
    assert np.max(np.abs(Qd[1, alpha] - Qd[1, theta])) > 1e-3 * np.max(np.abs(Qd[1, theta]))
    assert np.max(np.abs(deflection)) > 1e-6
    # no torque, start = goal: the arm stays at rest and every residual is zero
    still = design.RestToRestMove(arm, [0.3, -0.2], [0.3, -0.2], 0.3, 0.4, settle=0.1, n_window=6, dt=1e-3)
    np.testing.assert_allclose(np.asarray(design.move_residuals(jnp.zeros((4, 2)), still)), 0.0, atol=1e-15)


def test_rigid_joint_residuals_unchanged_in_length():
    # a rigid-joint arm has no rotor coordinates, so no extra residual blocks (shape only, no solve)
    move = design.RestToRestMove(fd.rigs.two_link_flexible_arm(), [0.0, 0.0], [0.1, 0.5], 0.5, 0.4, n_window=11)
    shape = jax.eval_shape(lambda c: design.move_residuals(c, move), jnp.zeros((5, 2))).shape
    assert shape == (11 * (2 + 2) + 2,)


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_design_says_whether_the_arm_reached_its_goal():
    """Review: an infeasible move (here 3 rad in 0.5 s with 0.05 N m) returned the same
    `result` as a good design, and nothing said that it ended far from its goal. Oracle
    for `goal_error`: `move_metrics`' independent simulation of the designed torque."""
    arm = fd.rigs.two_link_flexible_arm()
    T = 0.5
    bang = fd.BangBang([0.2, 0.2], T / 2)  # paper 002's input, compressed; its end point is the feasible goal
    y0 = fd.initial_state(arm, joint_angles=[0.0, 0.0])
    goal = fd.simulate(arm, y0, jnp.asarray([0.0, T]), bang, dt=1e-3).Q[-1, jnp.asarray(arm.layout.theta)]
    feasible = design.RestToRestMove(arm, [0.0, 0.0], goal, T, 0.4, settle=0.2, n_window=5, dt=2e-3)
    infeasible = design.RestToRestMove(arm, [0.0, 0.0], [3.0, 0.0], T, 0.05, settle=0.2, n_window=5, dt=2e-3)
    ts = np.linspace(0.0, T, 201)
    for move, scale, reached in ((feasible, 1.0, True), (infeasible, 0.2, False)):
        samples = scale * np.asarray(jax.vmap(lambda t: bang(t))(jnp.asarray(ts)))
        initial = design.BSplineTorque.fit(ts, samples, 6, T, move.tau_max)
        res = design.design_move(move, initial, max_steps=20)
        metrics = design.move_metrics(move, res.torque)
        assert float(res.goal_error) == pytest.approx(
            max(metrics["angle_error_T"], metrics["angle_error_end"]), rel=0.05
        )
        assert res.reached_goal is reached, res.summary()
        assert ("does not stop at its goal" in res.summary()) is not reached
        # review: `result` read max_steps_reached after a good design; the summary says it is usual
        hit_budget = bool(res.result == optx.RESULTS.max_steps_reached)
        assert ("max_steps_reached, usual for a design" in res.summary()) is hit_budget
    with pytest.raises(ValueError, match=r"design_move.max_steps: expected an integer >= 1, got 0"):
        design.design_move(infeasible, initial, max_steps=0)


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_reverse_mode_gradient_of_the_residuals_with_a_reverse_adjoint():
    """Review: `jax.grad` of a cost on `move_residuals` failed inside diffrax (the default
    forward-mode adjoint cannot be reversed); with `adjoint=RecursiveCheckpointAdjoint()`
    it works, and equals J^T r from the forward-mode Jacobian (the other AD mode)."""
    arm = fd.Chain(
        links=[fd.FlexibleLink(length=0.5, rho=0.2, EI=1.0, n_modes=1)],
        joints=[fd.RigidJoint()],
        hubs=[fd.Hub(inertia=0.02)],
        payload=fd.Payload(mass=0.05),
        gravity=(0.0, 0.0),
    )
    move = design.RestToRestMove(arm, [0.0], [0.3], 0.3, 0.5, settle=0.1, n_window=4, dt=2e-3)
    cp = jnp.asarray([[0.1], [-0.05], [0.02], [-0.1]])

    def cost(c):
        r = design.move_residuals(c, move, adjoint=diffrax.RecursiveCheckpointAdjoint())
        return 0.5 * jnp.sum(r**2)

    grad = jax.grad(cost)(cp)
    r = design.move_residuals(cp, move)
    J = jax.jacfwd(lambda c: design.move_residuals(c, move))(cp)
    np.testing.assert_allclose(np.asarray(grad), np.einsum("i,i...->...", r, J), rtol=1e-9, atol=1e-12)

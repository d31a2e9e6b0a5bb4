"""Tests of `flexdyn.fixed_step` (lean RK4 for batched sweeps and its discrete adjoint) and
`flexdyn.smallsolve`.

Oracles: NumPy's LU solve for the unrolled Cholesky; a Dopri8 solution at rtol 1e-12 and
the fourth-order convergence law (halving dt divides the error by 16) for the
integrator, across a bang-bang switch; conservation of energy for an undamped chain;
diffrax's RK4 (`fd.simulate(..., dt=...)`) for `rk4_trajectory`'s states; JAX's own
reverse mode through the same steps, and central finite differences, for its adjoint.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from adjoint_cases import PENDULUM, PENDULUM_PARAMS, PENDULUM_Y0, pd_tracking  # tests/ is on sys.path

import flexdyn as fd
from flexdyn import fixed_step
from flexdyn.smallsolve import UNROLL_MAX_DOF, refine_rsqrt, spd_solve, spd_solve_rsqrt


@pytest.mark.parametrize("solve", [spd_solve, spd_solve_rsqrt])
@pytest.mark.parametrize("n", [1, 2, 5, 8, UNROLL_MAX_DOF, UNROLL_MAX_DOF + 3])
def test_spd_solve_matches_lu(n, solve):
    rng = np.random.default_rng(n)
    A = rng.normal(size=(n, n))
    M = A @ A.T + n * np.eye(n) * 10.0 ** rng.uniform(-3, 1)  # SPD, condition numbers up to ~1e4
    b = rng.normal(size=n)
    x = np.asarray(jax.jit(solve)(jnp.asarray(M), jnp.asarray(b)))
    np.testing.assert_allclose(x, np.linalg.solve(M, b), rtol=1e-10, atol=1e-12)


def test_one_refinement_step_takes_an_approximate_rsqrt_to_float64():
    """`refine_rsqrt` from starts off by up to 2^-22 (relative), across 600 decades: the
    error ends within 2 units of the last place of the exact `1 / sqrt(s)`, as the
    iteration's cubic error `(5/16) e^3 ~ 2^-68` promises (`flexdyn.scalarize` refines the
    GPU kernel's `rsqrt.approx.f64` so; on the CPU `lax.rsqrt` is exact and the step keeps it)."""
    s = np.logspace(-300, 300, 20_001)
    exact = 1.0 / np.sqrt(s)
    for e in (2.0**-22, -(2.0**-22), 2.0**-30):
        start = exact * (1.0 + e * np.cos(np.arange(s.size)))
        got = np.asarray(refine_rsqrt(jnp.asarray(s), jnp.asarray(start)))
        assert np.max(np.abs(got - exact) / exact) < 2 * np.finfo(float).eps
    got = np.asarray(refine_rsqrt(jnp.asarray(s), jax.lax.rsqrt(jnp.asarray(s))))
    assert np.max(np.abs(got - exact) / exact) < 2 * np.finfo(float).eps


def test_spd_solve_vmapped_and_not_positive_definite():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(16, 4, 4))
    Ms = A @ A.transpose(0, 2, 1) + np.eye(4)
    bs = rng.normal(size=(16, 4))
    x = np.asarray(jax.jit(jax.vmap(spd_solve))(jnp.asarray(Ms), jnp.asarray(bs)))
    np.testing.assert_allclose(x, np.linalg.solve(Ms, bs[..., None])[..., 0], rtol=1e-10)
    # An indefinite matrix yields NaN (as cho_factor does), for the caller's finiteness check.
    assert np.isnan(np.asarray(spd_solve(jnp.diag(jnp.array([1.0, -1.0])), jnp.ones(2)))).any()
    assert np.isnan(np.asarray(spd_solve_rsqrt(jnp.diag(jnp.array([1.0, -1.0])), jnp.ones(2)))).any()
    assert not np.isfinite(np.asarray(spd_solve_rsqrt(jnp.diag(jnp.array([1.0, 0.0])), jnp.ones(2)))).all()


ARM = fd.rigs.two_link_flexible_arm(payload_mass=0.05, n_modes=1)
TORQUE = fd.BangBang([0.3, -0.2], 0.25)  # jumps at 0.25 s and 0.5 s
Y0 = fd.initial_state(ARM, joint_angles=[0.1, -0.2])
T1 = 0.8


@pytest.fixture(scope="module")
def reference():
    import diffrax

    traj = fd.simulate(ARM, Y0, jnp.array([0.0, T1]), TORQUE, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-14)
    return np.asarray(traj.y[-1])


@pytest.mark.parametrize("solve", ["unrolled", pytest.param("cho", marks=pytest.mark.slow)])  # CI time
def test_rk4_final_fourth_order_across_jumps(reference, solve):
    # dt = 1/400 and 1/800 s: 0.25 s and 0.5 s are step boundaries, and so is T1.
    errors = []
    for dt in (1 / 400, 1 / 800):
        y = jax.jit(lambda y0, dt=dt: fixed_step.rk4_final(ARM, y0, 0.0, T1, TORQUE, dt=dt, solve=solve))(Y0)
        errors.append(np.max(np.abs(np.asarray(y) - reference)))
    assert errors[1] < 1e-7
    assert 12.0 < errors[0] / errors[1] < 20.0, errors  # 2^4 = 16 for a fourth-order method


def test_rk4_final_steps_not_aligned_with_jumps(reference):
    # dt = 7 ms does not divide 0.25 s: each piece between jumps gets its own equal steps
    # <= dt, so the method stays fourth order (a step straddling a jump would make it first order).
    errs = [
        np.max(np.abs(np.asarray(fixed_step.rk4_final(ARM, Y0, 0.0, T1, TORQUE, dt=dt)) - reference))
        for dt in (7e-3, 3.5e-3)
    ]
    assert 12.0 < errs[0] / errs[1] < 20.0, errs


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_fixed_step_paths_ending_on_a_jump_stay_fourth_order():
    """Review: with the span ending exactly on an input jump (t1 = 0.5 s), `simulate(dt=...)`
    and `rk4_trajectory` read the torque after the jump in the last step's final stage: the
    final rates were off by h dtau / (6 J) (first order; 1.7e-3 rad/s on paper 004's arm at
    1 ms). Oracle: Dopri8 at rtol 1e-12 with 0.5 s an interior output time."""
    import diffrax

    ref = fd.simulate(ARM, Y0, jnp.array([0.0, 0.5, T1]), TORQUE, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-14)
    ref = np.asarray(ref.y[1])
    paths = {
        "simulate": lambda dt: fd.simulate(ARM, Y0, jnp.array([0.0, 0.5]), TORQUE, dt=dt).y[-1],
        "rk4_trajectory": lambda dt: fd.rk4_trajectory(ARM, Y0, np.array([0.0, 0.5]), TORQUE, dt=dt).y[-1],
        "rk4_final": lambda dt: fixed_step.rk4_final(ARM, Y0, 0.0, 0.5, TORQUE, dt=dt),
    }
    for name, run in paths.items():
        errs = [np.max(np.abs(np.asarray(run(dt)) - ref)) for dt in (1 / 400, 1 / 800)]
        assert errs[1] < 1e-7 and 12.0 < errs[0] / errs[1] < 20.0, (name, errs)


def test_rk4_final_conserves_energy_undamped():
    chain = fd.rigs.flexible_pendulum(n_modes=2, joint_damping=0.0, damping_ratio=0.0)
    y0 = fd.initial_state(chain, [-0.5], [1.0], modal=[1e-4, 0.0])
    y1 = fixed_step.rk4_final(chain, y0, 0.0, 1.0, fd.ZeroTorque(1), dt=2e-5)
    n = chain.n_dof
    e0 = fd.total_energy(fd.assemble(chain), y0[:n], y0[n:])
    e1 = fd.total_energy(fd.assemble(chain), y1[:n], y1[n:])
    assert abs(float(e1 - e0)) < 1e-8 * abs(float(e0))


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_rk4_final_vmaps_over_payloads():
    import equinox as eqx

    masses = jnp.array([0.0, 0.05, 0.1])

    def final(m):
        arm = eqx.tree_at(lambda c: c.payload.mass, ARM, m)
        return fixed_step.rk4_final(arm, Y0, 0.0, 0.3, TORQUE, dt=1e-3)

    batched = jax.jit(jax.vmap(final))(masses)
    single = jax.jit(final)  # one program for the three (an eager call compiles each time)
    for i, m in enumerate(masses):
        np.testing.assert_allclose(batched[i], single(m), rtol=1e-12, atol=1e-14)


def test_rk4_final_errors():
    with pytest.raises(ValueError, match="dt expected a step > 0"):
        fixed_step.rk4_final(ARM, Y0, 0.0, 1.0, TORQUE, dt=0.0)
    with pytest.raises(ValueError, match="expected t1 > t0"):
        fixed_step.rk4_final(ARM, Y0, 1.0, 0.5, TORQUE, dt=1e-3)
    with pytest.raises(ValueError, match=r"y0 expected shape \(8,\)"):
        fixed_step.rk4_final(ARM, Y0[:4], 0.0, 1.0, TORQUE, dt=1e-3)
    with pytest.raises(ValueError, match="jump_times\\(\\) must be concrete"):
        jax.jit(lambda w: fixed_step.rk4_final(ARM, Y0, 0.0, 1.0, fd.BangBang([0.1, 0.1], w), dt=1e-3))(0.25)
    with pytest.raises(ValueError, match="solve expected one of"):
        fixed_step.rk4_final(ARM, Y0, 0.0, 1.0, TORQUE, dt=1e-3, solve="lu")
    # An unstable step (far above the flexural modes' limit) is an error, not NaNs.
    with pytest.raises(Exception, match="rk4_final: the fixed step dt = 0.4 s is above RK4's stability limit"):
        jax.block_until_ready(fixed_step.rk4_final(ARM, Y0, 0.0, 40.0, TORQUE, dt=0.4))


# --- rk4_trajectory and its discrete adjoint -------------------------------------------

TS_1KHZ = np.linspace(0.0, 0.6, 601)  # jumps at 0.25 s and 0.5 s lie on the grid


def test_rk4_trajectory_matches_diffrax_rk4_on_a_log_grid():
    # Same steps as simulate(dt=1 ms) with its jump clipping: the states agree to round-off.
    ours = jax.jit(lambda y0: fixed_step.rk4_trajectory(ARM, y0, TS_1KHZ, TORQUE, dt=1e-3))(Y0)
    peer = fd.simulate(ARM, Y0, jnp.asarray(TS_1KHZ), TORQUE, dt=1e-3)
    assert int(ours.num_steps) == 600 and ours.names == peer.names
    np.testing.assert_allclose(ours.ts, TS_1KHZ)
    np.testing.assert_allclose(ours.Q, peer.Q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ours.Qd, peer.Qd, rtol=0, atol=1e-10)


def test_rk4_trajectory_off_grid_outputs_are_fourth_order(reference):
    # Output times that are not multiples of dt (and dt that does not divide the jumps):
    # every output time and jump is a step boundary, so the error falls 16x per halving.
    ts = np.array([0.0, 0.0137, 0.25, 0.31, T1])
    errs = [
        np.max(np.abs(np.asarray(fixed_step.rk4_trajectory(ARM, Y0, ts, TORQUE, dt=dt).y[-1]) - reference))
        for dt in (7e-3, 3.5e-3)
    ]
    assert 12.0 < errs[0] / errs[1] < 20.0, errs


# The adjoint's own tests use a one-link flexible pendulum with every kind of force the
# Lagrange residual carries (`tests/adjoint_cases.py`). The finite-difference test runs on
# the two-link arm across input jumps.


def _pendulum_loss(values, y0, torque, adjoint):
    chain = fd.with_parameters(PENDULUM, dict(zip(PENDULUM_PARAMS, values)))
    traj = fixed_step.rk4_trajectory(chain, y0, TS_1KHZ[:301], torque, dt=1e-3, adjoint=adjoint)
    return jnp.sum(traj.Q**2) + jnp.sum(traj.Qd[-1] ** 2)


@pytest.mark.slow  # 58 s in a 2-worker run; the adjoint against central differences of the loss stays in CI (below)
def test_discrete_adjoint_equals_reverse_and_forward_mode_through_the_steps():
    # The rule's gradient (parameters, y0 and the input's array fields) against JAX's own
    # reverse mode through the same lax.scan (adjoint="autodiff"), and against JAX's forward
    # mode along a direction: three derivations of the same discrete gradient.
    x = jnp.asarray([float(fd.get_parameter(PENDULUM, n)) for n in PENDULUM_PARAMS]) * 1.1
    torque = fd.SampledTorque(jnp.linspace(0.0, 0.3, 7), 0.02 * jnp.cos(jnp.arange(7.0)))
    grad = jax.jit(jax.grad(_pendulum_loss, argnums=(0, 1, 2)), static_argnums=3)
    ours, peer = grad(x, PENDULUM_Y0, torque, "discrete"), grad(x, PENDULUM_Y0, torque, "autodiff")
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(peer)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(b))))
    assert float(jnp.max(jnp.abs(ours[2].values))) > 0  # the input's samples do get a gradient
    direction = x * jnp.asarray([1.0, -0.5, 2.0, 0.3])
    _, tangent = jax.jit(
        lambda v: jax.jvp(lambda u: _pendulum_loss(u, PENDULUM_Y0, torque, "autodiff"), (v,), (direction,))
    )(x)
    np.testing.assert_allclose(tangent, ours[0] @ direction, rtol=1e-9)
    # A custom_vjp has no forward mode: adjoint="discrete" says so.
    with pytest.raises(TypeError, match="custom_vjp"):
        jax.jvp(lambda u: _pendulum_loss(u, PENDULUM_Y0, torque, "discrete"), (x,), (direction,))


ARM_PARAMS = ("link1.EI", "link2.rho", "hub1.inertia", "payload.mass")


def test_discrete_adjoint_matches_finite_differences_across_input_jumps():
    # The two-link arm, the bang-bang input (jumps at 0.25 s, inside the 0.3 s log) closed
    # over: its jump times lay out the steps at trace time.
    def loss(values):
        arm = fd.with_parameters(ARM, dict(zip(ARM_PARAMS, values)))
        traj = fixed_step.rk4_trajectory(arm, Y0, TS_1KHZ[:301], TORQUE, dt=1e-3)
        return jnp.sum(traj.Q**2) + jnp.sum(traj.Qd[-1] ** 2)

    x = jnp.asarray([float(fd.get_parameter(ARM, n)) for n in ARM_PARAMS]) * 1.1
    g = jax.jit(jax.grad(loss))(x)
    loss = jax.jit(loss)
    for i in range(len(ARM_PARAMS)):
        h = 1e-5 * float(x[i])
        e = jnp.zeros_like(x).at[i].set(h)
        fd_i = (float(loss(x + e)) - float(loss(x - e))) / (2 * h)
        assert abs(float(g[i]) - fd_i) <= 1e-6 * abs(fd_i) + 1e-9, (ARM_PARAMS[i], float(g[i]), fd_i)


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_discrete_adjoint_under_vmap_with_state_feedback():
    # A PD controller tracking a quintic move: the torque depends on the state, so each
    # stage's transpose carries the controller's own derivative into the state's cotangent.
    # The vmapped rule against JAX's reverse mode through the scan, entry by entry.
    torque = pd_tracking()
    x = jnp.asarray([float(fd.get_parameter(PENDULUM, n)) for n in PENDULUM_PARAMS])
    xs = jnp.stack([x, x * jnp.asarray([1.3, 0.8, 2.0, 1.0])])
    batched = jax.jit(jax.vmap(lambda v: jax.grad(_pendulum_loss)(v, PENDULUM_Y0, torque, "discrete")))(xs)
    peer = jax.jit(jax.grad(_pendulum_loss), static_argnums=3)
    for i in range(2):
        np.testing.assert_allclose(batched[i], peer(xs[i], PENDULUM_Y0, torque, "autodiff"), rtol=1e-9)


def test_rk4_trajectory_errors():
    with pytest.raises(ValueError, match="dt expected a step > 0"):
        fixed_step.rk4_trajectory(ARM, Y0, TS_1KHZ, TORQUE, dt=-1e-3)
    with pytest.raises(ValueError, match="adjoint expected 'discrete' or 'autodiff'"):
        fixed_step.rk4_trajectory(ARM, Y0, TS_1KHZ, TORQUE, dt=1e-3, adjoint="backsolve")
    with pytest.raises(ValueError, match=r"ts\[2\] = 0.1 after ts\[1\] = 0.2"):
        fixed_step.rk4_trajectory(ARM, Y0, [0.0, 0.2, 0.1], TORQUE, dt=1e-3)
    with pytest.raises(ValueError, match="at least 2 times"):
        fixed_step.rk4_trajectory(ARM, Y0, [0.0], TORQUE, dt=1e-3)
    with pytest.raises(ValueError, match="ts must be concrete"):
        jax.jit(lambda ts: fixed_step.rk4_trajectory(ARM, Y0, ts, TORQUE, dt=1e-3))(jnp.asarray(TS_1KHZ))
    with pytest.raises(ValueError, match=r"y0 expected shape \(8,\)"):
        fixed_step.rk4_trajectory(ARM, Y0[:4], TS_1KHZ, TORQUE, dt=1e-3)
    with pytest.raises(Exception, match=r"rk4_trajectory: the fixed step dt = 0.4 s is above RK4's stability limit"):
        jax.block_until_ready(fixed_step.rk4_trajectory(ARM, Y0, [0.0, 40.0], TORQUE, dt=0.4).Q)

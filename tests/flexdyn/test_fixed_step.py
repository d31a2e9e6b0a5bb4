"""Tests of `flexdyn.fixed_step` (lean RK4 for batched sweeps) and `flexdyn.smallsolve`.

Oracles: NumPy's LU solve for the unrolled Cholesky; a Dopri8 solution at rtol 1e-12 and
the fourth-order convergence law (halving dt divides the error by 16) for the
integrator, across a bang-bang switch; conservation of energy for an undamped chain.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
from flexdyn import fixed_step
from flexdyn.smallsolve import UNROLL_MAX_DOF, spd_solve


@pytest.mark.parametrize("n", [1, 2, 5, 8, UNROLL_MAX_DOF, UNROLL_MAX_DOF + 3])
def test_spd_solve_matches_lu(n):
    rng = np.random.default_rng(n)
    A = rng.normal(size=(n, n))
    M = A @ A.T + n * np.eye(n) * 10.0 ** rng.uniform(-3, 1)  # SPD, condition numbers up to ~1e4
    b = rng.normal(size=n)
    x = np.asarray(jax.jit(spd_solve)(jnp.asarray(M), jnp.asarray(b)))
    np.testing.assert_allclose(x, np.linalg.solve(M, b), rtol=1e-10, atol=1e-12)


def test_spd_solve_vmapped_and_not_positive_definite():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(16, 4, 4))
    Ms = A @ A.transpose(0, 2, 1) + np.eye(4)
    bs = rng.normal(size=(16, 4))
    x = np.asarray(jax.jit(jax.vmap(spd_solve))(jnp.asarray(Ms), jnp.asarray(bs)))
    np.testing.assert_allclose(x, np.linalg.solve(Ms, bs[..., None])[..., 0], rtol=1e-10)
    # An indefinite matrix yields NaN (as cho_factor does), for the caller's finiteness check.
    assert np.isnan(np.asarray(spd_solve(jnp.diag(jnp.array([1.0, -1.0])), jnp.ones(2)))).any()


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


def test_rk4_final_conserves_energy_undamped():
    chain = fd.rigs.flexible_pendulum(n_modes=2, joint_damping=0.0, damping_ratio=0.0)
    y0 = fd.initial_state(chain, [-0.5], [1.0], modal=[1e-4, 0.0])
    y1 = fixed_step.rk4_final(chain, y0, 0.0, 1.0, fd.ZeroTorque(1), dt=2e-5)
    n = chain.n_dof
    e0 = fd.total_energy(fd.assemble(chain), y0[:n], y0[n:])
    e1 = fd.total_energy(fd.assemble(chain), y1[:n], y1[n:])
    assert abs(float(e1 - e0)) < 1e-8 * abs(float(e0))


def test_rk4_final_vmaps_over_payloads():
    import equinox as eqx

    masses = jnp.array([0.0, 0.05, 0.1])

    def final(m):
        arm = eqx.tree_at(lambda c: c.payload.mass, ARM, m)
        return fixed_step.rk4_final(arm, Y0, 0.0, 0.3, TORQUE, dt=1e-3)

    batched = jax.jit(jax.vmap(final))(masses)
    for i, m in enumerate(masses):
        np.testing.assert_allclose(batched[i], final(m), rtol=1e-12, atol=1e-14)


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
    with pytest.raises(Exception, match="non-finite"):
        jax.block_until_ready(fixed_step.rk4_final(ARM, Y0, 0.0, 40.0, TORQUE, dt=0.4))

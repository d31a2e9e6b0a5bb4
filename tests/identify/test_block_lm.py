"""The block-by-block Levenberg-Marquardt step (`identify.block_lm`).

Oracles: NumPy's dense least-squares solution of `[J; sqrt(lambda) I] d = [r; 0]` for the
damped step, and optimistix's own `LevenbergMarquardt` (dense QR) for the iterates of a
whole solve.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import identify._fit.jacobian as jacobian_module
import identify._fit.levenberg_marquardt as levenberg_marquardt_module
import identify._model.parameters as parameters_module
from identify._fit.block_lm import BlockLevenbergMarquardt, Layout, damped_block_solve
from identify._model.variables import Variables


def _dense(r, S, U, used):
    L, n, P = S.shape
    cols = [S.reshape(L * n, P)]
    for l, j in zip(*np.nonzero(used)):
        c = np.zeros((L, n))
        c[l] = U[l, :, j]
        cols.append(c.reshape(-1, 1))
    return np.hstack(cols)


@pytest.mark.parametrize(("P", "k"), [(3, 3), (0, 2), (4, 0)])
@pytest.mark.parametrize("lam", [1e-6, 0.37, 1e3])
def test_damped_step_is_the_dense_least_squares_solution(P, k, lam):
    rng = np.random.default_rng(P + 10 * k)
    L, n = 4, 30
    used = np.ones((L, k), bool)
    if k:
        used[1, k - 1] = False  # a log with fewer nuisances
        used[3, :] = False  # a log with none
    S = rng.standard_normal((L, n, P))
    U = rng.standard_normal((L, n, k)) * used[:, None, :]  # padding slots have zero columns
    r = rng.standard_normal((L, n))
    ds, du = damped_block_solve(jnp.asarray(r), jnp.asarray(S), jnp.asarray(U), used, lam)
    J = _dense(r, S, U, used)
    A = np.vstack([J, np.sqrt(lam) * np.eye(J.shape[1])])
    d = np.linalg.lstsq(A, np.concatenate([r.reshape(-1), np.zeros(J.shape[1])]), rcond=None)[0]
    scale = np.max(np.abs(d))
    np.testing.assert_allclose(ds, d[:P], atol=1e-12 * scale)
    np.testing.assert_allclose(np.asarray(du)[used], d[P:], atol=1e-12 * scale)
    assert not np.any(np.asarray(du)[~used])


@pytest.mark.slow  # 132 s in a 2-worker run (10 programs compiled); the block step stays in CI (the 9 cases above)
def test_block_levenberg_marquardt_takes_optimistix_steps(multilog_problem):
    """The whole solve, on three logs with different nuisance layouts, against optimistix's
    `LevenbergMarquardt` (its loop and trust region; only the linear solve differs): the
    same iterates step by step, and the same optimum. (Not necessarily the same number of
    steps: near the optimum a trial's actual cost reduction is round-off, ~1e-12 of the
    cost, and the trust region's accept/reject decision there goes either way.)"""
    p, x, y0, off = multilog_problem
    z0 = Variables(offset=off, phys=jnp.asarray(parameters_module.z_from_x(p, np.asarray(x))), y0=y0)
    args = (p, p.sigma, None, 2e-3)
    fn = levenberg_marquardt_module._residual_fn_lm
    block_lm = BlockLevenbergMarquardt(1e-4, 1e-10, Layout.of(p), norm=optx.rms_norm)
    dense_lm = optx.LevenbergMarquardt(1e-4, 1e-10, norm=optx.rms_norm)
    for steps in (1, 2, 3, 4):
        block = optx.least_squares(fn, block_lm, z0, args=args, max_steps=steps, throw=False)
        dense = optx.least_squares(fn, dense_lm, z0, args=args, max_steps=steps, throw=False)
        for key in z0:
            np.testing.assert_allclose(block.value[key], dense.value[key], rtol=1e-9, atol=1e-13)
    block = optx.least_squares(fn, block_lm, z0, args=args, max_steps=60)
    dense = optx.least_squares(fn, dense_lm, z0, args=args, max_steps=60)
    for key in z0:
        np.testing.assert_allclose(block.value[key], dense.value[key], rtol=1e-8, atol=1e-12)


def test_fit_uses_the_block_solve_from_many_logs(multilog_problem):
    p = multilog_problem[0]
    assert isinstance(levenberg_marquardt_module._levenberg_marquardt(p, 1e-3, 1e-10), optx.LevenbergMarquardt)
    L = levenberg_marquardt_module.BLOCK_SOLVE_MIN_LOGS
    wide = dataclasses.replace(p, t=jnp.tile(p.t[:1], (L, 1)), y0_free=tuple((l, 0) for l in range(L)), offset_free=())
    assert isinstance(levenberg_marquardt_module._levenberg_marquardt(wide, 1e-3, 1e-10), BlockLevenbergMarquardt)
    # no nuisances: nothing to eliminate, the dense solve
    bare = dataclasses.replace(wide, y0_free=())
    assert isinstance(levenberg_marquardt_module._levenberg_marquardt(bare, 1e-3, 1e-10), optx.LevenbergMarquardt)


@pytest.mark.slow  # 43 s in CI; the block step stays in CI (the damped-step cases and the choice test above)
def test_a_fit_of_many_logs_recovers_the_truth():
    """`identify.fit` of `BLOCK_SOLVE_MIN_LOGS` pendulum releases (each with its own unknown
    release angle and potentiometer offset: the block solve) brackets the true damping and
    payload with its 95 % intervals and recovers each log's release angle and offset."""
    import flexdyn as fd
    import identify

    L = levenberg_marquardt_module.BLOCK_SOLVE_MIN_LOGS
    truth = fd.rigs.rigid_pendulum(joint_damping=2.5e-3, payload_mass=0.025)
    t = np.arange(301) / 100.0
    rng = np.random.default_rng(7)
    angles = rng.uniform(0.3, 1.2, L)
    offsets = rng.uniform(-0.01, 0.01, L)
    logs = []
    for l in range(L):
        log = identify.simulate_log(
            truth,
            t,
            initial={"theta1": angles[l]},
            channels=("theta1",),
            noise={"theta1": 2e-3},
            rng=rng,
            true_offsets={"theta1": offsets[l]},
            fit_initial=("theta1",),
            offsets=("theta1",),
            name=f"release_{l}",
        )
        logs.append(dataclasses.replace(log, initial={"theta1": 0.5}))  # the guess of the angle
    params = [
        identify.Parameter("joint1.damping", 1e-3, 1e-6, 1e-1),
        identify.Parameter("payload.mass", 0.04, 1e-3, 1.0),
    ]
    chain = fd.rigs.rigid_pendulum()
    problem = identify.make_problem(chain, params, logs, {"theta1": 2e-3})
    assert isinstance(levenberg_marquardt_module._levenberg_marquardt(problem, 1e-3, 1e-10), BlockLevenbergMarquardt)
    res = identify.fit(problem, params)
    assert res.converged, res.summary()
    for name, value in (("joint1.damping", 2.5e-3), ("payload.mass", 0.025)):
        i = res.names.index(name)
        assert res.ci_low[i] <= value <= res.ci_high[i], (name, res.summary())
    for l in range(L):
        angle, se = res.initial_states[f"release_{l}"]["theta1"]
        assert abs(angle - angles[l]) < 4 * se, (l, angle, angles[l], se)
        offset, se = res.offsets[f"release_{l}"]["theta1"]
        assert abs(offset - offsets[l]) < 4 * se, (l, offset, offsets[l], se)
    # its standard errors came block by block (identify.covariance.blocked); the dense
    # Jacobian's SVD at the same optimum gives the same ones
    x = parameters_module.x_from_z(problem, res.z.phys)
    sigma = jnp.asarray([res.sigma[c] for c in problem.channels])
    r, J, ok = jacobian_module._jacobian_natural(problem, x, res.z.y0, res.z.offset, sigma, res.step)
    dense = jacobian_module._dense_covariance(problem, r, J)
    assert bool(ok)
    np.testing.assert_allclose(res.std_errors, res.values * dense.std_errors[:2], rtol=1e-8)
    for l in range(L):
        assert res.initial_states[f"release_{l}"]["theta1"][1] == pytest.approx(dense.std_errors[2 + l], rel=1e-8)
        assert res.offsets[f"release_{l}"]["theta1"][1] == pytest.approx(dense.std_errors[2 + L + l], rel=1e-8)
    np.testing.assert_allclose(res.correlation, dense.correlation, rtol=1e-8, atol=1e-12)
    assert res.cost == pytest.approx(dense.rss, rel=1e-12)

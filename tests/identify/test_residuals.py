"""The residuals' block-arrow Jacobian (`identify.residuals`).

The oracle is `jax.jacfwd` of the plain residual function (every column's tangent through
every log's solve, the definition of the Jacobian the fit needs), and, for the offsets'
columns, the closed form `dr/do = 1/sigma` on the samples that count. The logs differ in
length and in which nuisances they estimate (including none), so the per-log slots, their
padding and the columns' order are all exercised.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import identify._fit.levenberg_marquardt as levenberg_marquardt_module
import identify._model.parameters as parameters_module
from identify._model.residuals import log_blocked, log_jacobian, residuals
from identify._model.variables import Variables


def _theta_of(p):
    return lambda x: parameters_module.theta_from_x(p, x)


def _jacfwd(p, x, y0, off, horizon):
    def fn(v):
        return residuals(p, _theta_of(p)(v["x"]), v["y0"], v["off"], p.sigma, horizon, 2e-3)[0]

    v = {"x": x, "y0": y0, "off": off}
    J = jax.jacfwd(fn)(v)
    return fn(v), np.concatenate([J["x"], J["y0"], J["off"]], axis=1)


@pytest.mark.parametrize("horizon", [None, pytest.param(0.3, marks=pytest.mark.slow)])  # CI time
def test_log_jacobian_is_the_forward_mode_jacobian(multilog_problem, horizon):
    p, x, y0, off = multilog_problem
    h = None if horizon is None else jnp.asarray(horizon)
    r_ref, J_ref = _jacfwd(p, x, y0, off, h)
    jac = log_jacobian(p, _theta_of(p), x, y0, off, p.sigma, h, 2e-3)
    J = np.asarray(jac.dense(len(p.y0_free), len(p.offset_free)))
    assert J.shape == J_ref.shape == (r_ref.size, 2 + 3 + 3)
    np.testing.assert_array_equal(jac.r.reshape(-1), r_ref)
    np.testing.assert_allclose(J, J_ref, rtol=1e-12, atol=1e-12 * np.abs(J_ref).max())
    assert bool(np.all(jac.ok))
    # the offsets' columns in closed form: 1/sigma_c on the log's used samples of channel c
    used = np.asarray(p.valid[:, :, None] & p.present[:, None, :])
    if h is not None:
        used = used & (np.asarray(p.t) <= np.asarray(p.t[:, :1]) + horizon)[:, :, None]
    for k, (l, c) in enumerate(p.offset_free):
        expected = np.zeros(used.shape)
        expected[l, :, c] = np.where(used[l, :, c], 1.0 / float(p.sigma[c]), 0.0)
        np.testing.assert_allclose(J[:, 5 + k], expected.reshape(-1), rtol=1e-15)
    # the block structure itself: a log's residuals do not depend on another log's nuisances
    rows = np.arange(r_ref.size) // (used.shape[1] * used.shape[2])
    for k, (l, _) in enumerate(p.y0_free):
        assert not np.any(J[rows != l, 2 + k])


def test_log_blocked_linearises_to_the_jacobian(multilog_problem):
    """What optimistix's Levenberg-Marquardt sees (`jax.linearize` of the wrapped residuals)
    is the forward-mode Jacobian, column by column; differentiating the arguments is an
    error, not a wrong answer."""
    p, x, y0, off = multilog_problem
    z = Variables(offset=off, phys=jnp.asarray(parameters_module.z_from_x(p, np.asarray(x))), y0=y0)
    args = (p, p.sigma, None, 2e-3)
    fn = log_blocked(levenberg_marquardt_module._unpack)
    plain = levenberg_marquardt_module._residual_fn
    np.testing.assert_array_equal(fn(z, args), plain(z, args))
    r, lin = jax.linearize(lambda z_: fn(z_, args), z)
    J_ref = jax.jacfwd(lambda z_: plain(z_, args))(z)
    flat_ref = np.concatenate([J_ref.phys, J_ref.y0, J_ref.offset], axis=1)
    sizes = {"phys": 2, "y0": 3, "offset": 3}
    col = 0
    for key, n in sizes.items():
        for i in range(n):
            tangent = Variables(**{k: jnp.zeros(m) for k, m in sizes.items()})
            tangent = dataclasses.replace(tangent, **{key: getattr(tangent, key).at[i].set(1.0)})
            np.testing.assert_allclose(lin(tangent), flat_ref[:, col], rtol=1e-12, atol=1e-12 * np.abs(flat_ref).max())
            col += 1
    with pytest.raises(NotImplementedError, match="only the first argument"):
        jax.jvp(lambda s: fn(z, (p, s, None, 2e-3)), (p.sigma,), (jnp.ones_like(p.sigma),))


def test_levenberg_marquardt_takes_the_same_steps(multilog_problem):
    """Levenberg-Marquardt through the block rule takes the iterates of the plain residual
    function (whose linear map JAX builds itself) and reaches the same optimum."""
    p, x, y0, off = multilog_problem
    z0 = Variables(offset=off, phys=jnp.asarray(parameters_module.z_from_x(p, np.asarray(x))), y0=y0)
    args = (p, p.sigma, None, 2e-3)
    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10)
    blocked = optx.least_squares(log_blocked(levenberg_marquardt_module._unpack), solver, z0, args=args, max_steps=60)
    plain = optx.least_squares(levenberg_marquardt_module._residual_fn, solver, z0, args=args, max_steps=60)
    assert int(blocked.stats["num_steps"]) == int(plain.stats["num_steps"])
    for k in ("offset", "phys", "y0"):
        np.testing.assert_allclose(getattr(blocked.value, k), getattr(plain.value, k), rtol=1e-8, atol=1e-12)
    theta = parameters_module.theta_from_x(p, parameters_module.x_from_z(p, blocked.value.phys))
    np.testing.assert_allclose(theta[0], 3e-3, rtol=0.05)  # the data's own damping


def test_nuisances_only(multilog_problem):
    """With no shared variables (held-out logs: the physical parameters fixed, only each
    log's own initial state and offsets fitted) the Jacobian is the nuisances' columns."""
    p, x, y0, off = multilog_problem
    theta = parameters_module.theta_from_x(p, x)
    r_ref, J_ref = _jacfwd(p, x, y0, off, None)
    jac = log_jacobian(p, lambda shared: theta, {}, y0, off, p.sigma, None, 2e-3)
    J = np.asarray(jac.dense(len(p.y0_free), len(p.offset_free)))
    assert J.shape == (r_ref.size, 6) and J.dtype == np.float64
    np.testing.assert_allclose(J, J_ref[:, 2:], rtol=1e-12, atol=1e-12 * np.abs(J_ref).max())
    fn = log_blocked(lambda args: (p, lambda shared: theta, p.sigma, None, 2e-3))
    v = Variables(offset=off, phys=jnp.zeros(0), y0=y0)  # nothing shared
    _, lin = jax.linearize(lambda v_: fn(v_, None), v)
    tangent = Variables(offset=jnp.array([0.0, 1.0, 0.0]), phys=jnp.zeros(0), y0=jnp.zeros(3))
    np.testing.assert_allclose(lin(tangent), J_ref[:, 6], rtol=1e-15)


@pytest.mark.parametrize(
    "theta, y0",
    [
        ([np.inf, 0.03], [0.41, 0.05, -0.02]),  # a log-scale parameter's exp overflowed
        ([np.nan, 0.03], [0.41, 0.05, -0.02]),  # a NaN from a singular step
        ([2e-3, 0.03], [np.nan, 0.05, -0.02]),  # a NaN initial state
    ],
)
def test_a_trial_point_the_model_refuses_is_a_failed_solve_not_an_error(multilog_problem, theta, y0):
    """The spinning-link diagnosis dropped its joint-elasticity candidate: a Levenberg-
    Marquardt trial point overflowed the (unbounded, log-scale) joint stiffness, and the
    model's parameter check stopped the whole fit ("joint1.stiffness must be finite and >
    0"). Such a point must be what a failed solve is: `FAILED_RESIDUAL` on every used
    sample, so the step is rejected; the other logs' residuals and a good point unchanged."""
    from identify._model.residuals import FAILED_RESIDUAL

    p, x, y0_good, off = multilog_problem
    r, ok = jax.jit(lambda th, y: residuals(p, th, y, off, p.sigma, None, 2e-3))(
        jnp.asarray(theta, dtype=float), jnp.asarray(y0, dtype=float)
    )
    r, ok = np.asarray(r).reshape(p.measured.shape), np.asarray(ok)
    used = np.asarray(p.valid[:, :, None] & p.present[:, None, :])
    bad_theta = not np.all(np.isfinite(theta))
    # a bad parameter fails every log; a bad initial state (log 0's) only its own log
    failed = np.array([True, True, True]) if bad_theta else np.array([True, False, False])
    np.testing.assert_array_equal(ok, ~failed)
    for l in range(3):
        if failed[l]:
            assert np.all(r[l][used[l]] == FAILED_RESIDUAL)
        else:
            assert np.all(np.abs(r[l][used[l]]) < FAILED_RESIDUAL)


@pytest.mark.parametrize("x_far", [-800.0, 800.0])
def test_an_unbounded_log_scale_parameter_far_out_is_a_bad_point_not_an_error(x_far):
    """Review (diagnose on a pendulum): a new elastic joint's unbounded rotor inertia, a
    log-scale parameter, reached exp(-800) = 0 at a Levenberg-Marquardt trial point and
    the model's check ("must be finite and > 0") stopped the fit. Its natural coordinate
    is clipped (`identify.fit.exp_natural`): the point gives finite residuals or the
    failed-solve ones, and the value inside the clip is exp's."""
    import flexdyn as fd
    import identify

    chain = fd.rigs.rigid_pendulum()
    t = np.arange(80) * 5e-3
    log = identify.simulate_log(chain, t, initial={"theta1": 0.4}, channels=("theta1",))
    params = [identify.Parameter("hub1.inertia", 2e-5), identify.Parameter("payload.mass", 0.03, 1e-3, 1.0)]
    p = identify.make_problem(chain, params, [log], {"theta1": 1e-3})
    assert p.log_scale[0] and not np.isfinite(np.asarray(p.lower[0]))  # unbounded, log scale
    theta = parameters_module.theta_from_x(p, jnp.asarray([x_far, np.log(0.03)]))
    assert 0 < float(theta[0]) < np.inf
    r, ok = residuals(p, theta, jnp.zeros(0), jnp.zeros(0), p.sigma, None, 2e-3)
    assert np.all(np.isfinite(np.asarray(r)))
    np.testing.assert_allclose(parameters_module.exp_natural(jnp.asarray(3.0)), np.exp(3.0), rtol=1e-15)


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_a_per_log_parameter_reaches_its_own_log_only():
    """A per-log parameter (`Parameter.per_log`): log l simulates with its own value. The
    residuals equal those of the same logs with each log's value given as a known one
    (`LogData.set`, another path into the model), and the block-arrow Jacobian equals
    `jax.jacfwd` of the residuals, whose per-log columns vanish on the other logs' rows."""
    import dataclasses

    import flexdyn as fd
    import identify

    truth = fd.rigs.rigid_pendulum(joint_damping=3e-3)
    logs = []
    for l in range(3):
        t = np.arange(60 + 20 * l) * 5e-3
        logs.append(
            identify.simulate_log(
                truth, t, initial={"theta1": 0.4 + 0.1 * l}, torque=0.01 * np.sin(3 * t)[:, None],
                channels=("theta1",), noise={"theta1": 1e-3}, rng=np.random.default_rng(l),
                fit_initial=("theta1",) if l != 1 else (), name=f"drop{l}",
            )
        )  # fmt: skip
    params = [
        identify.Parameter("joint1.damping", 2e-3, 1e-6, 1.0),
        identify.Parameter("payload.mass", 0.03, 1e-3, 1.0, per_log=True),
    ]
    p = identify.make_problem(truth, params, logs, {"theta1": 1e-3})
    assert p.names == ("joint1.damping", "payload.mass[drop0]", "payload.mass[drop1]", "payload.mass[drop2]")
    assert p.per_log == (("payload.mass", (1, 2, 3)),)
    masses = [0.02, 0.05, 0.11]
    theta = jnp.asarray([2.5e-3, *masses])
    x = jnp.asarray(parameters_module.x_from_theta(p, np.asarray(theta)))
    y0 = jnp.asarray([0.41, 0.52])
    off = jnp.zeros(0)

    known = [dataclasses.replace(log, set={"payload.mass": m}) for log, m in zip(logs, masses)]
    q = identify.make_problem(truth, params[:1], known, {"theta1": 1e-3})
    r_known = residuals(q, theta[:1], y0, off, q.sigma, None, 2e-3)[0]
    r_own, J_ref = _jacfwd(p, x, y0, off, None)
    # (the per-log masses pass through log and exp: round-off, 1e-11 noise levels)
    np.testing.assert_allclose(r_own, r_known, rtol=1e-12, atol=1e-11)

    jac = log_jacobian(p, _theta_of(p), x, y0, off, p.sigma, None, 2e-3)
    J = np.asarray(jac.dense(len(p.y0_free), 0))
    np.testing.assert_allclose(J, J_ref, rtol=1e-12, atol=1e-12 * np.abs(J_ref).max())
    rows = np.arange(J.shape[0]) // (p.t.shape[1] * len(p.channels))
    for l in range(3):
        assert not np.any(J[rows != l, 1 + l])
        assert np.any(J[rows == l, 1 + l])


def _free_rotor_logs(hold: str):
    """A rigid link in the horizontal plane (a free rotor, `J theta'' = tau`) driven by a
    controller's commands: random torque samples at 100 Hz, each held until the next (or
    read linearly). Oracle, the held input's exact recursion over each sample interval `h`:
    `theta += omega h + tau h^2 / (2 J)`, `omega += tau h / J`."""
    import flexdyn as fd
    from identify._model.problem import LogData

    length, mass, hub = 0.5, 0.2, 0.02
    chain = fd.Chain([fd.RigidLink(length, mass)], joints=[fd.RigidJoint(damping=0.0)], hubs=[fd.Hub(inertia=hub)])
    J = hub + mass * length**2 / 3
    t = np.arange(0.0, 1.0, 0.01)
    tau = np.random.default_rng(3).uniform(-0.05, 0.05, t.size)
    theta, omega = np.zeros(t.size), 0.0
    for k in range(t.size - 1):
        h = t[k + 1] - t[k]
        theta[k + 1] = theta[k] + omega * h + tau[k] * h**2 / (2 * J)
        omega += tau[k] * h / J
    log = LogData(t=t, outputs={"theta1": theta}, torque=tau[:, None], name="steps", hold=hold)
    return chain, log, theta


@pytest.mark.parametrize("hold", ["zoh", ("zoh",)])
def test_a_held_torque_is_simulated_held(hold):
    """`LogData.hold = "zoh"`: the simulation holds each torque sample until the next, as
    the closed form does; read linearly (the default), the same samples lead the held input
    by half a sample and the angle is off by thousands of times more."""
    from identify._model.parameters import Parameter
    from identify._model.problem import make_problem
    from identify._model.residuals import predict

    chain, log, theta = _free_rotor_logs(hold)
    for reading, rel in (("zoh", 1e-8), ("linear", None)):
        problem = make_problem(
            chain,
            [Parameter("hub1.inertia", 0.02)],
            [dataclasses.replace(log, hold=hold if reading == "zoh" else "linear")],
        )
        assert problem.hold == reading
        out, ok = predict(problem, jnp.asarray([0.02]), problem.y0_known)
        assert bool(ok[0])
        error = np.max(np.abs(np.asarray(out)[0, :, 0] - theta))
        if rel is not None:
            assert error < rel * np.max(np.abs(theta)), error
        else:
            assert error > 1e4 * 1e-8 * np.max(np.abs(theta)), error


def test_logs_read_differently_are_refused_in_one_problem():
    from identify._model.parameters import Parameter
    from identify._model.problem import make_problem

    chain, log, _ = _free_rotor_logs("zoh")
    other = dataclasses.replace(log, name="other", hold="linear")
    with pytest.raises(
        ValueError, match=r"read their torque samples differently \('zoh': 'steps'; 'linear': 'other'\)"
    ):
        make_problem(chain, [Parameter("hub1.inertia", 0.02)], [log, other])
    with pytest.raises(ValueError, match=r"log 'steps': hold: SampledTorque.hold: expected 'linear' or 'zoh'"):
        make_problem(chain, [Parameter("hub1.inertia", 0.02)], [dataclasses.replace(log, hold="cubic")])

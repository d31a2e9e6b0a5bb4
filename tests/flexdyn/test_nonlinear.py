"""Dry friction, aerodynamic drag and backlash (flexdyn.nonlinear) against closed forms,
a power identity computed independently, the classical friction decrement, energy
conservation, and the neutral values reproducing the linear model exactly."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
from flexdyn.chain import generalised_forces


def _forces(chain, Q, Qd):
    asm = fd.assemble(chain)
    return np.asarray(generalised_forces(asm, jnp.asarray(Q), jnp.asarray(Qd), jnp.zeros(chain.n_links)))


def test_drag_on_a_rigid_link_turning_about_its_joint_closed_form():
    # f(x) = -c |w x| w x, torque = int f x dx = -c w |w| l^4 / 4
    c, l = 0.37, 0.42
    base = fd.Chain([fd.RigidLink(l, 0.2)])
    chain = fd.Chain([fd.RigidLink(l, 0.2, drag=c)])
    for w in (-3.1, -0.2, 0.7, 5.0):
        extra = _forces(chain, [0.3], [w]) - _forces(base, [0.3], [w])
        assert extra[0] == pytest.approx(-c * w * abs(w) * l**4 / 4, rel=1e-10)


def test_drag_power_on_a_two_link_arm_equals_the_integral_of_c_abs_vn_cubed():
    # The drag force is homogeneous of degree 2 in the rates, so its power is
    # F . Qd = -sum_i c_i int |v_n|^3 dx. v_n is computed here by hand for a two-link
    # rigid arm (link 2's points: v = o2_dot + (w1 + w2) x S e2), independently of flexdyn.
    l1, l2, c1, c2 = 0.5, 0.4, 0.3, 0.2
    chain = fd.Chain([fd.RigidLink(l1, 0.3, drag=c1), fd.RigidLink(l2, 0.2, drag=c2)])
    base = fd.Chain([fd.RigidLink(l1, 0.3), fd.RigidLink(l2, 0.2)])
    rng = np.random.default_rng(3)
    x, w = np.polynomial.legendre.leggauss(200)
    for _ in range(3):
        q = rng.uniform(-2, 2, 2)
        qd = rng.uniform(-3, 3, 2)
        F = _forces(chain, q, qd) - _forces(base, q, qd)
        a1, a2 = q[0], q[0] + q[1]
        w1, w2 = qd[0], qd[0] + qd[1]
        o2_dot = w1 * l1 * np.array([-np.sin(a1), np.cos(a1)])
        n2 = np.array([-np.sin(a2), np.cos(a2)])
        s1 = 0.5 * l1 * (x + 1)
        s2 = 0.5 * l2 * (x + 1)
        vn1 = w1 * s1
        vn2 = o2_dot @ n2 + w2 * s2
        power = -(c1 * 0.5 * l1 * w @ np.abs(vn1) ** 3 + c2 * 0.5 * l2 * w @ np.abs(vn2) ** 3)
        assert F @ qd == pytest.approx(power, rel=1e-6)


def test_coulomb_friction_torque_and_neutral_values():
    chain = fd.Chain([fd.RigidLink(0.3, 0.18)], [fd.RigidJoint(coulomb=0.01, coulomb_velocity=0.02)])
    base = fd.Chain([fd.RigidLink(0.3, 0.18)])
    for rate in (-1.0, -0.01, 0.0, 0.005, 2.0):
        extra = _forces(chain, [0.1], [rate]) - _forces(base, [0.1], [rate])
        assert extra[0] == pytest.approx(-0.01 * math.tanh(rate / 0.02), abs=1e-15)
    # present at zero = absent, exactly
    zero = fd.Chain([fd.RigidLink(0.3, 0.18, drag=0.0)], [fd.RigidJoint(coulomb=0.0)])
    np.testing.assert_array_equal(_forces(zero, [0.1], [0.7]), _forces(base, [0.1], [0.7]))


def test_coulomb_friction_linear_decrement_of_a_pendulum():
    # A pendulum with dry friction only loses 2 F_c / (m g l_c) of amplitude every half
    # period (small swings): the classical straight-line envelope.
    F_c, m, l, g = 2e-3, 0.2, 0.3, 9.81
    chain = fd.Chain([fd.RigidLink(l, m)], [fd.RigidJoint(coulomb=F_c, coulomb_velocity=1e-3)], gravity=(0.0, -g))
    a0 = 0.08
    y0 = fd.initial_state(chain, joint_angles=[-math.pi / 2 + a0])
    ts = jnp.linspace(0.0, 4.0, 8001)
    th = np.asarray(fd.simulate(chain, y0, ts, rtol=1e-10, atol=1e-12).coordinate("theta1")) + math.pi / 2
    k = np.nonzero((np.abs(th[1:-1]) > np.abs(th[:-2])) & (np.abs(th[1:-1]) >= np.abs(th[2:])))[0] + 1
    peaks = np.abs(th[k])[:6]
    drops = -np.diff(peaks)
    expected = 2 * F_c / (m * g * l / 2)
    # small-angle oracle; the sin nonlinearity at 0.08 rad changes it by < 0.2 %
    np.testing.assert_allclose(drops, expected, rtol=0.01)


def _arm(backlash, damping=0.0):
    rig = fd.rigs.flexible_link_joint_arm(structural_damping=damping)
    joints = tuple(
        fd.ElasticJoint(
            j.stiffness, j.rotor_inertia, j.gear_ratio, spong_approximation=j.spong_approximation, backlash=backlash
        )
        for j in rig.joints
    )
    return eqx.tree_at(lambda c: c.joints, rig, joints)


def test_backlash_conserves_energy_and_zero_backlash_is_the_linear_spring():
    ts = jnp.linspace(0.0, 0.2, 21)
    chain = _arm(0.004)
    y0 = fd.initial_state(chain, joint_angles=[0.0, 0.0], rotor_angles=[0.012, -0.01])
    traj = fd.simulate(chain, y0, ts, rtol=1e-11, atol=1e-13)
    asm = fd.assemble(chain)
    E = np.asarray(jax.vmap(lambda Q, Qd: fd.total_energy(asm, Q, Qd))(traj.Q, traj.Qd))
    assert np.ptp(E) < 1e-8 * abs(E[0])
    lin = fd.rigs.flexible_link_joint_arm(structural_damping=0.0)
    a = fd.simulate(_arm(0.0), y0, ts, rtol=1e-11, atol=1e-13)
    b = fd.simulate(lin, y0, ts, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(np.asarray(a.Q), np.asarray(b.Q), atol=1e-12)


def test_backlash_dead_zone_limits():
    from flexdyn.nonlinear import backlash_deflection

    b = 0.01
    assert float(backlash_deflection(jnp.asarray(0.2), b)) == pytest.approx(0.2 - b, rel=1e-12)
    assert float(backlash_deflection(jnp.asarray(-0.2), b)) == pytest.approx(-0.2 + b, rel=1e-12)
    small = 1e-4
    assert float(backlash_deflection(jnp.asarray(small), b)) == pytest.approx(small**3 / (3 * b**2), rel=1e-3)
    assert float(backlash_deflection(jnp.asarray(0.003), 0.0)) == 0.003


@pytest.mark.parametrize("name", ["joint1.coulomb", "link1.drag"])
def test_derivatives_at_the_neutral_value_are_finite_and_match_finite_differences(name):
    chain = fd.Chain([fd.RigidLink(0.3, 0.18, drag=0.0)], [fd.RigidJoint(coulomb=0.0)], gravity=(0.0, -9.81))
    Q, Qd = jnp.asarray([0.2]), jnp.asarray([1.3])

    def acc(p):
        c = fd.with_parameters(chain, {name: p})
        return fd.accelerations(c, Q, Qd, jnp.zeros(1))[0]

    d = float(jax.jacfwd(acc)(jnp.asarray(0.0)))
    h = 1e-6
    fd_ = (float(acc(jnp.asarray(h))) - float(acc(jnp.asarray(0.0)))) / h
    assert np.isfinite(d) and d != 0.0
    assert d == pytest.approx(fd_, rel=1e-5)


def test_absent_terms_are_not_parameters():
    rig = fd.rigs.rigid_pendulum()
    assert "joint1.coulomb" not in fd.parameter_names(rig)
    with pytest.raises(KeyError, match="coulomb=0.0"):
        fd.with_parameters(rig, {"joint1.coulomb": 1e-3})
    with pytest.raises(ValueError, match="coulomb_velocity"):
        fd.RigidJoint(coulomb=1e-3, coulomb_velocity=0.0)
    with pytest.raises(ValueError, match="RigidJoint.coulomb"):
        fd.RigidJoint(coulomb=-1e-3)


@pytest.mark.slow  # 84 s in a 2-worker run; friction's and drag's derivatives (the neutral-value test above) and
# backlash's energy balance stay in CI
def test_forward_dynamics_derivatives_with_friction_drag_and_backlash_match_finite_differences():
    """`fd.accelerations` has its own derivative rule (implicit function of the Lagrange
    residual, `flexdyn.chain`); with dry friction, drag on a flexible link and backlash in
    the residual, its forward- and reverse-mode derivatives w.r.t. those parameters, a few
    others, Q and Q_dot equal central finite differences (step 1e-4 in log-parameters, 1e-6
    in the state) to 1e-6 of each column's largest entry (measured: 1.2e-7 at worst), at a
    state inside the backlash's smooth transition zone."""
    rig = fd.rigs.flexible_link_joint_arm(structural_damping=0.01)
    j = rig.joints[0]
    joint1 = fd.ElasticJoint(
        j.stiffness,
        j.rotor_inertia,
        j.gear_ratio,
        spong_approximation=j.spong_approximation,
        backlash=0.004,
        coulomb=0.01,
    )
    chain = eqx.tree_at(lambda c: c.joints, rig, (joint1, rig.joints[1]))
    chain = eqx.tree_at(lambda c: c.links[0].drag, chain, 0.05, is_leaf=lambda x: x is None)
    names = ["joint1.coulomb", "link1.drag", "joint1.backlash", "joint1.stiffness", "link2.EI", "payload.mass"]
    p0 = np.array([float(fd.get_parameter(chain, n)) for n in names])
    n = chain.layout.n_dof
    rng = np.random.default_rng(11)
    Q0 = rng.normal(0.0, 0.01, n)
    Q0[chain.layout.rotor[0]] = Q0[chain.layout.theta[0]] + 0.003  # inside the dead zone's smooth part
    Qd0 = rng.normal(0.0, 0.5, n)
    x0 = np.concatenate([np.log(p0), Q0, Qd0])
    tau = jnp.asarray([0.05, -0.02])

    def acc(x):
        c = fd.with_parameters(chain, dict(zip(names, jnp.exp(x[: len(names)]))))
        return fd.accelerations(c, x[len(names) : len(names) + n], x[len(names) + n :], tau)

    forward = np.asarray(jax.jit(jax.jacfwd(acc))(jnp.asarray(x0)))
    reverse = np.asarray(jax.jit(jax.jacrev(acc))(jnp.asarray(x0)))
    f = jax.jit(acc)
    steps = np.concatenate([np.full(len(names), 1e-4), np.full(2 * n, 1e-6)])
    central = np.stack(
        [
            (np.asarray(f(jnp.asarray(x0 + h * e))) - np.asarray(f(jnp.asarray(x0 - h * e)))) / (2 * h)
            for h, e in zip(steps, np.eye(len(x0)))
        ],
        axis=1,
    )
    colmax = np.max(np.abs(central), axis=0)
    floor = 1e-12 * np.max(colmax)  # columns that are exactly zero (a rate that enters nothing here)
    for ad in (forward, reverse):
        assert np.all(np.max(np.abs(ad - central), axis=0) <= 1e-6 * colmax + floor)
    # measured: coulomb, drag, backlash columns 0.5, 1.7, 1.1e3 (the largest 4.9e6): not vacuous
    assert np.all(colmax[:3] > 1e-2)

"""Bad input gets a clear error naming the part and the parameter; solver failures are
raised with a message that says what to change, never returned as NaNs."""

import json
import math
import os
import subprocess
import sys
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd

NAN = math.nan

# Errors raised inside compiled code by `eqx.error_if`: EquinoxRuntimeError in recent
# equinox (a RuntimeError subclass), ValueError/XlaRuntimeError in older ones.
RUNTIME_ERRORS = (RuntimeError, ValueError, getattr(eqx, "EquinoxRuntimeError", RuntimeError))


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: fd.RigidLink(length=0.0, mass=1.0), r"RigidLink\.length.*> 0"),
        (lambda: fd.RigidLink(length=-0.3, mass=1.0), r"RigidLink\.length.*> 0"),
        (lambda: fd.RigidLink(length=0.3, mass=0.0), r"RigidLink\.mass.*> 0"),
        (lambda: fd.RigidLink(length=0.3, mass=-1.0), r"RigidLink\.mass.*> 0"),
        (lambda: fd.RigidLink(length=0.3, mass=1.0, inertia=-1e-3), r"RigidLink\.inertia"),
        (lambda: fd.FlexibleLink(length=0.0, rho=0.2, EI=1.0), r"FlexibleLink\.length.*> 0"),
        (lambda: fd.FlexibleLink(length=0.5, rho=-0.2, EI=1.0), r"FlexibleLink\.rho.*> 0"),
        (lambda: fd.FlexibleLink(length=0.5, rho=0.0, EI=1.0), r"FlexibleLink\.rho.*> 0"),
        (lambda: fd.FlexibleLink(length=0.5, rho=0.2, EI=0.0), r"FlexibleLink\.EI.*> 0"),
        (lambda: fd.FlexibleLink(length=0.5, rho=0.2, EI=-1.0), r"FlexibleLink\.EI.*> 0"),
        (lambda: fd.FlexibleLink(length=0.5, rho=0.2, EI=1.0, damping_ratio=-0.1), r"FlexibleLink\.damping_ratio"),
        (lambda: fd.ElasticJoint(stiffness=0.0, rotor_inertia=0.02), r"ElasticJoint\.stiffness.*> 0"),
        (lambda: fd.ElasticJoint(stiffness=100.0, rotor_inertia=-0.02), r"ElasticJoint\.rotor_inertia"),
        (lambda: fd.RigidJoint(damping=-1.0), r"RigidJoint\.damping"),
        (lambda: fd.RigidJoint(gear_ratio=0.0), r"RigidJoint\.gear_ratio"),
        (lambda: fd.Hub(mass=-1.0), r"Hub\.mass"),
        (lambda: fd.Hub(inertia=-1e-3), r"Hub\.inertia"),
        (lambda: fd.Payload(mass=-0.1), r"Payload\.mass"),
        (lambda: fd.Payload(inertia=-1e-3), r"Payload\.inertia"),
    ],
)
def test_non_physical_parameters_are_rejected(build, match):
    with pytest.raises(ValueError, match=match):
        build()


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: fd.RigidLink(length=NAN, mass=1.0), r"RigidLink\.length.*finite"),
        (lambda: fd.RigidLink(length=0.3, mass=NAN), r"RigidLink\.mass.*finite"),
        (lambda: fd.FlexibleLink(length=0.5, rho=NAN, EI=1.0), r"FlexibleLink\.rho.*finite"),
        (lambda: fd.FlexibleLink(length=0.5, rho=0.2, EI=NAN), r"FlexibleLink\.EI.*finite"),
        (lambda: fd.FlexibleLink(length=0.5, rho=0.2, EI=math.inf), r"FlexibleLink\.EI.*finite"),
        (lambda: fd.ElasticJoint(stiffness=NAN, rotor_inertia=0.02), r"ElasticJoint\.stiffness.*finite"),
        (lambda: fd.RigidJoint(damping=NAN), r"RigidJoint\.damping.*finite"),
        (lambda: fd.Hub(inertia=NAN), r"Hub\.inertia.*finite"),
        (lambda: fd.Payload(mass=NAN), r"Payload\.mass.*finite"),
        (lambda: fd.Chain([fd.RigidLink(0.3, 0.1)], gravity=(0.0, NAN)), r"Chain\.gravity"),
    ],
)
def test_nan_parameters_are_rejected(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_wrong_shapes_are_rejected():
    link = fd.RigidLink(0.3, 0.1)
    with pytest.raises(ValueError, match=r"Chain\.gravity.*\(2,\).*\(3,\)"):
        fd.Chain([link], gravity=(0.0, 0.0, -9.81))
    with pytest.raises(ValueError, match=r"RigidLink\.length.*shape"):
        fd.RigidLink(jnp.ones(2), 0.1)
    with pytest.raises(ValueError, match=r"Payload\.mass.*shape"):
        fd.Payload(mass=jnp.ones(3))


def test_damping_ratio_of_the_wrong_length_is_rejected():
    """One ratio per mode (or one for all): 3 ratios for 2 modes must name the parameter."""
    with pytest.raises(ValueError, match=r"FlexibleLink\.damping_ratio"):
        fd.FlexibleLink(length=0.5, rho=0.2, EI=1.0, n_modes=2, damping_ratio=[0.01, 0.02, 0.03])


@pytest.mark.parametrize("value", [1, 0.0, "true", None])
def test_non_boolean_geometric_stiffening_is_rejected(value):
    with pytest.raises(ValueError, match=r"FlexibleLink\.geometric_stiffening: expected True or False"):
        fd.FlexibleLink(length=0.5, rho=0.2, EI=1.0, geometric_stiffening=value)


def test_denoc_refuses_a_stiffened_link_by_name():
    link = fd.FlexibleLink(length=0.5, rho=0.2, EI=1.0, n_modes=1, geometric_stiffening=True)
    chain = fd.Chain([fd.RigidLink(length=0.3, mass=0.1), link])
    with pytest.raises(ValueError, match=r"links\[1\] \(link2\): geometric_stiffening=True is not in the DeNOC"):
        fd.denoc.denoc_accelerations(chain, jnp.zeros(3), jnp.zeros(3), jnp.zeros(2))


@pytest.mark.parametrize("n_modes", [2.0, 0, -1, "2", 1.5])
def test_non_integer_or_non_positive_n_modes_is_rejected(n_modes):
    with pytest.raises(ValueError, match=r"FlexibleLink\.n_modes"):
        fd.FlexibleLink(length=0.5, rho=0.2, EI=1.0, n_modes=n_modes)


def test_chain_with_mismatched_parts_is_rejected():
    links = [fd.RigidLink(0.3, 0.1), fd.RigidLink(0.3, 0.1)]
    with pytest.raises(ValueError, match=r"Chain\.joints.*2.*got 1"):
        fd.Chain(links, joints=[fd.RigidJoint()])
    with pytest.raises(ValueError, match=r"Chain\.hubs.*2.*got 3"):
        fd.Chain(links, hubs=[fd.Hub()] * 3)
    with pytest.raises(ValueError, match=r"Chain\.joints\[1\].*RigidJoint or ElasticJoint"):
        fd.Chain(links, joints=[fd.RigidJoint(), fd.Hub()])
    with pytest.raises(ValueError, match=r"Chain\.links"):
        fd.Chain([])
    with pytest.raises(ValueError, match=r"Chain\.payload"):
        fd.Chain(links, payload=fd.Hub())


def test_bad_simulation_arguments_are_rejected():
    chain = fd.rigs.rigid_pendulum()
    with pytest.raises(ValueError, match=r"y0.*\(2,\).*theta1.*\(3,\)"):
        fd.simulate(chain, jnp.zeros(3), jnp.linspace(0.0, 1.0, 3))
    with pytest.raises(ValueError, match=r"ts.*at least 2"):
        fd.simulate(chain, jnp.zeros(2), jnp.array([0.0]))
    with pytest.raises(ValueError, match=r"initial_state: joint_angles.*\(1,\)"):
        fd.initial_state(chain, [0.0, 1.0])
    ts = jnp.linspace(0.0, 1.0, 3)
    with pytest.raises(ValueError, match=r"simulate: dtmax expected a step > 0 s, got -0.001"):
        fd.simulate(chain, jnp.zeros(2), ts, dtmax=-1e-3)
    with pytest.raises(ValueError, match=r"simulate: dtmax bounds the adaptive steps"):
        fd.simulate(chain, jnp.zeros(2), ts, dt=1e-3, dtmax=1e-3)
    with pytest.raises(ValueError, match=r"tsit5_trajectory: dtmax expected a step > 0 s, got nan"):
        fd.tsit5_trajectory(chain, jnp.zeros(2), ts, dtmax=float("nan"))
    with pytest.raises(ValueError, match=r"simulate: dt expected a fixed step > 0 s.*got 0.0"):
        fd.simulate(chain, jnp.zeros(2), ts, dt=0.0)


def test_non_finite_initial_states_and_torques_are_named():
    """Found in a new-user review: a NaN in `y0` or in the input ran until max_steps (4 s)
    and then advised raising max_steps; `initial_state` took a NaN angle."""
    chain = fd.rigs.two_link_flexible_arm()
    ts = jnp.linspace(0.0, 0.2, 3)
    y0 = fd.initial_state(chain, [0.1, 0.0])
    for solve in ("simulate", "tsit5_trajectory"):
        with pytest.raises(RUNTIME_ERRORS, match=rf"{solve}: y0 has a non-finite entry"):
            getattr(fd, solve)(chain, y0.at[0].set(NAN), ts).Q.block_until_ready()
        with pytest.raises(RUNTIME_ERRORS, match=rf"{solve}: the torque input is not finite \(NaN or inf\) at ts\[0\]"):
            getattr(fd, solve)(chain, y0, ts, fd.BangBang([NAN, 0.1], 0.1)).Q.block_until_ready()
    with pytest.raises(RUNTIME_ERRORS, match=r"simulate: the torque input is not finite"):
        fd.simulate(chain, y0, ts, fd.BangBang([NAN, 0.1], 0.1), dt=1e-3).Q.block_until_ready()
    from flexdyn.simulation import as_initial_state

    with pytest.raises(ValueError, match=r"simulate: y0 expected finite values, got nan at index 0 \(theta1\)"):
        as_initial_state(fd.assemble(chain), y0.at[0].set(NAN), "simulate")
    with pytest.raises(ValueError, match=r"initial_state.joint_angles: expected a finite number, got \[nan"):
        fd.initial_state(chain, [NAN, 0.0])


def test_initial_state_can_be_traced():
    """`jax.vmap` over release angles (review: a TracerArrayConversionError): the same
    states as built one by one."""
    chain = fd.rigs.flexible_link_joint_arm()
    angles = jnp.asarray([[0.1, -0.2], [0.3, 0.0]])
    batch = jax.vmap(lambda a: fd.initial_state(chain, a, joint_rates=2 * a))(angles)
    for a, y in zip(angles, batch):
        assert jnp.array_equal(y, fd.initial_state(chain, [float(a[0]), float(a[1])], joint_rates=2 * a))


@pytest.mark.parametrize("solve", ["simulate", "tsit5_trajectory", "rk4_trajectory"])
@pytest.mark.parametrize("ts", [[0.5, 0.4, 0.3], [0.0, 0.2, 0.1, 0.3], [0.0, math.nan, 0.3]])
def test_times_that_are_not_finite_and_increasing_are_rejected(solve, ts):
    """diffrax integrates a decreasing grid backwards from `y0` at `ts[0]` without a word
    (found in review): every solve checks `ts` (at run time when traced)."""
    chain = fd.rigs.rigid_pendulum()
    y0 = fd.initial_state(chain, [0.3])
    kwargs = {"dt": 1e-3} if solve == "rk4_trajectory" else {}
    with pytest.raises(RUNTIME_ERRORS, match=rf"{solve}: ts expected finite, strictly increasing times"):
        getattr(fd, solve)(chain, y0, jnp.asarray(ts), **kwargs).Q.block_until_ready()


def test_review_api_mistakes_get_clear_errors():
    """Found in a new-user review: `modal_analysis` given the whole state failed in a
    broadcast; `FlexibleLink(n_modes=19)` was accepted and failed later without naming
    the link; `Hub(2e-3)` silently set the hub's mass."""
    chain = fd.rigs.flexible_pendulum(n_modes=2)
    with pytest.raises(ValueError, match=r"modal_analysis: Q0 expected shape \(3,\).*y0\[:3\]"):
        fd.modal_analysis(chain, jnp.zeros(6))
    with pytest.raises(ValueError, match=r"FlexibleLink.n_modes: expected an integer from 1 to 18, got 19"):
        fd.FlexibleLink(length=0.5, rho=0.1, EI=1.0, n_modes=19)
    with pytest.raises(TypeError):
        fd.Hub(2e-3)


def test_single_precision_is_warned_about():
    """flexdyn expects float64 (its default tolerances are below float32's resolution):
    a solve in single precision warns (found in review: it ran 5x the steps in silence)."""
    with jax.enable_x64(False), pytest.warns(UserWarning, match="simulate: JAX runs in single precision"):
        chain = fd.rigs.rigid_pendulum()  # float32 parameters
        traj = fd.simulate(chain, jnp.zeros(2), jnp.linspace(0.0, 0.1, 3), rtol=1e-4, atol=1e-6)
        assert traj.Q.dtype == jnp.float32


def test_a_parameter_given_as_a_jax_array_is_shown_as_a_number():
    # found in review: "got Array(-0.003, dtype=float64)"
    chain = fd.rigs.rigid_pendulum()
    with pytest.raises(ValueError, match=r"RigidJoint.damping: expected a value >= 0, got -0.003$"):
        fd.with_parameters(chain, {"joint1.damping": jnp.asarray(-3e-3)})


def test_angles_that_look_like_degrees_are_warned_about():
    """flexdyn takes radians: a start or goal angle above a turn (90, meant as degrees)
    warns, naming the argument and the value in radians it may have meant; angles within
    a turn, and traced ones, do not."""
    from flexdyn import design

    chain = fd.rigs.two_link_flexible_arm()
    with pytest.warns(UserWarning, match=r"initial_state.joint_angles\[1\] = 90 rad .* 1.5708 rad"):
        fd.initial_state(chain, joint_angles=[0.0, 90.0])
    with pytest.warns(UserWarning, match=r"QuinticReference.end\[0\] = -180 rad"):
        fd.QuinticReference([0.0, 0.0], [-180.0, 30.0], 2.0)
    with pytest.warns(UserWarning, match=r"RestToRestMove.goal_angles\[0\] = 45 rad"):
        design.RestToRestMove(chain, [0.0, 0.0], [45.0, 0.5], 1.0, 0.4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fd.initial_state(chain, joint_angles=[-6.28, 6.28])
        fd.QuinticReference([0.0, 0.0], [math.pi / 2, math.pi / 6], 2.0)
        jax.vmap(lambda a: fd.QuinticReference(a, a, 1.0).end)(jnp.full((3, 2), 90.0))


def test_torque_of_the_wrong_size_is_rejected():
    """A 2-joint input on a 1-joint chain must say so, not fail inside a matmul."""
    chain = fd.rigs.rigid_pendulum()
    with pytest.raises(ValueError, match=r"torque"):
        fd.simulate(chain, jnp.zeros(2), jnp.linspace(0.0, 0.1, 3), fd.BangBang([0.2, 0.2], 1.0))


# ---------------------------------------------------------------------------
# Solver failures are raised, never returned as NaN
# ---------------------------------------------------------------------------


STABILITY = r"dt = \S+ s is above RK4's stability limit.*reduce dt"


def test_unstable_fixed_step_raises_instead_of_returning_nan():
    """RK4 at 50 ms on the 3-mode flexible pendulum (highest mode ~2700 rad/s, RK4's
    stability limit ~2.8 / 2700 s = 1 ms) would blow up: the error names dt (raised before
    the run, from the linearisation at y0: `fd.linear.check_rk4_step`)."""
    chain = fd.rigs.flexible_pendulum(n_modes=3)
    y0 = fd.initial_state(chain, [0.0], modal=[1e-4, 0.0, 0.0])
    with pytest.raises(RUNTIME_ERRORS, match=STABILITY):
        fd.simulate(chain, y0, jnp.linspace(0.0, 2.0, 5), dt=0.05).Q.block_until_ready()
    with pytest.raises(RUNTIME_ERRORS, match=STABILITY):  # input jumps: the step controller's path
        fd.simulate(chain, y0, jnp.linspace(0.0, 2.0, 5), fd.BangBang(0.01, 0.5), dt=0.05, max_steps=1000).Q


def _rk4_rigs():
    own = fd.Chain(  # an aluminium strip on a hub with a payload, undamped (review's rig)
        [fd.FlexibleLink(length=0.5, rho=0.081, EI=0.39375, n_modes=2)],
        hubs=[fd.Hub(inertia=2e-3)],
        payload=fd.Payload(mass=0.05),
    )
    # paper 004's arm: elastic joints and structural damping (not proportional damping)
    return {"strip": own, "paper004": fd.rigs.flexible_link_joint_arm()}


def _rk4_final_as_trajectory(chain, y0, ts, torque, dt):
    """`fixed_step.rk4_final`'s final state, as `.Q` like a trajectory's (the whole state)."""
    import types

    from flexdyn import fixed_step

    y = fixed_step.rk4_final(chain, y0, float(ts[0]), float(ts[-1]), torque, dt=float(dt))
    return types.SimpleNamespace(Q=y[None])


@pytest.mark.parametrize(
    "rig, solve",
    [("strip", "simulate"), ("paper004", "simulate"), ("strip", "rk4_trajectory"), ("strip", "rk4_final")],
)
def test_a_fixed_step_just_above_the_rk4_stability_limit_is_refused(rig, solve):
    """Oracle: `fd.stable_step(solver="rk4")`, the limit from the eigenvalues of the full
    linearisation `A` (NumPy). 3 % above it the run is refused (found in review: 16 %
    above, a finite but wrong hub angle, 6.16 rad against 0.107); 3 % below it runs."""
    chain = _rk4_rigs()[rig]
    y0 = fd.initial_state(chain, [0.3] * chain.n_links)
    limit = fd.stable_step(chain, y0, solver="rk4", safety=1.0)
    ts = jnp.linspace(0.0, 50 * limit, 3)
    torque = fd.BangBang([0.01] * chain.n_links, 10 * limit)
    run = _rk4_final_as_trajectory if solve == "rk4_final" else getattr(fd, solve)
    with pytest.raises(RUNTIME_ERRORS, match=rf"{solve}: the fixed step {STABILITY}"):
        run(chain, y0, ts, torque, dt=1.03 * limit).Q.block_until_ready()
    traj = run(chain, y0, ts, torque, dt=0.97 * limit)
    assert jnp.all(jnp.isfinite(traj.Q))


def test_too_few_steps_raises_naming_max_steps():
    chain = fd.rigs.rigid_pendulum()
    y0 = fd.initial_state(chain, [0.0])
    with pytest.raises(RUNTIME_ERRORS, match=r"max_steps"):
        fd.simulate(chain, y0, jnp.linspace(0.0, 1.0, 3), max_steps=4).Q.block_until_ready()


def test_negative_traced_stiffness_raises_at_run_time():
    """Under jit the parameter is a tracer (no construction-time check): assembly's
    run-time check must stop a negative EI rather than return NaN or a wrong answer."""
    ts = jnp.linspace(0.0, 0.1, 3)

    @jax.jit
    def final_state(EI):
        link = fd.FlexibleLink(length=0.3, rho=0.4, EI=EI, n_modes=1)
        chain = fd.Chain([link], gravity=(0.0, -9.81))
        y0 = fd.initial_state(chain, [0.0])
        return fd.simulate(chain, y0, ts).Q[-1]

    assert jnp.all(jnp.isfinite(final_state(3.3)))  # a valid EI runs
    with pytest.raises(RUNTIME_ERRORS, match=r"link1\.EI must be finite and > 0"):
        final_state(-3.3).block_until_ready()
    with pytest.raises(RUNTIME_ERRORS, match=r"link1\.EI must be finite and > 0"):
        final_state(jnp.nan).block_until_ready()


def test_negative_traced_payload_mass_raises_under_vmap():
    """The same through eqx.tree_at + vmap: one bad batch member is reported."""
    chain = fd.rigs.flexible_pendulum(n_modes=1)
    y0 = fd.initial_state(chain, [0.0])
    ts = jnp.linspace(0.0, 0.1, 3)

    def final_state(mass):
        c = eqx.tree_at(lambda c: c.links[0].rho, chain, mass)
        return fd.simulate(c, y0, ts).Q[-1]

    with pytest.raises(RUNTIME_ERRORS, match=r"link1\.rho must be finite and > 0"):
        jax.vmap(final_state)(jnp.array([0.39, -0.39])).block_until_ready()


def _every_parameter():
    """(chain, part path, parameter, kind) for every entry of every part's `PARAMETERS`
    table, on a chain holding each kind of part (drag, friction and backlash present)."""
    chain = fd.Chain(
        [
            fd.RigidLink(length=0.3, mass=0.2, drag=0.01),
            fd.FlexibleLink(length=0.4, rho=0.2, EI=2.0, n_modes=1, drag=0.01),
        ],
        joints=[
            fd.RigidJoint(coulomb=0.01),
            fd.ElasticJoint(stiffness=50.0, rotor_inertia=1e-3, coulomb=0.01, backlash=0.01),
        ],
        hubs=[fd.Hub(mass=0.1, inertia=1e-3), fd.Hub(mass=0.1, inertia=1e-3)],
        payload=fd.Payload(mass=0.05, inertia=1e-5),
    )
    cases = []
    for group, parts in (("links", chain.links), ("joints", chain.joints), ("hubs", chain.hubs)):
        for i, part in enumerate(parts):
            for name, kind in part.PARAMETERS:
                assert getattr(part, name) is not None, name  # every optional term present
                cases.append((chain, (group, i), f"{group[:-1]}{i + 1}.{name}", name, kind))
    for name, kind in chain.payload.PARAMETERS:
        cases.append((chain, ("payload", None), f"payload.{name}", name, kind))
    return cases


@pytest.mark.parametrize("case", _every_parameter(), ids=lambda c: c[2])
def test_every_parameter_set_after_construction_is_checked(case):
    """`eqx.tree_at` bypasses the constructor's checks, and under vmap the values are
    traced: assembly checks every parameter of every part as its constructor does
    (found in review: a negative damping ratio under vmap made the energy grow 1700x,
    a negative hub inertia read as 'raise max_steps'). A concrete bad value raises the
    constructor's ValueError; a traced one an error naming `partN.name`; a Python float
    is accepted as an array (it used to fail with "No arrays to thread error on to")."""
    chain, (group, i), label, name, kind = case

    def part_of(c):
        return c.payload if group == "payload" else getattr(c, group)[i]

    good = getattr(part_of(chain), name)
    bad = -1.0 if kind != "signed" else math.nan
    replaced = eqx.tree_at(lambda c: getattr(part_of(c), name), chain, jnp.full(jnp.shape(good), bad))
    with pytest.raises(ValueError, match=rf"{label}: expected"):
        fd.assemble(replaced)

    def assembled_mass(value):
        c = eqx.tree_at(lambda c: getattr(part_of(c), name), chain, jnp.full(jnp.shape(good), value))
        return fd.mass_matrix(fd.assemble(c), jnp.zeros(chain.n_dof))[0, 0]

    values = jnp.array([float(jnp.ravel(good)[0]), bad])
    with pytest.raises(RUNTIME_ERRORS, match=rf"{label} must be finite"):
        jax.vmap(assembled_mass)(values).block_until_ready()
    if jnp.ndim(good) == 0:  # a Python float set by tree_at: the same chain as with an array
        as_float = eqx.tree_at(lambda c: getattr(part_of(c), name), chain, float(good))
        q = jnp.zeros(chain.n_dof)
        assert jnp.array_equal(fd.mass_matrix(fd.assemble(as_float), q), fd.mass_matrix(fd.assemble(chain), q))


def test_review_mistakes_of_a_new_arm_get_clear_errors_and_warnings():
    """Found in a new-user review of payload sweeps and move design: a single link passed
    as `links=` failed with "'FlexibleLink' object is not iterable"; a mode shape of the
    wrong length reached a raw dot_general error; lengths in mm passed without a word; a
    tip deflection above the link's length came back without a word (the model
    assumes small deflections)."""
    link = fd.FlexibleLink(0.5, 0.3, 1.0, n_modes=2)
    with pytest.raises(TypeError, match=r"Chain.links: expected a list of parts.*got a single FlexibleLink"):
        fd.Chain(links=link)
    with pytest.raises(TypeError, match=r"Chain.hubs: expected a list of parts.*got a single Hub"):
        fd.Chain(links=[link], hubs=fd.Hub(inertia=0.01))
    arm = fd.Chain([fd.RigidLink(0.3, 0.4), link], hubs=[fd.Hub(inertia=0.01), fd.Hub(mass=0.3, inertia=0.002)])
    with pytest.raises(ValueError, match=r"tip_deflections: Q expected shape \(4,\).*got \(3,\)"):
        fd.tip_deflections(arm, jnp.zeros(3))
    # review: mass_matrix of a short Q came back smaller without a word, the energies raised
    # IndexError (wrong shapes) or AttributeError (a Chain instead of an assembled one)
    with pytest.raises(ValueError, match=r"mass_matrix: Q expected shape \(4,\).*got \(3,\)"):
        fd.mass_matrix(arm, jnp.zeros(3))
    with pytest.raises(ValueError, match=r"kinetic_energy: Qd expected shape \(4,\).*y\[4:\] of a state"):
        fd.kinetic_energy(arm, jnp.zeros(4), jnp.zeros(2))
    with pytest.raises(ValueError, match=r"potential_energy: Q expected shape \(4,\)"):
        fd.potential_energy(arm, jnp.zeros(5))
    with pytest.raises(ValueError, match=r"stiffness_matrix: Q expected shape \(4,\)"):
        fd.stiffness_matrix(arm, jnp.zeros(2))
    # a Chain is assembled on the way in: its energy equals the assembled chain's (0 at rest, Q = 0)
    assert float(fd.total_energy(arm, jnp.zeros(4), jnp.zeros(4))) == 0.0
    with pytest.raises(TypeError, match=r"RigidLink.length: expected a number or an array of numbers.*'abc'"):
        fd.RigidLink(length="abc", mass=0.3)
    with pytest.raises(TypeError, match=r"FlexibleLink.EI: expected a number"):
        fd.FlexibleLink(0.5, 0.3, "stiff")
    with pytest.warns(UserWarning, match=r"RigidLink.length = 300 m is over 50 m.*pass 0.3"):
        fd.RigidLink(300.0, 0.4)
    y0 = fd.initial_state(arm, [0.0, 0.0])
    ts = jnp.linspace(0.0, 1.0, 101)
    small, large = fd.BangBang([0.3, 0.1], 0.3), fd.BangBang([5.0, 2.5], 0.3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fd.observe(arm, fd.simulate(arm, y0, ts, small), small)
    with pytest.warns(
        UserWarning, match=r"observe: link2's elastic tip deflection reaches [\d.]+ m, \d+ % of its 0.5 m length"
    ):
        fd.observe(arm, fd.simulate(arm, y0, ts, large), large)


def test_modal_analysis_in_single_precision_is_warned_about():
    """`modal_analysis` in float32 warns, as `simulate` does (found in review: it said
    nothing), and the error the warning states (~1e-4 relative, up to 2.2e-4 on paper
    004's arm) holds against the float64 analysis. Run as a user would, in a process of
    its own started with FLEXDYN_NO_X64=1 (switching precision inside this process mixes
    float64 constants already built into float32 code)."""
    code = (
        "import flexdyn as fd, numpy as np; "
        "print(np.asarray(fd.modal_analysis(fd.rigs.flexible_link_joint_arm()).natural_frequency).tolist())"
    )
    env = dict(os.environ, FLEXDYN_NO_X64="1")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "modal_analysis: JAX runs in single precision" in run.stderr, run.stderr
    f32 = np.array(json.loads(run.stdout.strip().splitlines()[-1]))
    f64 = np.asarray(fd.modal_analysis(fd.rigs.flexible_link_joint_arm()).natural_frequency)
    flexible = f64 > 0
    assert np.all(f32[~flexible] == 0.0), f32
    error = np.abs(f32[flexible] / f64[flexible] - 1)
    assert error.max() < 5e-4, error


def test_an_unknown_parameter_name_suggests_the_one_meant():
    """Review: `link1.ei` raised a `KeyError` shown with escaped quotes and no hint (and
    `identify.make_problem` a `ValueError` for the same mistake): now one error that is
    both, its message as written, with the name meant."""
    chain = fd.rigs.flexible_pendulum()
    with pytest.raises(fd.UnknownParameterError) as e:
        fd.with_parameters(chain, {"link1.ei": 2.0})
    assert isinstance(e.value, KeyError) and isinstance(e.value, ValueError)
    assert str(e.value).startswith("unknown parameter 'link1.ei' (did you mean 'link1.EI'?); this chain has: ")
    with pytest.raises(ValueError, match=r"'joint1.dampin' \(did you mean 'joint1.damping'\?\)"):
        fd.get_parameter(chain, "joint1.dampin")
    with pytest.raises(ValueError, match=r"unknown parameter 'spring'; this chain has"):  # nothing close
        fd.get_parameter(chain, "spring")


def test_an_absent_optional_term_is_named_and_can_be_added():
    """Review: `joint2.coulomb` on a rig without dry friction raised a plain `KeyError`
    (quoted message). Now an `UnknownParameterError` saying how to add the term;
    `with_optional_terms` adds it at 0.0, where the equations are those without it: the
    pendulum swings the same to the last bit, and a dry friction of 1 mN m then slows it."""
    chain = fd.rigs.rigid_pendulum()
    with pytest.raises(fd.UnknownParameterError) as e:
        fd.get_parameter(chain, "joint1.coulomb")
    assert "joint 1 has no coulomb term" in str(e.value) and "with_optional_terms" in str(e.value)
    assert not str(e.value).startswith('"')
    added = fd.with_optional_terms(chain, ["joint1.coulomb", "link1.drag"])
    assert {"joint1.coulomb", "link1.drag"} <= set(fd.parameter_names(added))
    assert fd.with_optional_terms(added, ["joint1.coulomb"]) is added  # present: unchanged
    with pytest.raises(fd.UnknownParameterError, match="unknown parameter 'joint1.backlash'"):
        fd.with_optional_terms(chain, ["joint1.backlash"])  # an elastic joint's term
    ts = jnp.linspace(0.0, 1.0, 11)
    y0 = fd.initial_state(chain, joint_angles=[0.0])
    plain = fd.simulate(chain, y0, ts, dt=1e-3).Q[:, 0]
    neutral = fd.simulate(added, y0, ts, dt=1e-3).Q[:, 0]
    np.testing.assert_array_equal(np.asarray(neutral), np.asarray(plain))
    dry = fd.simulate(fd.with_parameters(added, {"joint1.coulomb": 1e-3}), y0, ts, dt=1e-3).Q[:, 0]
    assert float(jnp.max(jnp.abs(dry - plain))) > 1e-4


def test_modal_analysis_away_from_an_equilibrium_is_warned_about():
    """Physics review: a pendulum under gravity analysed horizontal gave `[0.]` (its
    gravity stiffness vanishes there), read as a free rotation. The holding torque there is
    m g c (closed form, named in the warning); hanging, or a milliradian off, nothing is
    said (warnings are errors in this suite); 0.1 rad off, the first-order distance to the
    rest is named."""
    chain = fd.rigs.rigid_pendulum()
    with pytest.warns(
        UserWarning, match=r"Q0 is not an equilibrium at rest: the generalised force there is (\S+) on theta1"
    ):
        fd.modal_analysis(chain, jnp.array([0.0]))
    hold = float(fd.inverse_dynamics(chain, jnp.array([0.0]), jnp.zeros(1), jnp.zeros(1))[0])  # m g c
    assert abs(hold) > 0.1
    with pytest.warns(UserWarning, match=f"{-hold:.3g} on theta1"):
        fd.modal_analysis(chain, jnp.array([0.0]))
    fd.modal_analysis(chain, jnp.array([-jnp.pi / 2]))
    fd.modal_analysis(chain, jnp.array([-jnp.pi / 2 + 1e-3]))  # (a simulation's end, still swinging)
    # 0.1 rad off hanging: the rest is -0.1 rad away to first order (tan(0.1) = 0.1003)
    with pytest.warns(UserWarning, match=r"whose rest, to first order, is -5\.7\d deg away in theta1"):
        fd.modal_analysis(chain, jnp.array([-jnp.pi / 2 + 0.1]))

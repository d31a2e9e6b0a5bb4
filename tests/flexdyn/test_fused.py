"""Tests of `flexdyn.fused.rk4_sweep_final` (whole RK4 trajectories of a batch in one
program, the right-hand side written out on scalars).

Oracles: `vmap(fixed_step.rk4_final)`, the same method on the same steps through the
generic array program (itself checked against Dopri8 and the fourth-order law in
test_fixed_step), to round-off; and a Dopri8 solution at rtol 1e-12, to RK4's error.
The Pallas kernel runs in Pallas's interpreter here (CI has no GPU); the GPU runs are in
`benchmarks/bench_gpu_sweep.py`.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
from flexdyn import fixed_step, fused

ARM = fd.rigs.two_link_flexible_arm(payload_mass=0.05, n_modes=1)
TORQUE = fd.BangBang([0.3, -0.2], 0.25)  # jumps at 0.25 s and 0.5 s
Y0 = fd.initial_state(ARM, joint_angles=[0.1, -0.2])
PAYLOADS = jnp.linspace(0.02, 0.12, 6)
T1, DT = 0.3, 1 / 200  # 60 steps across the jump at 0.25 s (one horizon: the programs compile once)


def arms(payloads, hub_inertia=None):
    """A payload sweep of ARM (hub 1 inertia changed too when given)."""

    def one(m):
        chain = eqx.tree_at(lambda c: c.payload.mass, ARM, m)
        if hub_inertia is not None:
            chain = eqx.tree_at(lambda c: c.hubs[0].inertia, chain, hub_inertia)
        return chain

    return jax.vmap(one)(payloads)


@jax.jit
def rk4_final_each(chains, y0):
    return jax.vmap(lambda c, y: fixed_step.rk4_final(c, y, 0.0, T1, TORQUE, dt=DT))(chains, y0)


def test_xla_backend_matches_rk4_final_and_dopri8():
    chains = arms(PAYLOADS)
    got = np.asarray(fused.rk4_sweep_final(chains, Y0, 0.0, T1, TORQUE, dt=DT, backend="xla"))
    want = np.asarray(rk4_final_each(chains, jnp.broadcast_to(Y0, (6, Y0.size))))
    # Same steps and method; only the order of the floating-point operations differs.
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.max(np.abs(want)))
    # The payload changes the answer (the swept scalars are read per trajectory, not folded).
    assert np.max(np.abs(got[0] - got[-1])) > 1e-3
    # Against the physics: Dopri8 at rtol 1e-12 for the heaviest payload, to RK4's error at this dt.
    last = jax.tree_util.tree_map(lambda x: x[-1] if eqx.is_array(x) else x, chains)
    ref = fd.simulate(last, Y0, jnp.array([0.0, T1]), TORQUE, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(got[-1], np.asarray(ref.y[-1]), atol=1e-6)


def test_pallas_kernel_interpreted_matches_rk4_final():
    # 6 trajectories in programs of 4 (the batch padded to 8).
    y0 = Y0 + 0.01 * jnp.arange(6.0)[:, None] * (jnp.arange(Y0.size) < 2).astype(float)  # one per entry
    chains = arms(PAYLOADS)
    got = np.asarray(
        fused.rk4_sweep_final(chains, y0, 0.0, T1, TORQUE, dt=DT, backend="pallas", block=4, interpret=True)
    )
    want = np.asarray(rk4_final_each(chains, y0))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.max(np.abs(want)))
    assert np.max(np.abs(got[0, :2] - got[-1, :2])) > 1e-3  # the per-entry initial states are used


def test_folded_constants_not_reused_across_sweeps():
    # Two sweeps of the same payloads with a different (folded) hub inertia: the second
    # must not reuse the first one's program, whose constants hold the first inertia.
    first = np.asarray(fused.rk4_sweep_final(arms(PAYLOADS), Y0, 0.0, T1, TORQUE, dt=DT))
    chains = arms(PAYLOADS, 0.05)
    second = np.asarray(fused.rk4_sweep_final(chains, Y0, 0.0, T1, TORQUE, dt=DT))
    want = np.asarray(rk4_final_each(chains, jnp.broadcast_to(Y0, (6, Y0.size))))
    np.testing.assert_allclose(second, want, rtol=0, atol=1e-12 * np.max(np.abs(want)))
    assert np.max(np.abs(first - second)) > 1e-3


@pytest.mark.slow  # 33 s in a 2-worker run; the gather it needs stays in CI (test_scalarize)
def test_state_feedback_input():
    # A PD controller tracking a quintic: the torque reads the state (through a gather).
    reference = fd.QuinticReference(jnp.array([0.0, 0.0]), jnp.array([0.5, 0.3]), 0.2)
    pd = fd.PDTracking(reference, jnp.array([5.0, 3.0]), jnp.array([0.5, 0.3]), ARM.layout.actuated, ARM.layout.n_dof)
    same = fd.PDTracking.for_chain(ARM, reference, [5.0, 3.0], [0.5, 0.3])  # the convenience constructor
    assert jax.tree.structure(same) == jax.tree.structure(pd)
    assert jax.tree.all(jax.tree.map(jnp.array_equal, same, pd))
    chains = arms(PAYLOADS[:3])
    got = np.asarray(fused.rk4_sweep_final(chains, Y0, 0.0, T1, pd, dt=DT, backend="xla"))
    y0 = jnp.broadcast_to(Y0, (3, Y0.size))
    want = np.asarray(jax.vmap(lambda c, y: fixed_step.rk4_final(c, y, 0.0, T1, pd, dt=DT))(chains, y0))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.max(np.abs(want)))


def test_traced_batch_inside_jit():
    # Under jit nothing is known: every assembled scalar is read per trajectory. Same answer.
    got = jax.jit(lambda m: fused.rk4_sweep_final(arms(m), Y0, 0.0, T1, TORQUE, dt=DT, backend="xla"))(PAYLOADS)
    want = fused.rk4_sweep_final(arms(PAYLOADS), Y0, 0.0, T1, TORQUE, dt=DT, backend="xla")
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-12)


def test_errors():
    chains = arms(PAYLOADS[:2])
    with pytest.raises(ValueError, match="got a single chain"):
        fused.rk4_sweep_final(ARM, Y0, 0.0, 0.1, TORQUE, dt=1e-3)
    with pytest.raises(ValueError, match="block expected a power of 2"):
        fused.rk4_sweep_final(chains, Y0, 0.0, 0.1, TORQUE, dt=1e-3, block=3)
    with pytest.raises(ValueError, match="dt expected a step > 0 s"):
        fused.rk4_sweep_final(chains, Y0, 0.0, 0.1, TORQUE, dt=0.0)
    with pytest.raises(ValueError, match="expected t1 > t0"):
        fused.rk4_sweep_final(chains, Y0, 0.1, 0.1, TORQUE, dt=1e-3)
    with pytest.raises(ValueError, match="backend expected one of"):
        fused.rk4_sweep_final(chains, Y0, 0.0, 0.1, TORQUE, dt=1e-3, backend="cuda")
    with pytest.raises(ValueError, match="solve expected one of"):
        fused.rk4_sweep_final(chains, Y0, 0.0, 0.1, TORQUE, dt=1e-3, solve="cho")
    with pytest.raises(ValueError, match=r"y0 expected shape \(8,\) or \(2, 8\)"):
        fused.rk4_sweep_final(chains, Y0[:4], 0.0, 0.1, TORQUE, dt=1e-3)
    # An input whose evaluation has no scalar form (a SampledTorque's interpolation searches).
    sampled = fd.SampledTorque(jnp.linspace(0.0, 0.1, 5), jnp.ones((5, 2)))
    with pytest.raises(NotImplementedError, match=r"SampledTorque: its interpolation searches .*'scan'.*rk4_final"):
        fused.rk4_sweep_final(chains, Y0, 0.0, 0.1, sampled, dt=1e-2)
    # A step far above the stability limit of the link's mode: a clear error, not NaN.
    with pytest.raises(ValueError, match=r"dt = 0.2 s is above RK4's stability limit .* batch entries 0, 1 \(of 2\)"):
        jax.block_until_ready(fused.rk4_sweep_final(chains, Y0, 0.0, 2.0, TORQUE, dt=0.2, backend="xla"))
    # One bad entry among good ones is named (review: the error did not say which); here
    # its initial state (a NaN parameter is refused earlier, by the assembly's checks).
    y0 = jnp.stack([Y0, Y0.at[3].set(jnp.nan), Y0])
    with pytest.raises(ValueError, match=r"batch entry 1 \(of 3\)"):
        fused.rk4_sweep_final(arms(PAYLOADS[:3]), y0, 0.0, 0.01, TORQUE, dt=1e-3, backend="xla")
    with pytest.raises(ValueError, match=r"torque: the input returns shape \(1,\), expected \(2,\)"):
        fused.rk4_sweep_final(chains, Y0, 0.0, 0.01, fd.BangBang([0.3], 0.25), dt=1e-3, backend="xla")
    # A NaN parameter in one entry: named with its entry before anything is assembled.
    with pytest.raises(ValueError, match=r"rk4_sweep_final: payload.mass expected finite .* entry 1 \(nan\) of 2"):
        fused.rk4_sweep_final(arms(jnp.asarray([0.05, jnp.nan])), Y0, 0.0, 0.01, TORQUE, dt=1e-3, backend="xla")
    # A step above RK4's stability limit of one entry only (the lightest payload's stiffest
    # mode): named, not a finite but wrong final state (review). Oracle: fd.stable_step.
    light = arms(jnp.asarray([0.005, 0.12]))
    limit = [
        fd.stable_step(eqx.tree_at(lambda c: c.payload.mass, ARM, m), Y0, solver="rk4", safety=1.0)
        for m in (0.005, 0.12)
    ]
    dt = 1.1 * limit[0]
    assert dt < limit[1]  # the heavier entry is stable at this step
    with pytest.raises(ValueError, match=r"above RK4's stability limit .* batch entry 0 \(of 2\)"):
        fused.rk4_sweep_final(light, Y0, 0.0, 0.01, TORQUE, dt=dt, backend="xla")
    # Inside jit the values are not known on the host: the check still raises.
    with pytest.raises(Exception, match="stability limit .* an entry of the batch"):
        jax.block_until_ready(
            jax.jit(lambda c: fused.rk4_sweep_final(c, Y0, 0.0, 2.0, TORQUE, dt=0.2, backend="xla"))(chains)
        )

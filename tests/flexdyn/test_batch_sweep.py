"""flexdyn.batch: sweeps sharded over devices equal the plain vmapped call.

Several devices are emulated on the CPU with `XLA_FLAGS=--xla_force_host_platform_device_count=4`,
which must be set before jax is imported: those checks run in a subprocess."""

import json
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
from flexdyn import batch as fb

# Run in the subprocess: 4 emulated CPU devices, a batch of 7 (padded to 8) payload masses of
# a rigid-link arm (fixed-step RK4, so the arithmetic per entry is identical however the
# batch is split), and a batch given as a stacked Chain with a replicated shared argument.
_SHARDED_SCRIPT = textwrap.dedent(
    """
    import json, os, sys
    import equinox as eqx, jax, jax.numpy as jnp, numpy as np
    import flexdyn as fd
    from flexdyn import batch as fb

    chain = fd.Chain([fd.RigidLink(0.4, 0.5), fd.FlexibleLink(0.5, 0.2, 1.0, n_modes=1)],
                     payload=fd.Payload(0.1), hubs=[fd.Hub(inertia=0.02), fd.Hub(mass=0.2)])
    torque = fd.BangBang([0.2, 0.1], 0.05)
    y0 = fd.initial_state(chain, joint_angles=[0.1, -0.2])
    ts = jnp.linspace(0.0, 0.2, 5)

    def final_state(mass, y0, ts):
        c = eqx.tree_at(lambda c: c.payload.mass, chain, mass)
        return fd.simulate(c, y0, ts, torque, dt=1e-3).Q

    masses = jnp.linspace(0.05, 0.35, 7)
    sharded = fb.sweep(final_state, masses, y0, ts)
    plain = jax.vmap(lambda m: final_state(m, y0, ts))(masses)
    chains = jax.vmap(lambda m: eqx.tree_at(lambda c: c.payload.mass, chain, m))(masses)
    per_chain = fb.sweep(lambda c, y0, ts: fd.simulate(c, y0, ts, torque, dt=1e-3).Q, chains, y0, ts)
    placed, n = fb.shard_batch(masses)
    # sharded_vmap: batched and replicated arguments, a static (non-array) output
    sv, label = fb.sharded_vmap(lambda m, y0, ts: (final_state(m, y0, ts), "Q"), (0, None, None))(placed, y0, ts)
    print(json.dumps({
        "devices": len(jax.devices()),
        "n": n,
        "padded": int(placed.shape[0]),
        "shards": sorted(int(s.data.shape[0]) for s in placed.addressable_shards),
        "shape": list(sharded.shape),
        "max_diff": float(np.max(np.abs(np.asarray(sharded) - np.asarray(plain)))),
        "max_diff_chain": float(np.max(np.abs(np.asarray(per_chain) - np.asarray(plain)))),
        "spread": float(np.max(np.abs(np.asarray(plain[0]) - np.asarray(plain[-1])))),
        "max_diff_sharded_vmap": float(np.max(np.abs(np.asarray(sv)[:n] - np.asarray(plain)))),
        "sharded_vmap_shards": sorted(int(s.data.shape[0]) for s in sv.addressable_shards),
        "label": label,
    }))
    """
)


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_sweep_sharded_over_four_cpu_devices_equals_vmap():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", _SHARDED_SCRIPT], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices"] == 4
    assert (out["n"], out["padded"], out["shards"]) == (7, 8, [2, 2, 2, 2])
    assert out["shape"] == [7, 5, 3]
    assert out["spread"] > 1e-3  # the entries differ, so a mix-up of entries would show
    assert out["max_diff"] < 1e-12
    assert out["max_diff_chain"] < 1e-12
    assert out["max_diff_sharded_vmap"] < 1e-12 and out["sharded_vmap_shards"] == [2, 2, 2, 2]
    assert out["label"] == "Q"


def test_sweep_on_one_device_equals_vmap():
    chain = fd.rigs.rigid_pendulum()
    y0 = fd.initial_state(chain, joint_angles=[0.3])
    ts = jnp.linspace(0.0, 0.1, 3)

    def final_angle(damping, y0):
        c = eqx.tree_at(lambda c: c.joints[0].damping, chain, damping)
        return fd.simulate(c, y0, ts, dt=1e-3).Q[-1, 0]

    dampings = jnp.linspace(0.0, 0.05, 5)
    got = fb.sweep(final_angle, dampings, y0, devices=jax.devices()[:1])
    want = jax.vmap(lambda d: final_angle(d, y0))(dampings)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-14)
    assert float(jnp.ptp(want)) > 0


def test_pad_and_unpad_batch():
    tree = {"a": jnp.arange(5.0), "b": jnp.ones((5, 2)), "name": "static"}
    padded, n = fb.pad_batch(tree, 4)
    assert n == 5 and padded["a"].shape == (8,) and padded["b"].shape == (8, 2) and padded["name"] == "static"
    np.testing.assert_array_equal(np.asarray(padded["a"]), [0, 1, 2, 3, 4, 4, 4, 4])  # repeats the last entry
    back = fb.unpad_batch(padded, n)
    np.testing.assert_array_equal(np.asarray(back["a"]), np.arange(5.0))
    same, n = fb.pad_batch(tree, 5)
    assert same["a"] is tree["a"] and n == 5


def test_mismatched_batch_sizes_are_an_error():
    with pytest.raises(ValueError, match="leading"):
        fb.batch_size({"a": jnp.zeros(3), "b": jnp.zeros(4)})
    with pytest.raises(ValueError, match="scalar leaf"):
        fb.batch_size({"a": jnp.zeros(3), "b": jnp.zeros(())})
    # review: a list of Python floats said "got leading sizes []"
    with pytest.raises(ValueError, match=r"got no array at all \(\[0.1, 0.2, 0.3\]\).*jnp.asarray"):
        fb.sweep(lambda m: m, [0.1, 0.2, 0.3])


def test_an_invalid_chain_in_the_batch_is_named_with_its_entries():
    # Review: under vmap the assembly's check can only say "payload.mass must be finite and
    # >= 0"; a concrete batch is checked on the host first, naming the entries.
    base = fd.rigs.flexible_link_joint_arm()
    masses = jnp.asarray([0.1, -0.2, 0.1, jnp.nan])
    chains = jax.vmap(lambda m: eqx.tree_at(lambda c: c.payload.mass, base, m))(masses)
    with pytest.raises(
        ValueError, match=r"sweep: payload.mass expected finite and >= 0 .* entries 1 \(-0.2\), 3 \(nan\) of 4"
    ):
        fb.sweep(lambda c: fd.assemble(c).chain.payload.mass, chains)
    ratios = jax.vmap(lambda z: eqx.tree_at(lambda c: c.links[0].damping_ratio, base, z))(
        jnp.asarray([[0.01, 0.02], [0.01, -0.02]])
    )
    with pytest.raises(ValueError, match=r"link1.damping_ratio .* entry 1 \(\[ 0.01 -0.02\]\) of 2"):
        fb.sweep(lambda c: fd.assemble(c).chain.payload.mass, ratios)
    # valid batches pass, and shared (unbatched) parameters are not mistaken for a batch axis
    good = jax.vmap(lambda m: eqx.tree_at(lambda c: c.payload.mass, base, m))(jnp.asarray([0.1, 0.2]))
    out = fb.sweep(lambda c: fd.assemble(c).chain.payload.mass, good)
    np.testing.assert_allclose(np.asarray(out), [0.1, 0.2])


def test_a_check_failing_inside_fn_says_how_to_have_the_entry_named():
    """Chains built inside `fn` are checked under vmap, where the check cannot name the
    entry (review: only "payload.mass must be finite and >= 0" under Equinox's stack):
    sweep says what failed and how to have the entry named."""
    base = fd.rigs.flexible_link_joint_arm()

    def mass(m):
        return fd.assemble(eqx.tree_at(lambda c: c.payload.mass, base, m)).chain.payload.mass

    with pytest.raises(
        RuntimeError, match=r"sweep: an entry of the batch failed a check inside fn: payload.mass must be .*outside fn"
    ):
        fb.sweep(mass, jnp.asarray([0.1, -0.2]))
    np.testing.assert_allclose(np.asarray(fb.sweep(mass, jnp.asarray([0.1, 0.2]))), [0.1, 0.2])

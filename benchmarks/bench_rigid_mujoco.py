"""Benchmark: the rigid limit, batched rollouts vs MuJoCo's `mujoco.rollout`.

A rigid 2-link arm in the vertical plane (links 0.4 m / 1.0 kg and 0.3 m / 0.6 kg, uniform
rods, payload 0.2 kg, joint viscous damping 0.05 N m s), no torque, released from `--batch`
random joint angles and rates (seeded). Both integrate 1 s with RK4 at a fixed 1 ms step
and return the state at every step:

- MuJoCo (`mujoco.rollout.rollout`, the model built as `tests/oracles.py`'s
  `mujoco_planar_chain` builds it, `integrator="RK4"`), with one thread and with one
  thread per usable core;
- flexdyn: `fd.simulate(..., dt=1e-3)` vmapped over the initial states (via
  `flexdyn.batch.sweep`, all devices).

Steps/s = batch x 1,000 steps / warm time. Agreement: max abs difference of the joint
angles over all steps and entries (same model, same integrator: rounding only).

Usage: `python benchmarks/bench_rigid_mujoco.py [--batch 1024] [--repeats N] [--json out.json]`
"""

from __future__ import annotations

import argparse
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "tests"))  # oracles.py: the MuJoCo model builder

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import environment, median_time, publish, timed, usable_cores  # noqa: E402

import flexdyn as fd  # noqa: E402  (enables float64)
from flexdyn import batch as fb  # noqa: E402

DT, N_STEPS = 1e-3, 1000
LINKS = [dict(length=0.4, mass=1.0), dict(length=0.3, mass=0.6)]
PAYLOAD, DAMPING, GRAVITY = 0.2, 0.05, (0.0, -9.81)


def flexdyn_chain():
    return fd.Chain(
        [fd.RigidLink(lk["length"], lk["mass"]) for lk in LINKS],
        joints=[fd.RigidJoint(damping=DAMPING) for _ in LINKS],
        payload=fd.Payload(mass=PAYLOAD),
        gravity=GRAVITY,
    )


def mujoco_model():
    from oracles import mujoco_planar_chain

    links = [dict(lk, com=lk["length"] / 2, inertia=lk["mass"] * lk["length"] ** 2 / 12) for lk in LINKS]
    return mujoco_planar_chain(links, gravity=GRAVITY, payload_mass=PAYLOAD, joint_damping=[DAMPING] * len(LINKS))


COLUMNS = [
    ("run", "run", ""),
    ("cold_s", "cold [s]", ".2f"),
    ("warm_s", "warm [s]", ".3f"),
    ("steps_per_s", "steps/s", ".3g"),
    ("ratio", "warm / MuJoCo (1 thread)", ".2f"),
    ("speedup", "steps/s / MuJoCo (1 thread)", ".2f"),
    ("max_diff", "max |angle diff| vs MuJoCo", ".1e"),
]


def main(argv=None):
    import mujoco
    from mujoco import rollout

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=1024, help="number of rollouts")
    parser.add_argument("--repeats", type=int, default=5, help="warm runs per case (median)")
    parser.add_argument("--json", default=None, help="also write the results as JSON to this path")
    args = parser.parse_args(argv)
    env = environment()
    env["mujoco"] = mujoco.__version__
    rng = np.random.default_rng(7)
    q0 = rng.uniform(-np.pi, np.pi, size=(args.batch, 2))
    qd0 = rng.normal(0.0, 1.0, size=(args.batch, 2))

    model = mujoco_model()
    assert model.opt.timestep == DT
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(model, spec)
    data0 = mujoco.MjData(model)
    init = np.empty((args.batch, nstate))
    for k in range(args.batch):
        mujoco.mj_resetData(model, data0)
        data0.qpos[:], data0.qvel[:] = q0[k], qd0[k]
        mujoco.mj_getState(model, data0, init[k], spec)
    qpos_slice = slice(1, 3)  # FULLPHYSICS state: time, qpos, qvel, ...

    rows = []
    mj_ref = None
    for threads in sorted({1, usable_cores()}):
        datas = [mujoco.MjData(model) for _ in range(threads)]

        def call(datas=datas):
            state, _ = rollout.rollout(model, datas, init, nstep=N_STEPS)
            return state

        state, cold = timed(call)
        warm = median_time(call, args.repeats)
        mj_ref = state[:, :, qpos_slice] if mj_ref is None else mj_ref
        rows.append(
            dict(run=f"MuJoCo {mujoco.__version__} rollout, RK4, {threads} thread(s)", cold_s=cold, warm_s=warm)
        )

    chain = flexdyn_chain()
    ts = jnp.linspace(0.0, N_STEPS * DT, N_STEPS + 1)

    def one(y0):
        return fd.simulate(chain, y0, ts, dt=DT).Q[1:]

    y0s = jnp.asarray(np.concatenate([q0, qd0], axis=1))

    def ours():
        return jax.block_until_ready(fb.sweep(one, y0s))

    Q, cold = timed(ours)
    warm = median_time(ours, args.repeats)
    rows.append(
        dict(
            run=f"flexdyn fd.simulate RK4, vmapped ({len(jax.devices())} device(s))",
            cold_s=cold,
            warm_s=warm,
            max_diff=float(np.max(np.abs(np.asarray(Q) - mj_ref))),
        )
    )
    for r in rows:
        r["steps_per_s"] = args.batch * N_STEPS / r["warm_s"]
        r["speedup"] = r["steps_per_s"] / rows[0]["steps_per_s"]
        r["ratio"] = r["warm_s"] / rows[0]["warm_s"]

    print(f"bench_rigid_mujoco: rigid 2-link arm, vertical plane, {args.batch} rollouts x {N_STEPS} RK4 steps of 1 ms")
    publish(args.json, "rigid_mujoco", env, rows, COLUMNS, note=f"; MuJoCo {mujoco.__version__}", batch=args.batch)
    return rows


if __name__ == "__main__":
    main()

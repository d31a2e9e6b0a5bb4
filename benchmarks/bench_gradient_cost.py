"""Benchmark: the cost of derivatives through a simulation, as multiples of one forward solve.

Paper 004's arm (`fd.rigs.flexible_link_joint_arm()`, 8 coordinates), bang-bang 0.2 N m /
0.5 s on both joints, from rest, a `--duration` s log (default 10 s) sampled at 1 kHz. The
"measured" log is the simulation at the nominal parameters; the model is evaluated at
parameters 5 % off. Loss: mean squared difference of all coordinates over the log.

- forward: one solve and the loss;
- reverse: `jax.value_and_grad` of the loss w.r.t. 10 parameters (link1/2 EI and rho, joint1/2
  stiffness and rotor inertia, payload mass and inertia) through diffrax's recursive
  checkpointing adjoint (`fd.simulate`'s default), three ways: with `fd.simulate`'s default
  step budget (`max_steps=200,000`: the checkpoint schedule is planned for that many steps,
  so it recomputes more), with `max_steps` = 2x the steps the solve takes, and with a
  checkpoint at every step (`RecursiveCheckpointAdjoint(checkpoints=max_steps)`: no
  recomputation, most memory);
- forward mode: the Jacobian of the residual vector (10,001 samples x 8 coordinates) w.r.t. 4
  parameters (link1.EI, link2.EI, joint1.stiffness, payload.mass) by `jax.jacfwd` with
  `diffrax.ForwardMode()`, the way `identify` computes its Jacobians;

each with fixed-step RK4 at 1 ms (papers 002/004) and with adaptive Tsit5 (rtol 1e-6). With
RK4, also `fd.fixed_step.rk4_trajectory` (the same steps in a `lax.scan`, differentiated by
its discrete-adjoint rule): its forward solve and its `value_and_grad`. With Tsit5, also
`fd.tsit5_trajectory` (the same diffrax solve, differentiated by the discrete adjoint of the
steps it took): its forward solve and its `value_and_grad`. Warm times are
medians of `--repeats` rounds, each round calling every program once (round robin, so that
the machine's slow spells fall on all programs alike); ratios are to `fd.simulate`'s forward solve with the same solver,
and (last column) to the same integrator's own forward solve.
Memory: XLA's `memory_analysis()` of each compiled program (temporaries + outputs +
arguments; the reverse pass's checkpoints are in the temporaries).

Usage: `python benchmarks/bench_gradient_cost.py [--duration 10] [--repeats N] [--json out.json]`
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import environment, publish, round_robin, timed  # noqa: E402

import flexdyn as fd  # noqa: E402  (enables float64)

PARAMS_10 = (
    "link1.EI",
    "link2.EI",
    "link1.rho",
    "link2.rho",
    "joint1.stiffness",
    "joint2.stiffness",
    "joint1.rotor_inertia",
    "joint2.rotor_inertia",
    "payload.mass",
    "payload.inertia",
)
PARAMS_4 = ("link1.EI", "link2.EI", "joint1.stiffness", "payload.mass")
SOLVERS = {"RK4 dt = 1 ms": dict(dt=1e-3), "Tsit5 rtol 1e-6": dict(rtol=1e-6, atol=1e-8)}


def setup(duration: float):
    chain = fd.rigs.flexible_link_joint_arm()
    torque = fd.BangBang([0.2, 0.2], 0.5)
    y0 = fd.initial_state(chain, joint_angles=[0.0, 0.0])
    ts_np = np.linspace(0.0, duration, int(round(duration * 1000)) + 1)
    ts = jnp.asarray(ts_np)
    measured = fd.simulate(chain, y0, ts, torque, dt=1e-3).Q
    return chain, torque, y0, ts, ts_np, measured


def memory_mb(compiled) -> float | None:
    try:
        m = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend reports it
        return None
    if m is None:
        return None
    total = m.temp_size_in_bytes + m.output_size_in_bytes + m.argument_size_in_bytes - m.alias_size_in_bytes
    return total / 2**20


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=10.0, help="log length, s (1 kHz samples)")
    parser.add_argument("--repeats", type=int, default=3, help="warm runs per case (median)")
    parser.add_argument("--solvers", default=",".join(SOLVERS), help="comma-separated subset of: " + ", ".join(SOLVERS))
    parser.add_argument("--json", default=None, help="also write the results as JSON to this path")
    args = parser.parse_args(argv)
    env = environment()
    chain, torque, y0, ts, ts_np, measured = setup(args.duration)
    nominal10 = jnp.asarray([float(fd.get_parameter(chain, n)) for n in PARAMS_10]) * 1.05
    nominal4 = jnp.asarray([float(fd.get_parameter(chain, n)) for n in PARAMS_4]) * 1.05

    rows = []
    for solver_name in args.solvers.split(","):
        kw = SOLVERS[solver_name]
        # Steps this solve takes (sets the checkpoint budget of the variants below).
        probe = fd.with_parameters(chain, dict(zip(PARAMS_10, nominal10)))
        n_steps = int(fd.simulate(probe, y0, ts, torque, **kw).num_steps)

        def residuals(values, names, adjoint=None, max_steps=200_000, kw=kw):
            c = fd.with_parameters(chain, dict(zip(names, values)))
            Q = fd.simulate(c, y0, ts, torque, adjoint=adjoint, max_steps=max_steps, **kw).Q
            return (Q - measured).reshape(-1)

        def loss(values, **options):
            return jnp.mean(residuals(values, PARAMS_10, **options) ** 2)

        tight = 2 * n_steps
        every_step = diffrax.RecursiveCheckpointAdjoint(checkpoints=tight)
        programs = {
            "forward solve (loss)": (jax.jit(loss), nominal10),
            "value_and_grad, 10 params, default adjoint (max_steps 200,000)": (
                jax.jit(jax.value_and_grad(loss)),
                nominal10,
            ),
            f"value_and_grad, 10 params, max_steps = {tight} (2x the steps)": (
                jax.jit(jax.value_and_grad(lambda v: loss(v, max_steps=tight))),
                nominal10,
            ),
            f"value_and_grad, 10 params, checkpoint every step ({tight} slots)": (
                jax.jit(jax.value_and_grad(lambda v: loss(v, max_steps=tight, adjoint=every_step))),
                nominal10,
            ),
            "jacfwd of residuals, 4 params (diffrax.ForwardMode)": (
                jax.jit(jax.jacfwd(lambda v: residuals(v, PARAMS_4, diffrax.ForwardMode(), tight))),
                nominal4,
            ),
        }
        if "dt" in kw:

            def loss_adjoint(values, dt=kw["dt"]):
                c = fd.with_parameters(chain, dict(zip(PARAMS_10, values)))
                Q = fd.fixed_step.rk4_trajectory(c, y0, ts_np, torque, dt=dt).Q
                return jnp.mean((Q - measured) ** 2)

            programs["fixed_step.rk4_trajectory: forward solve (loss)"] = (jax.jit(loss_adjoint), nominal10)
            programs["fixed_step.rk4_trajectory: value_and_grad, 10 params (discrete adjoint)"] = (
                jax.jit(jax.value_and_grad(loss_adjoint)),
                nominal10,
            )
        else:

            def loss_tsit5(values, kw=kw):
                c = fd.with_parameters(chain, dict(zip(PARAMS_10, values)))
                Q = fd.tsit5_trajectory(c, y0, ts, torque, **kw).Q
                return jnp.mean((Q - measured) ** 2)

            programs["tsit5_trajectory: forward solve (loss)"] = (jax.jit(loss_tsit5), nominal10)
            programs["tsit5_trajectory: value_and_grad, 10 params (discrete adjoint)"] = (
                jax.jit(jax.value_and_grad(loss_tsit5)),
                nominal10,
            )
        compiled_programs = {}
        for name, (fn, x) in programs.items():
            compiled, lower_s = timed(lambda fn=fn, x=x: fn.lower(x).compile())
            jax.block_until_ready(compiled(x))  # the first call, untimed
            compiled_programs[name] = (compiled, x, lower_s)
            print(f"  {solver_name}: {name}: compile {lower_s:.1f} s", flush=True)
        samples = round_robin(
            {
                name: (lambda compiled=compiled, x=x: jax.block_until_ready(compiled(x)))
                for name, (compiled, x, _) in compiled_programs.items()
            },
            args.repeats,
        )
        forward_warm = own_forward = None
        for name, (compiled, x, lower_s) in compiled_programs.items():
            mem = memory_mb(compiled)
            warm = statistics.median(samples[name])
            if forward_warm is None:
                forward_warm = own_forward = warm
            if name.endswith("trajectory: forward solve (loss)"):
                own_forward = warm
            rows.append(
                dict(
                    run=f"{solver_name}: {name}",
                    compile_s=lower_s,
                    warm_s=warm,
                    min_s=min(samples[name]),
                    ratio=warm / forward_warm,
                    own_ratio=warm / own_forward,
                    memory_mb=mem,
                    steps=n_steps,
                )
            )
            print(f"  {rows[-1]['run']}: warm {warm:.3f} s (min {min(samples[name]):.3f} s), {mem} MiB", flush=True)

    print()
    print(f"bench_gradient_cost: paper 004 arm, {args.duration:g} s log at 1 kHz ({ts.shape[0]} samples)")
    publish(args.json, "gradient_cost", env, rows, COLUMNS, duration_s=args.duration)
    print()
    print("Targets: value_and_grad w.r.t. 10 params <= 4x a forward solve; jacfwd with 4 params <= 3x.")
    for r in rows:
        if "value_and_grad" in r["run"] or "jacfwd" in r["run"]:
            target = 3.0 if "jacfwd" in r["run"] else 4.0
            worst = max(r["ratio"], r["own_ratio"])
            verdict = "met" if worst <= target else f"missed by {worst / target:.2f}x"
            print(f"  {r['run']}: {r['ratio']:.2f}x / {r['own_ratio']:.2f}x (target {target:g}x): {verdict}")
    return rows


COLUMNS = [
    ("run", "run", ""),
    ("compile_s", "compile [s]", ".1f"),
    ("warm_s", "warm [s]", ".3f"),
    ("ratio", "warm / simulate's forward solve", ".2f"),
    ("own_ratio", "warm / own forward solve", ".2f"),
    ("memory_mb", "XLA memory [MiB]", ".1f"),
    ("steps", "solver steps", "d"),
]


if __name__ == "__main__":
    main()

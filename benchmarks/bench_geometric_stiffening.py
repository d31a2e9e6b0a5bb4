"""Benchmark: what geometric stiffening costs, side by side with the plain model.

Paper 004's arm (two flexible links with two modes each, elastic joints, payload; 8
coordinates), bang-bang 0.2 N m / 0.5 s on both joints, 0 -> 5 s, simulated with
`FlexibleLink(geometric_stiffening=False)` (the papers' model, the reference run) and
`True` on both links, each with RK4 at a fixed 1 ms and Tsit5 at rtol 1e-8 (`fd.simulate`,
jitted; the same input, state and tolerances). Cold = first call (tracing + compilation +
run), warm = median of `--repeats` calls. Ratio = warm time / the plain model's with the
same solver.

Usage: `python benchmarks/bench_geometric_stiffening.py [--repeats N] [--json out.json]`
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from _common import environment, median_time, publish, timed  # noqa: E402

import flexdyn as fd  # noqa: E402  (enables float64)

COLUMNS = [
    ("run", "run", ""),
    ("cold_s", "cold [s]", ".3f"),
    ("warm_s", "warm [s]", ".4f"),
    ("ratio", "warm / plain model", ".2f"),
    ("steps", "steps", "d"),
]
T_END, DT, RTOL = 5.0, 1e-3, 1e-8


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7, help="warm runs per case (median reported)")
    parser.add_argument("--json", default=None, help="also write the results as JSON to this path")
    args = parser.parse_args(argv)

    ts = jnp.linspace(0.0, T_END, 501)
    torque = fd.BangBang(jnp.array([0.2, 0.2]), 0.5)
    rows = []
    for label, kw in (("RK4, dt 1 ms", dict(dt=DT)), (f"Tsit5, rtol {RTOL:g}", dict(rtol=RTOL, atol=1e-2 * RTOL))):
        plain = None
        for stiffening in (False, True):
            chain = fd.rigs.flexible_link_joint_arm(geometric_stiffening=stiffening)
            y0 = fd.initial_state(chain, [0.0, 0.0])
            run = jax.jit(lambda c, y, kw=kw: fd.simulate(c, y, ts, torque, **kw))

            def call(run=run, chain=chain, y0=y0):
                traj = run(chain, y0)
                traj.Q.block_until_ready()
                return traj

            traj, cold = timed(call)
            warm = median_time(call, args.repeats)
            row = {
                "run": f"{label}, geometric_stiffening={stiffening}",
                "cold_s": cold,
                "warm_s": warm,
                "steps": int(traj.num_steps),
            }
            plain = plain or row
            row["ratio"] = warm / plain["warm_s"]
            rows.append(row)

    env = environment()
    print(f"bench_geometric_stiffening: paper 004 arm (8 coordinates), bang-bang 0.2 N m / 0.5 s, 0 -> {T_END:g} s")
    publish(args.json, "geometric_stiffening", env, rows, COLUMNS, repeats=args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

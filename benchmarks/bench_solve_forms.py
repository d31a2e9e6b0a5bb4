"""Benchmark: the two forms of the unrolled mass-matrix solve on this machine's CPU.

`flexdyn.smallsolve.spd_solve` divides by the Cholesky pivots and takes their square
roots; `spd_solve_rsqrt` takes one reciprocal square root per pivot and multiplies (the
form of the fused GPU kernel, `flexdyn.fused`, where a float64 division or square root is
a slow-path subroutine). This script times both inside the same program, paper 004's arm
(`fd.rigs.flexible_link_joint_arm`), `fixed_step.rk4_final` for 5 s at 1 ms, jitted, warm
calls round robin (`_common.round_robin`), and reports the final states' difference. It
says which form the CPU paths should keep; the GPU's side is `bench_gpu_sweep.py
--fused-configs 32x1,32x1:unrolled`.

    python benchmarks/bench_solve_forms.py [--repeats 7] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import jax  # noqa: E402
import numpy as np  # noqa: E402
from _common import environment, publish, round_robin, timed, warm_summary  # noqa: E402

import flexdyn as fd  # noqa: E402  (enables float64)
from flexdyn import fixed_step  # noqa: E402

T_END, DT = 5.0, 1e-3
COLUMNS = [
    ("run", "run", ""),
    ("cold_s", "cold [s]", ".2f"),
    ("warm_s", "warm [s]", ".4f"),
    ("min_s", "fastest [s]", ".4f"),
    ("ratio", "warm / unrolled", ".3f"),
    ("max_diff", "max |y - y_unrolled|", ".1e"),
]


def main(argv=None) -> list:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7, help="round-robin rounds of warm calls")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    chain = fd.rigs.flexible_link_joint_arm()
    y0 = fd.initial_state(chain, joint_angles=[0.3, -0.2])
    torque = fd.BangBang([0.5, 0.2], 0.4)
    calls, cold, final = {}, {}, {}
    for solve in ("unrolled", "rsqrt"):
        f = jax.jit(lambda c, y, solve=solve: fixed_step.rk4_final(c, y, 0.0, T_END, torque, dt=DT, solve=solve))
        final[solve], cold[solve] = timed(lambda f=f: jax.block_until_ready(f(chain, y0)))
        calls[solve] = lambda f=f: jax.block_until_ready(f(chain, y0))
    samples = round_robin(calls, args.repeats)
    rows = []
    for solve in calls:
        rows.append(dict(run=f"rk4_final, solve={solve!r}", cold_s=cold[solve], **warm_summary(samples[solve])))
        rows[-1]["max_diff"] = float(np.max(np.abs(np.asarray(final[solve]) - np.asarray(final["unrolled"]))))
    for r in rows:
        r["ratio"] = r["warm_s"] / rows[0]["warm_s"]
    env = environment()
    print(f"bench_solve_forms: paper 004 arm, RK4 {T_END} s at {DT * 1e3:g} ms, one state, CPU")
    publish(args.json, "solve_forms", env, rows, COLUMNS)
    return rows


if __name__ == "__main__":
    main()

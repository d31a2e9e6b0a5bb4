"""Where the fused GPU sweep's time goes (issue 6, the 4,096 x 5 s target).

`bench_gpu_sweep.py` times `flexdyn.fused.rk4_sweep_final` as a user calls it. This
script splits that call, on chains assembled beforehand:

- **kernel**: the compiled program that `rk4_sweep_final` dispatches, on the arguments
  it was given (since commit bc94d01: the gather of the varying scalars, the padding, the
  Pallas kernel and the finiteness check; before it, in the 2026-12-04 run
  `results/gpu_sweep_split_h200_2026-12-04.json`, the padding and the kernel alone), at two
  horizons: time = a + b x steps gives the per-step cost b and the fixed cost a;
- **prologue**: the whole call minus that program: the host work of the call (the batch
  assembled and flattened, its constant columns read, the program looked up);
- **occupancy**: the kernel at block sizes 32, 16, 8, 4 (trajectories per program, one warp
  each). At 4,096 trajectories and block 32 there is one warp per multiprocessor (132 on an
  H100/H200); smaller blocks give each multiprocessor several warps, each with fewer
  trajectories, which hides latency if the kernel is latency-bound and does not help if it
  is bound by issue or arithmetic;
- **size**: the kernel at 16,384 trajectories (4x the work; flat time means idle
  multiprocessors at 4,096).

Timing: wall clock around `jax.block_until_ready`, median of `--repeats` warm calls; SM
clock samples from `nvidia-smi` are written beside the JSON by the calling command.

Usage: `python benchmarks/gpu_sweep_split.py [--json out.json] [--budget-s 300]`.
Without a GPU it says so and exits 0 (`--interpret` runs it in Pallas's interpreter on
any backend, a smoke test at `--size 64`).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import environment, format_environment, median_time, publish, timed, write_json  # noqa: E402
from bench_gpu_sweep import DT, T_END, TORQUE, Y0, _assemble_batch, grid  # noqa: E402

from flexdyn import fused as fused_module  # noqa: E402


def prepared(chains, t_end: float, block: int, interpret: bool):
    """(runner, P, Y) of one `rk4_sweep_final` call, captured from the call itself (so the
    kernel is exactly the user's), and the whole call as a function."""
    captured = {}
    original = fused_module._runner

    def spy(*args, **kwargs):
        run = original(*args, **kwargs)

        def recording(P, Y):
            captured["args"] = (run, P, Y)
            return run(P, Y)

        return recording

    def call():
        return fused_module.rk4_sweep_final(
            chains, Y0, 0.0, t_end, TORQUE, dt=DT, backend="pallas", block=block, num_warps=1, interpret=interpret
        )

    fused_module._runner = spy
    try:
        out, cold = timed(lambda: jax.block_until_ready(call()))
    finally:
        fused_module._runner = original
    run, P, Y = captured["args"]
    return run, P, Y, call, cold, out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=4096)
    parser.add_argument("--big", type=int, default=16384, help="the size of the scaling run (0: skip)")
    parser.add_argument("--blocks", default="32,16,8,4")
    parser.add_argument("--short", type=float, default=1.0, help="the second horizon [s] (0: skip)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--budget-s", type=float, default=1e9)
    parser.add_argument("--interpret", action="store_true")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    start = time.perf_counter()
    env = environment()
    if not args.interpret:
        try:
            jax.devices("gpu")
        except RuntimeError as e:
            print(f"gpu_sweep_split: no GPU here ({e}); skipped")
            write_json(args.json, {"benchmark": "gpu_sweep_split", "environment": env, "columns": [], "results": []})
            return []
    print(f"gpu_sweep_split: paper 004 arm, on {jax.devices()[0].device_kind}")
    print(format_environment(env), flush=True)
    rows = []
    chains = {}
    reference = {}

    def batch(size):
        if size not in chains:
            chains[size] = jax.block_until_ready(_assemble_batch(jnp.asarray(grid(size))))
        return chains[size]

    def measure(label, size, t_end, block, whole=False):
        if time.perf_counter() - start > args.budget_s:
            print(f"  (budget) skipped {label}", flush=True)
            return None
        try:
            run, P, Y, call, cold, out = prepared(batch(size), t_end, block, args.interpret)
            kernel = median_time(lambda: jax.block_until_ready(run(P, Y)), args.repeats)
            total = median_time(lambda: jax.block_until_ready(call()), args.repeats) if whole else None
        except Exception as e:  # noqa: BLE001 - a benchmark reports and goes on
            print(f"  {label}: FAILED {type(e).__name__}: {str(e)[:300]}", flush=True)
            return None
        steps = int(round(t_end / DT))
        row = dict(
            run=label,
            size=size,
            block=block,
            t_end_s=t_end,
            steps=steps,
            cold_s=cold,
            kernel_s=kernel,
            whole_call_s=total,
            prologue_s=None if total is None else total - kernel,
            traj_per_s=size / kernel,
            finite=bool(np.all(np.isfinite(np.asarray(out)))),
        )
        if (size, t_end) in reference:  # the same trajectories at another block size
            row["max_diff_vs_block_32"] = float(np.max(np.abs(np.asarray(out) - reference[size, t_end])))
        else:
            reference[size, t_end] = np.asarray(out)
        rows.append(row)
        extra = "" if total is None else f", whole call {total:.4f} s (prologue {total - kernel:.4f} s)"
        print(f"  {label}: cold {cold:.1f} s, kernel {kernel:.4f} s{extra}", flush=True)
        return row

    n = args.size
    base = measure(f"block 32, {n}, {T_END} s", n, T_END, 32, whole=True)
    if args.short:
        short = measure(f"block 32, {n}, {args.short} s", n, args.short, 32)
        if base and short:
            b = (base["kernel_s"] - short["kernel_s"]) / (base["steps"] - short["steps"])
            a = base["kernel_s"] - b * base["steps"]
            base["kernel_us_per_step"], base["kernel_fixed_s"] = b * 1e6, a
            print(f"  kernel: {b * 1e6:.2f} us per step + {a * 1e3:.1f} ms fixed", flush=True)
    best = base
    for block in (int(x) for x in args.blocks.split(",")):
        if block == 32:
            continue
        row = measure(f"block {block}, {n}, {T_END} s", n, T_END, block)
        if row and row["finite"] and (best is None or row["kernel_s"] < best["kernel_s"]):
            best = row
    if best is not None and best["block"] != 32:
        measure(f"block {best['block']}, {n}, {T_END} s, whole call", n, T_END, best["block"], whole=True)
    if args.big:
        measure(f"block 32, {args.big}, {T_END} s", args.big, T_END, 32)
        if best is not None and best["block"] != 32:
            measure(f"block {best['block']}, {args.big}, {T_END} s", args.big, T_END, best["block"])
    columns = [
        ("run", "run", ""),
        ("cold_s", "cold [s]", ".1f"),
        ("kernel_s", "kernel [s]", ".4f"),
        ("whole_call_s", "whole call [s]", ".4f"),
        ("prologue_s", "prologue [s]", ".4f"),
        ("traj_per_s", "trajectories/s (kernel)", ".0f"),
        ("finite", "finite", ""),
        ("max_diff_vs_block_32", "max diff vs block 32", ".1e"),
    ]
    publish(args.json, "gpu_sweep_split", env, rows, columns, environment=False)
    return rows


if __name__ == "__main__":
    main()

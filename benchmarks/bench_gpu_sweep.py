"""Benchmark: payload sweeps of paper 004's arm on a GPU, and what limits them.

The issue-6 GPU target: 4,096 payloads x 5 s of `fd.rigs.flexible_link_joint_arm()` (two
flexible links with two modes each, two elastic joints: 8 coordinates, 16 states),
bang-bang 0.2 N m / 0.5 s on both joints, from rest, in at most 150 ms warm on one H100.
The batch is the payload-mass x hub-1-inertia grid of `bench_payload_sweep.py`.

Runs (each vmapped over the batch, jitted, timed warm = median of `--repeats` calls after
a first, compiling one):

- `diffrax RK4 1 ms`: `fd.simulate(..., dt=1e-3)`, the library's fixed-step path
  (diffrax's `diffeqsolve` with steps clipped onto the input's jumps);
- `diffrax Tsit5 rtol 1e-6`: `fd.simulate(..., rtol=1e-6, atol=1e-8)`, adaptive; under
  `vmap` the batch runs in lockstep, so it pays for its slowest member;
- `lean RK4 1 ms`: `flexdyn.fixed_step.rk4_final` (a `lax.fori_loop` of classical RK4
  steps between the input's jumps, no diffrax machinery), with the library's mass-matrix
  solve (`cho_factor`/`cho_solve`: a batched LAPACK/cuSOLVER call) or the unrolled
  Cholesky of `flexdyn.smallsolve` (elementwise over the batch, fusable), and with the loop
  body unrolled `--unroll` times.

The fused runs (`flexdyn.fused.rk4_sweep_final`, one Pallas kernel) are timed from the
parameter grid, as a user calls them: the chains are built and assembled (clamped-mass
mode shapes of both links) before the kernel runs. Two more rows split that time: the
build and assembly alone, and the best kernel configuration on chains assembled
beforehand. (Until 2026-11-26 the mode shapes' roots were found on the host, in a Python
loop over the links of the batch: 22.7 s for 4,096 arms on the 2-core development CPU.
The H200 timings of that day include it; now they are found over the whole batch at
once, in JAX on a GPU, 0.54 s on that CPU in vectorised NumPy.)

Also printed:

- accuracy: max abs error of Q(5 s) at the grid's two corners against Dopri8 at rtol 1e-12;
- the FLOPs of one right-hand-side evaluation (XLA's cost analysis of the jitted field for
  one state), hence the float64 FLOP floor of a sweep: size x steps x 4 x FLOPs / peak;
- the kernels XLA emits per loop iteration (instructions of the compiled while-loop body
  that launch work: fusions, custom calls, library GEMMs), and the time per step measured
  from two horizons, which together say whether the sweep is bound by launches or
  arithmetic;
- the same fixed-step run on the host CPU (all cores, JAX's CPU backend) for the GPU / CPU
  ratio.

Usage: `python benchmarks/bench_gpu_sweep.py [--sizes 1024,4096,65536] [--device gpu]
[--budget-s 480] [--json out.json]`. Without a GPU it says so and exits 0 (the CPU
sweeps are `bench_payload_sweep.py`).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import environment, format_environment, median_time, publish, timed, write_json  # noqa: E402

import flexdyn as fd  # noqa: E402  (enables float64)
from flexdyn import fixed_step  # noqa: E402
from flexdyn.fused import rk4_sweep_final  # noqa: E402
from flexdyn.simulation import as_input  # noqa: E402

T_END = 5.0
DT = 1e-3
RTOL, ATOL = 1e-6, 1e-8
# the same arm, input, grid and parameter substitution as the CPU sweep
from bench_payload_sweep import BASE, TORQUE, TS, Y0, arm, grid  # noqa: E402

N = BASE.n_dof
# Float64 peak of the H100/H200 SXM without tensor cores (vendor datasheet; the FP64
# tensor-core rate, 67 TFLOP/s, needs matrix products that a 16-state RHS does not have).
FP64_PEAK = 33.5e12


def diffrax_rk4(p):
    return fd.simulate(arm(p), Y0, TS, TORQUE, dt=DT).Q[-1]


def diffrax_tsit5(p):
    traj = fd.simulate(arm(p), Y0, TS, TORQUE, rtol=RTOL, atol=ATOL)
    return traj.Q[-1], traj.num_steps


def lean(solve: str, unroll: int, t_end: float = T_END):
    def run(p):
        y = fixed_step.rk4_final(arm(p), Y0, 0.0, t_end, TORQUE, dt=DT, solve=solve, unroll=unroll)
        return y[:N]

    return run


_build = jax.jit(jax.vmap(arm))


def fused(
    backend: str,
    block: int = 64,
    num_warps: int | None = None,
    t_end: float = T_END,
    interpret: bool = False,
    solve: str = "auto",
):
    """The batch in one call of `flexdyn.fused.rk4_sweep_final` (whole trajectories per
    kernel): timed from the parameter grid, chains built and assembled included."""

    def run(params):
        y = rk4_sweep_final(
            _build(params),
            Y0,
            0.0,
            t_end,
            TORQUE,
            dt=DT,
            backend=backend,
            block=block,
            num_warps=num_warps,
            interpret=interpret,
            solve=solve,
        )
        return y[:, :N]

    return run


_assemble_batch = jax.jit(jax.vmap(lambda p: fd.assemble(arm(p))))


def assembly(params):
    """The batch's chains built from the grid and assembled, as each fused run does first
    (mode shapes and shape integrals of both links)."""
    return jax.tree.leaves(eqx.filter(_assemble_batch(params), eqx.is_array))


def fused_assembled(block: int, warps: int | None, interpret: bool = False, solve: str = "auto"):
    """`fused(...)` on chains assembled beforehand (once per batch size, in the first,
    cold call): the kernel's own time, with the flattening of the assembled scalars."""
    done = {}

    def run(params):
        size = int(params.shape[0])
        if size not in done:
            done[size] = jax.block_until_ready(_assemble_batch(params))
        y = rk4_sweep_final(
            done[size],
            Y0,
            0.0,
            T_END,
            TORQUE,
            dt=DT,
            backend="pallas",
            block=block,
            num_warps=warps,
            interpret=interpret,
            solve=solve,
        )
        return y[:, :N]

    return run


def rigid_fused(interpret: bool = False):
    """A payload sweep of the rigid pendulum (`fd.rigs.rigid_pendulum`, 2 states) through
    the same fused kernel, bang-bang 0.02 N m / 0.5 s from 0.3 rad: final angle."""
    rigid = fd.rigs.rigid_pendulum()
    y0 = fd.initial_state(rigid, joint_angles=[0.3])
    torque = fd.BangBang([0.02], 0.5)
    build = jax.jit(jax.vmap(lambda p: eqx.tree_at(lambda c: c.payload.mass, rigid, p[0])))

    def run(params):
        y = rk4_sweep_final(build(params), y0, 0.0, T_END, torque, dt=DT, block=32, num_warps=1, interpret=interpret)
        return y[:, :1]

    return run


def fused_rhs_operations() -> int:
    """Scalar operations of one right-hand side in the fused kernel's program (the folded
    scalar program of `flexdyn.scalarize`, for the payload x hub-inertia sweep: what varies
    is read per trajectory, the rest folded)."""
    from flexdyn import fused as fz

    chains = _build(jnp.asarray(grid(16)))
    torque = as_input(TORQUE, BASE.n_links)
    _, first, same, _, asm = fz._assembled_scalars(chains, Y0, torque, 0.0, DT)
    columns = fz._columns(first, same)
    plan = fz._plan(asm, torque, 0.0, T_END, DT, Y0, columns, "rsqrt")
    rows = [jnp.zeros(4) for _ in range(plan.n_rows)]
    y = [jnp.zeros(4) for _ in range(plan.n_state)]
    jaxpr = jax.make_jaxpr(lambda r, t, y: plan.rhs(r, t, y))(rows, jnp.asarray(0.1), y)
    return len(jaxpr.jaxpr.eqns)


def reference(p):
    traj = fd.simulate(arm(p), Y0, TS, TORQUE, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-14, max_steps=10**6)
    return traj.Q[-1]


_ELEMENTWISE = {
    "add",
    "sub",
    "mul",
    "div",
    "neg",
    "max",
    "min",
    "abs",
    "sign",
    "sqrt",
    "rsqrt",
    "exp",
    "log",
    "sin",
    "cos",
    "tan",
    "tanh",
    "atan2",
    "pow",
    "integer_pow",
    "square",
    "select_n",
    "logistic",
    "log1p",
    "expm1",
    "erf",
    "asin",
    "acos",
    "atan",
    "sinh",
    "cosh",
    "rem",
    "floor",
    "ceil",
}


def jaxpr_flops(jaxpr) -> float:
    """Floating-point operations of a (closed) jaxpr, counted from its primitives: one per
    output element of an elementwise op, 2 m n k per `dot_general`, one per input element of
    a reduction, n^3 / 3 per Cholesky and n^2 per triangular solve column; nested jaxprs
    (jit, custom_jvp, scan bodies times their length) recursively."""
    total = 0.0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        out = sum(float(np.prod(v.aval.shape)) for v in eqn.outvars if hasattr(v.aval, "shape"))
        if name in _ELEMENTWISE:
            total += out
        elif name == "dot_general":
            (lc, _), (lb, _) = eqn.params["dimension_numbers"]
            k = float(np.prod([eqn.invars[0].aval.shape[d] for d in lc])) if lc else 1.0
            total += 2.0 * out * k
        elif name.startswith("reduce_") or name in ("cumsum",):
            total += float(np.prod(eqn.invars[0].aval.shape))
        elif name == "cholesky":
            n = eqn.invars[0].aval.shape[-1]
            total += float(np.prod(eqn.invars[0].aval.shape[:-2])) * n**3 / 3
        elif name == "triangular_solve":
            a, b = eqn.invars[0].aval.shape, eqn.invars[1].aval.shape
            total += float(np.prod(b)) * a[-1]
        length = eqn.params.get("length", 1) if name == "scan" else 1
        for sub in jax.core.subjaxprs(eqn.params) if hasattr(jax.core, "subjaxprs") else _subjaxprs(eqn.params):
            total += length * jaxpr_flops(sub)
    return total


def _subjaxprs(params):
    for v in params.values():
        vals = v if isinstance(v, (tuple, list)) else (v,)
        for x in vals:
            if hasattr(x, "jaxpr") and hasattr(x, "consts"):
                yield x.jaxpr
            elif hasattr(x, "eqns"):
                yield x


def rhs_flops(solve: str) -> dict:
    """FLOPs of one right-hand-side evaluation for one state: counted from the jaxpr
    (`jaxpr_flops`), and XLA's own cost analysis of the compiled CPU program (which counts
    what XLA emits, after simplification, and nothing inside library calls)."""
    field = fixed_step.vector_field(fd.assemble(BASE), TORQUE, solve=solve)
    counted = jaxpr_flops(jax.make_jaxpr(field)(0.1, Y0 + 1e-3).jaxpr)
    cpu = jax.devices("cpu")[0]
    compiled = jax.jit(field).lower(0.1, jax.device_put(Y0 + 1e-3, cpu)).compile()
    cost = compiled.cost_analysis()
    if isinstance(cost, list):
        cost = cost[0]
    return {"jaxpr": counted, "xla": float(cost.get("flops", float("nan")))}


_NOT_KERNELS = ("parameter", "get-tuple-element", "tuple", "constant", "bitcast")
_OPCODE = re.compile(r"=\s*(?:\([^=]*?\)|\S+)\s+([a-z][\w\-]*)\(")


def kernels_per_iteration(compiled_text: str) -> dict:
    """Instructions that launch device work in each while-loop body of an optimised HLO
    module: all but parameters, tuples, constants and bitcasts (on a GPU each remaining
    instruction is a fusion, a library call or a copy: one kernel launch, roughly)."""
    bodies, name, lines = {}, None, []
    for line in compiled_text.splitlines():
        head = re.match(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$", line)
        if head:
            name, lines = head.group(1), []
            continue
        if line.startswith("}") and name is not None:
            bodies[name] = lines
            name = None
            continue
        if name is not None:
            lines.append(line)
    body_names = set(re.findall(r"body=%?([\w.\-]+)", compiled_text))
    out = {}
    for b in body_names:
        ops = [m.group(1) for ln in bodies.get(b, []) if (m := _OPCODE.search(ln))]
        out[b] = sum(1 for op in ops if op not in _NOT_KERNELS)
    return out


COLUMNS = [
    ("run", "run", ""),
    ("device", "device", ""),
    ("size", "trajectories", "d"),
    ("cold_s", "cold [s]", ".1f"),
    ("warm_s", "warm [s]", ".4f"),
    ("traj_per_s", "trajectories/s", ".0f"),
    ("us_per_step", "us per step", ".1f"),
    ("steps", "steps (max)", "d"),
    ("error_Q", "max abs error of Q(5 s)", ".2e"),
    ("flop_fraction", "fraction of FP64 peak", ".2e"),
]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1024,4096,65536")
    parser.add_argument("--device", default="gpu", choices=("gpu", "cpu"))
    parser.add_argument("--main-size", type=int, default=4096, help="batch of the variant comparison (target: 4096)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--runs",
        default="fused,fused-rigid,fused-xla,lean,diffrax-rk4,tsit5",
        help="groups to run: fused (one Pallas kernel), fused-rigid (the same kernel on the rigid pendulum), "
        "fused-xla (its scalar program as XLA ops, on the device "
        "and on the host CPU), lean (rk4_final vmapped), "
        "diffrax-rk4, tsit5 (fd.simulate vmapped)",
    )
    parser.add_argument(
        "--fused-configs",
        default="32x1,32x1:unrolled,64x1,64x2",
        help="fused kernel: BLOCKxWARPS[:SOLVE], comma-separated (SOLVE: rk4_sweep_final's solve; default auto, "
        "rsqrt in the kernel: the mass-matrix solve without divisions; unrolled: with them)",
    )
    parser.add_argument("--tsit5-sizes", default=None, help="sizes of the adaptive runs (default: --sizes)")
    parser.add_argument("--interpret", action="store_true", help="fused kernel in Pallas's interpreter (smoke test)")
    parser.add_argument("--unroll", default="1,4", help="loop unroll factors tried for the lean RK4")
    parser.add_argument("--solves", default="unrolled,cho", help="mass-matrix solves tried for the lean RK4")
    parser.add_argument("--lean-sizes", default=None, help="further sizes for the best lean variant (default: --sizes)")
    parser.add_argument("--no-kernels", action="store_true", help="skip the HLO kernel count")
    parser.add_argument("--no-short", action="store_true", help="skip the 1 s horizon (per-step cost)")
    parser.add_argument("--cpu-size", type=int, default=256, help="entries of the CPU comparison run (0: skip)")
    parser.add_argument("--budget-s", type=float, default=1e9, help="skip runs that would start after this")
    parser.add_argument("--dump-hlo", default=None, help="write the compiled HLO of the lean variants to this folder")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    start = time.perf_counter()
    env = environment()
    try:
        devices = jax.devices(args.device)
    except RuntimeError as e:
        print(f"bench_gpu_sweep: no {args.device} backend here ({e}); skipped (CPU sweeps: bench_payload_sweep.py)")
        write_json(args.json, {"benchmark": "gpu_sweep", "environment": env, "columns": [], "results": []})
        return []
    dev = devices[0]
    print(f"bench_gpu_sweep: paper 004 arm, 0 -> {T_END} s, on {dev.device_kind} ({args.device})")
    print(format_environment(env), flush=True)
    sizes = [int(s) for s in args.sizes.split(",")]
    unrolls = [int(u) for u in args.unroll.split(",")]

    flops = {s: rhs_flops(s) for s in ("cho", "unrolled")}
    print(f"FLOPs per right-hand side (one state, XLA cost analysis): {flops}", flush=True)
    fused_ops = fused_rhs_operations()
    print(f"scalar operations per right-hand side in the fused kernel: {fused_ops}", flush=True)
    runs = set(args.runs.split(","))

    # Accuracy at the grid's two corners, once (CPU reference).
    sub = jnp.asarray(grid(64)[[0, 63]])  # the grid's corners, the same at every size
    ref_Q = np.asarray(jax.jit(jax.vmap(reference))(jax.device_put(sub, jax.devices("cpu")[0])))

    rows = []

    def over_budget():
        return time.perf_counter() - start > args.budget_s

    def bench(name, fn, size, device, steps, solve=None, extra=None, batched=False, check=True):
        if over_budget():
            print(f"  (budget) skipped {name} {size}", flush=True)
            return None
        params = jax.device_put(jnp.asarray(grid(size)), device)
        f = fn if batched else jax.jit(jax.vmap(fn))
        try:
            out, cold = timed(lambda: jax.block_until_ready(f(params)))
            warm = median_time(lambda: jax.block_until_ready(f(params)), args.repeats)
        except Exception as e:  # noqa: BLE001 - a benchmark reports and goes on
            print(f"  {name} {size}: FAILED {type(e).__name__}: {str(e)[:300]}", flush=True)
            return None
        idx = [0, size - 1]
        if isinstance(out, tuple):  # (Q, steps per entry): lockstep pays the max
            out, per_entry = out
            steps = int(np.max(np.asarray(per_entry)))
        err = None
        if check and "horizon" not in name and "RIGID" not in name:
            err = float(np.max(np.abs(np.asarray(out)[idx] - ref_Q)))
        row = dict(
            run=name,
            device=device.platform,
            size=size,
            cold_s=cold,
            warm_s=warm,
            traj_per_s=size / warm,
            steps=steps,
            us_per_step=warm / steps * 1e6 if steps else None,
            error_Q=err,
        )
        if solve is not None and steps:
            stages = 6 if "Tsit5" in name else 4  # right-hand sides per step
            per_rhs = fused_ops if solve == "fused" else flops[solve]["jaxpr"]
            floor = size * steps * stages * per_rhs / FP64_PEAK
            row["flop_floor_s"] = floor
            row["flop_fraction"] = floor / warm
        if extra:
            row.update(extra)
        rows.append(row)
        print(f"  {name}, {size} on {device.platform}: cold {cold:.2f} s, warm {warm:.4f} s", flush=True)
        return row

    n_fixed = int(round(T_END / DT))
    M = args.main_size
    # 0. Whole trajectories in one Pallas kernel: programs of `block` trajectories x warps.
    if "fused" in runs:
        fused_rows = []
        for cfg in args.fused_configs.split(","):
            cfg, _, solve = cfg.partition(":")
            block, warps = (int(x) for x in cfg.split("x"))
            solve = solve or "auto"
            name = f"fused RK4 1 ms, pallas, block {block} x {warps} warps, solve {solve}"
            fn = fused("pallas", block, warps, interpret=args.interpret, solve=solve)
            row = bench(name, fn, M, dev, n_fixed, "fused", batched=True)
            if row is not None:
                fused_rows.append((row, block, warps, solve))
        if fused_rows:
            row, block, warps, solve = min(fused_rows, key=lambda r: r[0]["warm_s"])
            short = bench(
                f"{row['run']}, 1 s horizon",
                fused("pallas", block, warps, 1.0, interpret=args.interpret, solve=solve),
                M,
                dev,
                1000,
                "fused",
                batched=True,
            )
            if short is not None:
                row["marginal_us_per_step"] = (row["warm_s"] - short["warm_s"]) / (n_fixed - 1000) * 1e6
            # The timed call builds and assembles the chains (mode shapes) before the kernel
            # runs: time that part alone, and the kernel on a batch assembled beforehand.
            bench(
                "build + assemble the batch (mode shapes), part of each fused run",
                assembly,
                M,
                dev,
                0,
                batched=True,
                check=False,
            )
            bench(
                f"{row['run']}, chains assembled beforehand (kernel + flattening)",
                fused_assembled(block, warps, interpret=args.interpret, solve=solve),
                M,
                dev,
                n_fixed,
                "fused",
                batched=True,
            )
            for size in sizes:
                if size != M:
                    fn = fused("pallas", block, warps, interpret=args.interpret, solve=solve)
                    bench(row["run"], fn, size, dev, n_fixed, "fused", batched=True)
    if "fused-rigid" in runs:  # the same kernel on a small chain: what it reaches without register pressure
        bench(
            "fused RK4 1 ms, pallas, block 32 x 1 warps: RIGID PENDULUM (174 operations per RHS)",
            rigid_fused(args.interpret),
            M,
            dev,
            n_fixed,
            None,
            batched=True,
        )
    if "fused-xla" in runs:
        bench("fused RK4 1 ms, xla (scalar program, fori_loop)", fused("xla"), M, dev, n_fixed, "fused", batched=True)
        if args.cpu_size:  # the same scalar program on this machine's CPU (all cores)
            cpu = jax.devices("cpu")[0]
            with jax.default_device(cpu):
                name = "fused RK4 1 ms, xla (scalar program, fori_loop)"
                bench(name, fused("xla"), args.cpu_size, cpu, n_fixed, "fused", batched=True)
    # 1. The lean fixed-step integrator: solve variants x unroll, at 4096.
    for solve in args.solves.split(",") if "lean" in runs else ():
        for u in unrolls:
            bench(f"lean RK4 1 ms, {solve} solve, unroll {u}", lean(solve, u), M, dev, n_fixed, solve)
    lean_rows = [r for r in rows if r["run"].startswith("lean") and r["size"] == M]
    best = min(lean_rows, key=lambda r: r["warm_s"]) if lean_rows else None
    # Kernels per loop iteration and per-step cost of the best lean variant.
    if best is not None:
        solve = "unrolled" if "unrolled" in best["run"] else "cho"
        u = int(best["run"].rsplit(" ", 1)[1])
        params = jax.device_put(jnp.asarray(grid(M)), dev)
        for s, uu in () if args.no_kernels else ((solve, u), ("cho", 1), ("unrolled", 1)):
            text = jax.jit(jax.vmap(lean(s, uu))).lower(params).compile().as_text()
            k = kernels_per_iteration(text)
            if args.dump_hlo:
                os.makedirs(args.dump_hlo, exist_ok=True)
                with open(os.path.join(args.dump_hlo, f"lean_{s}_unroll{uu}.hlo.txt"), "w") as fh:
                    fh.write(text)
            print(f"kernels per while-loop iteration (lean, {s}, unroll {uu}): {k}", flush=True)
            best.setdefault("kernels_per_iteration", {})[f"{s}_unroll{uu}"] = k
        # per-step cost from two horizons (1 s vs 5 s)
        short = (
            None
            if args.no_short
            else bench(
                f"lean RK4 1 ms, {solve} solve, unroll {u}, 1 s horizon",
                lean(solve, u, t_end=1.0),
                M,
                dev,
                1000,
                solve,
            )
        )
        if short is not None:
            per_step = (best["warm_s"] - short["warm_s"]) / (n_fixed - 1000)
            best["marginal_us_per_step"] = per_step * 1e6
            print(f"marginal cost per RK4 step at {M} (5 s vs 1 s horizons): {per_step * 1e6:.1f} us", flush=True)
        lean_sizes = sizes if args.lean_sizes is None else [int(x) for x in args.lean_sizes.split(",") if x]
        for size in lean_sizes:
            if size != M:
                bench(best["run"], lean(solve, u), size, dev, n_fixed, solve)
    # 2. diffrax through the library's simulate.
    for size in sizes if "diffrax-rk4" in runs else ():
        bench("diffrax RK4 1 ms (fd.simulate)", diffrax_rk4, size, dev, n_fixed, "cho")
    tsit5_sizes = sizes if args.tsit5_sizes is None else [int(x) for x in args.tsit5_sizes.split(",") if x]
    for size in tsit5_sizes if "tsit5" in runs else ():
        if over_budget():
            break
        bench(f"diffrax Tsit5 rtol {RTOL:g} (fd.simulate, lockstep)", diffrax_tsit5, size, dev, None, "cho")
    # 3. The same on this machine's CPU (all cores).
    if args.cpu_size and best is not None:
        cpu = jax.devices("cpu")[0]
        with jax.default_device(cpu):
            solve = "unrolled" if "unrolled" in best["run"] else "cho"
            u = int(best["run"].rsplit(" ", 1)[1])
            bench(best["run"], lean(solve, u), args.cpu_size, cpu, n_fixed, solve)
            bench("diffrax RK4 1 ms (fd.simulate)", diffrax_rk4, args.cpu_size, cpu, n_fixed, "cho")

    print()
    publish(args.json, "gpu_sweep", env, rows, COLUMNS, environment=False, rhs_flops=flops)
    print(f"\nFP64 peak assumed {FP64_PEAK / 1e12:.1f} TFLOP/s (vector, no tensor cores); FLOPs/RHS {flops}")
    return rows


if __name__ == "__main__":
    main()

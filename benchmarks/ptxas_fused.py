"""Static profile of the fused GPU kernel, without a GPU: registers, spills, instructions.

`flexdyn.fused.rk4_sweep_final` runs a whole sweep in one Pallas (Triton) kernel on a GPU.
Its register use and spills decide how fast it runs, and they are known before it runs:
JAX lowers the kernel for CUDA on any machine (`lower(lowering_platforms=("cuda",))`),
Pallas prints the kernel's Triton IR (`pallas_call(..., debug=True)`), the `triton`
package compiles that IR to PTX and a cubin for an H100/H200 (`sm_90a`) with no device
present, and `ptxas -v` reports what the GPU would get.

Steps, for paper 004's arm (the payload x hub-inertia sweep of `bench_gpu_sweep.py`) and
the rigid pendulum (the small chain that meets the GPU target):

1. In this interpreter (flexdyn's environment): the kernel's Triton IR, written to
   `--out/<case>.ttir`.
2. In `--triton-python` (any Python with `pip install triton`; not a flexdyn dependency,
   and it need not share flexdyn's environment): PTX and cubin, compiled as JAX compiles
   Pallas kernels (`num_warps`, `num_stages=1`), with PTX ISA `--ptx-version` so that
   Triton's bundled `ptxas` accepts it.
3. That `ptxas -v` on the PTX: registers per thread, stack frame, spill stores and loads;
   `cuobjdump -sass` on the cubin: the instruction mix (double-precision arithmetic,
   local-memory loads and stores `LDL`/`STL`, calls).

The Triton that XLA embeds is not the `triton` package, and its passes and versions can
differ: the numbers are an estimate of what the GPU runs, to be checked with a profiler
(`ncu`) where a GPU is at hand.

Usage: `python benchmarks/ptxas_fused.py [--triton-python /path/to/python] [--cases arm,rigid]
[--block 32] [--warps 1] [--out DIR] [--json out.json]`
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import io
import json
import os
import re
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import write_json  # noqa: E402

import flexdyn as fd  # noqa: E402  (enables float64)
from flexdyn import fused  # noqa: E402
from flexdyn.simulation import as_input  # noqa: E402

T_END, DT = 5.0, 1e-3

_COMPILE = r"""
import json, sys, triton
from triton.backends.compiler import GPUTarget
src, warps, ptx_version = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
kernel = triton.compile(src, target=GPUTarget("cuda", 90, 32),
                        options={"num_warps": warps, "num_stages": 1, "ptx_version": ptx_version})
open(src[:-5] + ".ptx", "w").write(kernel.asm["ptx"])
open(src[:-5] + ".cubin", "wb").write(kernel.asm["cubin"])
import triton.backends.nvidia as nv, os
print(json.dumps({"triton": triton.__version__, "bin": os.path.join(os.path.dirname(nv.__file__), "bin")}))
"""


def batch(case: str):
    """The swept chains, the initial state and the input of one case (64 entries: the
    kernel's code does not depend on the batch size)."""
    from bench_payload_sweep import BASE, TORQUE, Y0, arm, grid

    if case == "arm":
        return jax.vmap(arm)(jnp.asarray(grid(64))), Y0, as_input(TORQUE, BASE.n_links)
    rigid = fd.rigs.rigid_pendulum()
    chains = jax.vmap(lambda m: eqx.tree_at(lambda c: c.payload.mass, rigid, m))(jnp.linspace(0.01, 0.2, 64))
    return chains, jnp.array([0.3, 0.0]), fd.ZeroTorque(1)


def triton_ir(case: str, block: int, warps: int) -> tuple[str, int]:
    """The Triton IR of the fused kernel, as Pallas prints it with `debug=True`, with the
    location annotations removed so that a standalone MLIR parser reads it; and the number
    of pieces between input jumps (each piece's step loop has its own copy of the
    right-hand side in the kernel)."""
    from jax.experimental import pallas as pl

    chains, y0, torque = batch(case)
    flat, first, same, _, asm = fused._assembled_scalars(chains, y0, torque, 0.0, DT)
    columns = fused._columns(first, same)
    plan = fused._plan(asm, torque, 0.0, T_END, DT, y0, columns, "rsqrt")
    original = pl.pallas_call
    pl.pallas_call = functools.partial(original, debug=True)
    try:
        run = fused._pallas_runner(plan, block, warps, False)
        varying = np.array([j for j, (kind, _) in enumerate(columns) if kind == "row"], dtype=int)
        P = flat[:, varying].T
        Y = jnp.broadcast_to(y0, (P.shape[1], y0.shape[0])).T
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            run.trace(P, Y).lower(lowering_platforms=("cuda",))
    finally:
        pl.pallas_call = original
    text = printed.getvalue()
    start = text.find("module @kernel")
    if start < 0:
        raise RuntimeError("ptxas_fused: Pallas printed no Triton module (did its debug output change?)")
    lines = []
    for line in text[start:].splitlines():
        if line.startswith("#loc"):
            continue
        line = re.sub(r' "[^"]*"\(#loc\d*\)', "", line)
        line = re.sub(r" loc\([^()]*(\([^()]*\))?[^()]*\)", "", line)
        line = re.sub(r" (\[unknown\]|#loc\d*)", "", line)
        lines.append(line)
        if line == "}":  # the module's closing brace
            break
    return "\n".join(lines) + "\n", len(plan.segments)


def sass_mix(sass: str) -> dict:
    """Counts of SASS opcodes (predicates and modifiers dropped)."""
    counts: dict[str, int] = {}
    for m in re.finditer(r"^\s+/\*[0-9a-f]{4,6}\*/\s+(@!?U?P\w+\s+)?([A-Z][A-Z0-9]*)", sass, re.M):
        counts[m.group(2)] = counts.get(m.group(2), 0) + 1
    return counts


def profile(case: str, args) -> dict:
    os.makedirs(args.out, exist_ok=True)
    ttir = os.path.join(args.out, f"{case}.ttir")
    text, pieces = triton_ir(case, args.block, args.warps)
    with open(ttir, "w") as f:
        f.write(text)
    try:
        done = subprocess.run(
            [args.triton_python, "-c", _COMPILE, ttir, str(args.warps), str(args.ptx_version)],
            capture_output=True,
            text=True,
            env={**os.environ, "TRITON_DEFAULT_FP_FUSION": "1"},
        )
    except FileNotFoundError as e:
        raise SystemExit(f"ptxas_fused: --triton-python {args.triton_python!r}: no such interpreter") from e
    if done.returncode:
        raise RuntimeError(f"ptxas_fused: triton could not compile {ttir}:\n{done.stderr[-2000:]}")
    info = json.loads(done.stdout.strip().splitlines()[-1])
    ptx, cubin = ttir[:-5] + ".ptx", ttir[:-5] + ".cubin"
    ptxas = os.path.join(info["bin"], "ptxas")
    report = subprocess.run(
        [ptxas, "-v", "--gpu-name", "sm_90a", ptx, "-o", os.devnull], capture_output=True, text=True, check=True
    ).stderr
    kernel = report[report.index("Function properties for kernel") :]

    def number(pattern):
        return int(re.search(pattern, kernel).group(1))

    sass = subprocess.run(
        [os.path.join(info["bin"], "cuobjdump"), "-sass", cubin], capture_output=True, text=True, check=True
    ).stdout
    mix = sass_mix(sass)
    return dict(
        case=case,
        triton=info["triton"],
        block=args.block,
        warps=args.warps,
        rhs_copies=pieces,
        registers=number(r"Used (\d+) registers"),
        stack_bytes=number(r"(\d+) bytes stack frame"),
        spill_store_bytes=number(r"(\d+) bytes spill stores"),
        spill_load_bytes=number(r"(\d+) bytes spill loads"),
        sass_instructions=sum(mix.values()),
        fp64=sum(mix.get(k, 0) for k in ("DFMA", "DMUL", "DADD")),
        local_loads=mix.get("LDL", 0),
        local_stores=mix.get("STL", 0),
        calls=mix.get("CALL", 0),
        mix=dict(sorted(mix.items(), key=lambda kv: -kv[1])[:16]),
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--triton-python", default=sys.executable, help="a Python with the triton package")
    parser.add_argument("--cases", default="arm,rigid", help="arm (paper 004's arm), rigid (the rigid pendulum)")
    parser.add_argument("--block", type=int, default=32, help="trajectories per program (rk4_sweep_final's default)")
    parser.add_argument("--warps", type=int, default=1, help="warps per program (rk4_sweep_final's default)")
    parser.add_argument("--ptx-version", type=int, default=88, help="PTX ISA for Triton's bundled ptxas (88: 8.8)")
    parser.add_argument("--out", default=None, help="folder for the .ttir, .ptx and .cubin files (default: a new temp)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    args.out = args.out or tempfile.mkdtemp(prefix="ptxas_fused_")
    print(f"ptxas_fused: .ttir, .ptx and .cubin files in {args.out}", flush=True)
    rows = []
    for case in args.cases.split(","):
        row = profile(case.strip(), args)
        rows.append(row)
        print(
            f"{row['case']}: {row['registers']} registers/thread, stack {row['stack_bytes']} B, spills "
            f"{row['spill_store_bytes']} B stored / {row['spill_load_bytes']} B loaded (static), "
            f"{row['sass_instructions']} SASS instructions ({row['fp64']} FP64 arithmetic, "
            f"{row['local_loads']} LDL, {row['local_stores']} STL, {row['calls']} CALL) for "
            f"{row['rhs_copies']} copies of the right-hand side (one per piece between input jumps)",
            flush=True,
        )
    write_json(args.json, {"benchmark": "ptxas_fused", "results": rows})
    return rows


if __name__ == "__main__":
    main()

"""Benchmark: O(n) recursive DeNOC forward dynamics vs the dense solves, chains of 2 to 10 links.

Three ways to get the accelerations `Q_ddot(Q, Q_dot, tau)` of the same chain:

- `recursive`: `flexdyn.denoc.denoc_forward_dynamics_recursive` (articulated-body recursion on
  the DeNOC blocks, O(n));
- `denoc dense`: `flexdyn.denoc.denoc_accelerations` (M = N^T M_b N, h, F; Cholesky, O(n^3));
- `core dense`: `fd.accelerations` (Lagrange by AD of the kinetic energy; Cholesky).

Chains: `rigid` (k uniform rigid links 0.3 m, 0.5 kg, rigid joints) and `flexible` (k flexible
links 0.3 m, rho 1 kg/m, EI 2 N m^2, `--modes` modes each, rigid joints), hubs 0.1 kg /
1e-3 kg m^2, payload 0.1 kg, vertical plane. Each function is jitted and vmapped over a batch of
`--batch` random states; cold = first call (compilation included), warm = median of `--repeats`
further calls, each ending in `block_until_ready`. `ratio` = warm / warm of `core dense` for
the same chain. `error_Q` = max |Q_ddot - Q_ddot_core| / max |Q_ddot_core| over the batch (the
accelerations, not a trajectory).

Usage: `python benchmarks/bench_denoc_recursive.py [--sizes 2,4,6,8,10] [--batch 256]
[--repeats 5] [--modes 2] [--families rigid,flexible] [--json out.json]`
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import environment, median_time, publish, timed  # noqa: E402

import flexdyn as fd  # noqa: E402  (enables float64)
from flexdyn import denoc as dn  # noqa: E402

COLUMNS = [
    ("run", "run", ""),
    ("n_links", "links", "d"),
    ("n_dof", "dof", "d"),
    ("cold_s", "cold [s]", ".2f"),
    ("warm_s", "warm [s]", ".5f"),
    ("per_state_us", "warm per state [us]", ".2f"),
    ("ratio", "warm / core dense", ".2f"),
    ("error_Q", "max rel. diff of Q_ddot", ".1e"),
]

METHODS = {
    "recursive": dn.denoc_forward_dynamics_recursive,
    "denoc dense": dn.denoc_accelerations,
    "core dense": fd.accelerations,
}


def make_chain(family: str, k: int, n_modes: int) -> fd.Chain:
    if family == "rigid":
        links = [fd.RigidLink(0.3, 0.5) for _ in range(k)]
    else:
        links = [fd.FlexibleLink(0.3, 1.0, 2.0, n_modes=n_modes, damping_ratio=0.01) for _ in range(k)]
    return fd.Chain(
        links,
        joints=[fd.RigidJoint(damping=0.01) for _ in range(k)],
        hubs=[fd.Hub(mass=0.1, inertia=1e-3) for _ in range(k)],
        payload=fd.Payload(0.1),
        gravity=(0.0, -9.81),
    )


def states(chain: fd.Chain, batch: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    lay = chain.layout
    Q = rng.uniform(-np.pi, np.pi, (batch, lay.n_dof))
    Qd = rng.normal(0.0, 1.0, (batch, lay.n_dof))
    for idx in lay.modal:
        for j in idx:
            Q[:, j] = rng.normal(0.0, 0.01, batch)
            Qd[:, j] = rng.normal(0.0, 0.1, batch)
    tau = rng.normal(0.0, 0.5, (batch, chain.n_links))
    return jnp.asarray(Q), jnp.asarray(Qd), jnp.asarray(tau)


def make_fn(method):
    @eqx.filter_jit
    def f(asm, Q, Qd, tau):
        return jax.vmap(lambda a, b, c: method(asm, a, b, c))(Q, Qd, tau)

    return f


def run(families, sizes, batch, repeats, n_modes):
    rows = []
    for family in families:
        for k in sizes:
            chain = make_chain(family, k, n_modes)
            asm = fd.assemble(chain)
            Q, Qd, tau = states(chain, batch)
            results, per = {}, {}
            for name, method in METHODS.items():
                f = make_fn(method)
                out, cold = timed(lambda: jax.block_until_ready(f(asm, Q, Qd, tau)))
                warm = median_time(lambda: jax.block_until_ready(f(asm, Q, Qd, tau)), repeats)
                results[name] = np.asarray(out)
                per[name] = (cold, warm)
            ref = results["core dense"]
            for name in METHODS:
                cold, warm = per[name]
                rows.append(
                    dict(
                        run=f"{family} {k} links: {name}",
                        family=family,
                        method=name,
                        n_links=k,
                        n_dof=chain.n_dof,
                        cold_s=cold,
                        warm_s=warm,
                        per_state_us=1e6 * warm / batch,
                        ratio=warm / per["core dense"][1],
                        error_Q=float(np.max(np.abs(results[name] - ref)) / np.max(np.abs(ref))),
                    )
                )
            print(
                f"{family:>8} {k:2d} links ({chain.n_dof:2d} dof): "
                + ", ".join(f"{n} {1e6 * per[n][1] / batch:.2f} us/state (cold {per[n][0]:.1f} s)" for n in METHODS),
                flush=True,
            )
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="warm runs per case (median reported)")
    parser.add_argument("--json", default=None, help="also write the results as JSON to this path")
    parser.add_argument("--sizes", default="2,3,4,5,6,7,8,9,10", help="numbers of links, comma-separated")
    parser.add_argument("--families", default="rigid,flexible")
    parser.add_argument("--batch", type=int, default=256, help="states per vmapped call")
    parser.add_argument("--modes", type=int, default=2, help="assumed modes per flexible link")
    args = parser.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    families = args.families.split(",")
    env = environment()
    rows = run(families, sizes, args.batch, args.repeats, args.modes)
    print()
    print(
        f"bench_denoc_recursive: forward dynamics, batch {args.batch} states (vmapped, jitted), "
        f"{args.modes} modes per flexible link"
    )
    publish(args.json, "denoc_recursive", env, rows, COLUMNS, args=vars(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())

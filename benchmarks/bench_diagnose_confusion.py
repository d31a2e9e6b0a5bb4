"""Confusion matrix of `identify diagnose` over hidden effects (not a timing benchmark: an
accuracy one, run like the others).

For each catalogue entry that applies to the test rigs (`tests/diagnose_cases.py`:
paper 000's rigid pendulum, paper 002's flexible link on its hub) and for null logs,
`--seeds` seeded trials hide the effect with a random magnitude; the table counts what
`diagnose` named first (or "none"). Prints the matrix, the recovery rate (truth inside
the 95 % interval) and the held-out gains.

    python benchmarks/bench_diagnose_confusion.py --seeds 5 [--only coulomb_friction,...] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
sys.path.insert(0, HERE)

from _common import environment, format_environment  # noqa: E402
from diagnose_cases import ARM_ENTRIES, PENDULUM_ENTRIES, hidden  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--only", default=None)
    parser.add_argument("--json", default=None)
    parser.add_argument("--repeats", type=int, default=None, help="ignored (run_all passes it)")
    args = parser.parse_args(argv)
    entries = list(PENDULUM_ENTRIES + ARM_ENTRIES) + ["null_pendulum", "null_arm"]
    if args.only:
        entries = [e for e in entries if e in args.only.split(",")]
    print(format_environment(environment()))
    rows, matrix = [], {}
    for name in entries:
        for seed in range(args.seeds):
            run, truth, param = hidden(name, 500 + seed)
            start = time.perf_counter()
            diag = run()
            wall = time.perf_counter() - start
            first = diag.named[0] if diag.named else "none"
            covered = None
            if param and diag.causes and param in diag.causes[0].parameters:
                lo, hi = diag.causes[0].parameters[param]["ci95"]
                covered = bool(lo <= truth <= hi)
            matrix.setdefault(name, {}).setdefault(first, 0)
            matrix[name][first] += 1
            rows.append(
                {
                    "hidden": name,
                    "seed": seed,
                    "named": diag.named,
                    "gain_total": diag.held_out["gain_total"],
                    "truth_in_ci": covered,
                    "wall_s": wall,
                }
            )
            print(
                f"{name:<20} seed {seed}: named {diag.named}, gain {diag.held_out['gain_total']:.2f}x, "
                f"truth in CI: {covered}, {wall:.0f} s",
                flush=True,
            )
    columns = sorted({k for v in matrix.values() for k in v})
    print()
    corner = "hidden / named"
    print(f"{corner:<20} " + " ".join(f"{c[:12]:>12}" for c in columns))
    for name in entries:
        print(f"{name:<20} " + " ".join(f"{matrix.get(name, {}).get(c, 0):>12d}" for c in columns))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"results": rows, "matrix": matrix, "columns": ["hidden", "seed", "named", "gain_total"]}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())

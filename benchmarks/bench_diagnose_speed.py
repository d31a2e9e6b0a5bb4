"""How long `identify fit` / `identify diagnose` take cold, and where the time goes.

Each job runs in a fresh process (as a user's command does), for this checkout and, with
`--base REV`, for an older commit's tree (a `git worktree`), alternating round by round so
that a slow spell of the machine falls on both alike. Per run it records the wall time,
the CPU time of the process, and from `jax.monitoring` the number of programs XLA
compiled and the seconds spent tracing (jaxpr), lowering and compiling them; the rest is
running. With `--cache`, each job also runs twice more with JAX's persistent compilation
cache in a fresh folder: the first fills it, the second is the "second process" a user
gets on their next log.

Jobs:
- `main`: the README's main job, `identify diagnose` on
  `identify/examples/pendulum_friction/experiment.toml`;
- `fit-<example>`: `identify fit` of each shipped example given in `--fit-examples`;
- with `--full`: `identify diagnose` of `identify/examples/real_double_pendulum` (about an
  hour today).

Usage: `python benchmarks/bench_diagnose_speed.py [--base REV] [--rounds 1] [--cache]
[--fit-examples pendulum_drops,spinning_link] [--skip-main] [--full] [--json out.json]`
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, publish  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = Path("identify/examples")

# Runs inside the measured process: count and time compilations with `jax.monitoring`,
# then run the command line as `identify` would, and write the tallies as JSON.
HOOK = r"""
import json, resource, sys, time
import jax
from jax._src import dispatch
tally = {"programs": 0, "compile_s": 0.0, "trace_s": 0.0, "lower_s": 0.0}
names = {dispatch.BACKEND_COMPILE_EVENT: "compile_s", dispatch.JAXPR_TRACE_EVENT: "trace_s",
         dispatch.JAXPR_TO_MLIR_MODULE_EVENT: "lower_s"}
def listen(event, seconds, **kw):
    key = names.get(event)
    if key:
        tally[key] += seconds
        tally["programs"] += key == "compile_s"
jax.monitoring.register_event_duration_secs_listener(listen)
from identify.cli import main
try:
    status = main(sys.argv[2:])
except SystemExit as e:
    status = e.code if isinstance(e.code, int) else 1
usage = resource.getrusage(resource.RUSAGE_SELF)
tally.update(status=status, cpu_s=usage.ru_utime + usage.ru_stime)
open(sys.argv[1], "w").write(json.dumps(tally))
"""


def jobs(args) -> dict[str, list[str]]:
    """Job name -> `identify` arguments (the output folder appended per run)."""
    out = {} if args.skip_main else {"main": ["diagnose", str(EXAMPLES / "pendulum_friction" / "experiment.toml")]}
    for name in filter(None, args.fit_examples.split(",")):
        out[f"fit-{name}"] = ["fit", str(EXAMPLES / name / "experiment.toml")]
    if args.full:
        out["real_double_pendulum"] = ["diagnose", str(EXAMPLES / "real_double_pendulum" / "experiment.toml")]
    return out


def run_once(tree: Path, argv: list[str], workdir: Path, cache: Path | None = None) -> dict:
    """One fresh process of `identify ARGV` from `tree`: wall, CPU and compile tallies."""
    import time

    tallies = workdir / "tally.json"
    env = {**os.environ, "PYTHONPATH": str(tree)}
    if cache is not None:
        env.update(
            JAX_COMPILATION_CACHE_DIR=str(cache),
            JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
            JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="-1",
        )
    out = workdir / "out"
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", HOOK, str(tallies), *argv, "--out", str(out)],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - start
    if not tallies.exists():
        raise RuntimeError(f"identify {' '.join(argv)} in {tree} failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    row = json.loads(tallies.read_text())
    row["wall_s"] = wall
    row["run_s"] = wall - row["compile_s"] - row["trace_s"] - row["lower_s"]
    return row


def _trees(base: str | None, scratch: Path) -> dict[str, Path]:
    trees = {"this": ROOT}
    if base:
        where = scratch / f"base-{base}"
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(where), base], check=True, capture_output=True
        )
        trees[base] = where
    return trees


def measure(args) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-diagnose-") as tmp:
        scratch = Path(tmp)
        trees = _trees(args.base, scratch)
        try:
            runs: dict[tuple[str, str, str], list[dict]] = {}
            for r in range(args.rounds):
                for job, argv in jobs(args).items():
                    for label, tree in trees.items():
                        kinds = [("cold", None)]
                        if args.cache:
                            cache = scratch / f"cache-{label}-{job}-{r}"
                            kinds += [("cache fill", cache), ("second process", cache)]
                        for kind, cache in kinds:
                            work = scratch / f"{label}-{job}-{kind.replace(' ', '_')}-{r}"
                            work.mkdir()
                            row = run_once(tree, argv, work, cache)
                            print(
                                f"round {r + 1} {job} [{label}] {kind}: {row['wall_s']:.1f} s wall, "
                                f"{row['programs']} programs",
                                flush=True,
                            )
                            runs.setdefault((job, label, kind), []).append(row)
        finally:
            for label, tree in trees.items():
                if tree != ROOT:
                    subprocess.run(
                        ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], capture_output=True
                    )
    for (job, label, kind), found in runs.items():
        med = {
            k: statistics.median(float(f[k]) for f in found)
            for k in ("wall_s", "cpu_s", "programs", "trace_s", "lower_s", "compile_s", "run_s")
        }
        rows.append(
            {"job": job, "tree": label, "kind": kind, "rounds": len(found), "status": found[-1]["status"], **med}
        )
    base_wall = {(r["job"], r["kind"]): r["wall_s"] for r in rows if r["tree"] == args.base}
    for r in rows:
        old = base_wall.get((r["job"], r["kind"]))
        r["new_over_old"] = r["wall_s"] / old if old and r["tree"] == "this" else None
    return rows


COLUMNS = [
    ("job", "job", "s"),
    ("tree", "tree", "s"),
    ("kind", "run", "s"),
    ("wall_s", "wall [s]", ".1f"),
    ("cpu_s", "CPU [s]", ".1f"),
    ("programs", "programs", ".0f"),
    ("trace_s", "trace [s]", ".1f"),
    ("compile_s", "XLA [s]", ".1f"),
    ("run_s", "rest [s]", ".1f"),
    ("new_over_old", "this / base", ".2f"),
    ("status", "exit", "d"),
]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", default=None, help="an older commit to run beside this checkout")
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--cache", action="store_true", help="also: persistent compilation cache, fill and second process")
    p.add_argument("--fit-examples", default="", help="comma-separated shipped examples to `identify fit`")
    p.add_argument("--skip-main", action="store_true", help="leave out the main job")
    p.add_argument("--full", action="store_true", help="also the real double pendulum's diagnosis (long)")
    p.add_argument("--json", default=None)
    args = p.parse_args()
    env = environment()
    rows = measure(args)
    publish(args.json, "bench_diagnose_speed", env, rows, COLUMNS, base=args.base, cache=args.cache)


if __name__ == "__main__":
    main()

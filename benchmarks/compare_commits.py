"""Side by side: this checkout against an older commit, cold, in fresh processes.

Each round runs, for the older commit's tree and for this one (alternating, so that a slow
spell of the machine falls on both alike):

- the main job (README's first command): `identify diagnose` on
  `identify/examples/pendulum_friction/experiment.toml`, a new process (tracing,
  compilation and run), into a fresh folder;
- `benchmarks/bench_fit_vs_scipy.py --repeats 1 --skip-default` of that tree (its cold fit
  includes the fit pipeline's compilation; it prints its own warm time);
- in the first round only, `identify fit` of each of `--fit-examples` (cold).

It reports each job's wall time per tree (median over rounds) and the ratio new / old,
and checks that the two trees' `diagnosis.json` and `result.json` files agree to `--rtol`
(timing and version fields aside): a refactor must not change a result.

The older commit is checked out with `git worktree` into a temporary folder (removed at
the end); both trees run with this interpreter and its installed dependencies.

Usage: `python benchmarks/compare_commits.py [--base 1119d85] [--rounds 2] [--json out.json]`
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAIN_JOB = Path("identify/examples/pendulum_friction/experiment.toml")
IGNORED = ("time", "versions", "path", "file", "command")


def _run(tree: Path, args: list[str], cwd: Path) -> tuple[float, str]:
    """Wall time (s) of `python ARGS` with `tree` first on the path, and its output."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    start = time.perf_counter()
    done = subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{args} in {tree} exited {done.returncode}:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    return wall, done.stdout


def differences(a, b, rtol: float, where: str = "") -> list[str]:
    """Where two JSON trees differ beyond `rtol` (fields named in `IGNORED` skipped)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if any(word in k for word in IGNORED):
                continue
            if k not in a or k not in b:
                out.append(f"{where}/{k}: in one only")
            else:
                out += differences(a[k], b[k], rtol, f"{where}/{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} vs {len(b)} entries"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, rtol, f"{where}[{i}]")]
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool):
        close = a == b or abs(a - b) <= rtol * max(abs(a), abs(b))
        return [] if close else [f"{where}: {a!r} vs {b!r}"]
    return [] if a == b else [f"{where}: {str(a)[:60]!r} vs {str(b)[:60]!r}"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", default="1119d85", help="the older commit (default: before the identify redesign)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--rtol", type=float, default=1e-6)
    parser.add_argument("--json", default=None)
    parser.add_argument(
        "--fit-examples",
        nargs="*",
        default=["pendulum_drops", "pendulum_friction"],
        help="shipped examples (identify/examples/NAME) fitted in the first round, their result.json compared",
    )
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="compare_commits_"))
    old = work / "old"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old), args.base], check=True)
    trees = {"old": old, "new": ROOT}
    times = {name: {"main_job": [], "fit_vs_scipy": []} for name in trees}
    try:
        for r in range(args.rounds):
            for name, tree in trees.items():
                out = work / f"{name}-{r}"
                wall, _ = _run(tree, ["-m", "identify", "diagnose", str(tree / MAIN_JOB), "--out", str(out)], work)
                times[name]["main_job"].append(wall)
                wall, _ = _run(
                    tree, [str(tree / "benchmarks/bench_fit_vs_scipy.py"), "--repeats", "1", "--skip-default"], work
                )
                times[name]["fit_vs_scipy"].append(wall)
                if r == 0:
                    for ex in args.fit_examples:
                        exp = tree / "identify" / "examples" / ex / "experiment.toml"
                        fit_out = work / f"{name}-fit-{ex}"
                        wall, _ = _run(tree, ["-m", "identify", "fit", str(exp), "--out", str(fit_out)], work)
                        times[name][f"fit_{ex}"] = [wall]
                print(
                    f"round {r + 1} {name}: main job {times[name]['main_job'][-1]:.1f} s, "
                    f"fit_vs_scipy {times[name]['fit_vs_scipy'][-1]:.1f} s",
                    flush=True,
                )
        a, b = (json.loads((work / f"{n}-0" / "diagnosis.json").read_text()) for n in ("old", "new"))
        diff = differences(a, b, args.rtol, "diagnosis.json")
        for ex in args.fit_examples:
            a, b = (json.loads((work / f"{n}-fit-{ex}" / "result.json").read_text()) for n in ("old", "new"))
            diff += differences(a, b, args.rtol, f"{ex}/result.json")
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], check=False)
    summary = {
        job: {n: statistics.median(times[n][job]) for n in trees} | {"ratio_new_over_old": None} for job in times["old"]
    }
    for job, row in summary.items():
        row["ratio_new_over_old"] = row["new"] / row["old"]
        ratio = row["ratio_new_over_old"]
        print(f"{job}: old {row['old']:.1f} s, new {row['new']:.1f} s (median of {args.rounds}), new/old {ratio:.3f}")
    print(f"diagnosis.json and result.json: {len(diff)} differences beyond rtol {args.rtol}")
    print("\n".join(diff[:40]))
    if args.json:
        record = {"base": args.base, "rounds": args.rounds, "times_s": times, "median": summary, "differences": diff}
        Path(args.json).write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()

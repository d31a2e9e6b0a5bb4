"""Benchmark: loading a large CSV log (`identify.load_log`), the fast reader against the careful one.

A synthetic 200 Hz log of a two-link arm (time, 2 angles, 2 tip deflections, 2 torques and a
text status column, 7 numbers of 3-6 decimals per row) of `--mb` megabytes is written in a
temporary folder and loaded by:

- fast: `load_log` as shipped (chunks of plain rows through `np.loadtxt`, mapped columns only);
- careful: the same with every chunk read by the careful line-by-line reader (the fallback
  that names the line and column of a bad cell: `csv_rows.read_rows(fast=False)`);
- commit `REV` (with `--commit REV`): `load_log` of that git commit (`git archive` of its
  `identify` and `flexdyn`), e.g. the line-by-line reader before the chunked one (`8cebc72`);
- check: the whole `identify check` of an experiment (paper 002's two-link arm) that maps
  all six data columns of the log, as a user runs it (imports, the checks, the problem a
  fit would start from: the issue's goal, a 1 GB log checked in < 30 s and < 3 GB).

Each load runs in a fresh process (so its peak resident memory is its own), `--repeats`
rounds round robin; reported per run: the median and fastest wall time of the load (imports
excluded), throughput, the process's peak resident memory and its rise over the memory after
the imports, and both as ratios to the fast reader. Every run must read the same values
(a hash of the SI arrays, compared bit for bit).

Usage: `python benchmarks/bench_large_logs.py [--mb 200] [--repeats 1] [--runs fast,careful,check]
[--commit REV] [--json out.json]`
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

import numpy as np  # noqa: E402
from _common import environment, publish  # noqa: E402

COLUMNS = [
    ("run", "run", ""),
    ("rows", "rows", ","),
    ("warm_s", "load, median [s]", ".2f"),
    ("min_s", "fastest [s]", ".2f"),
    ("mb_per_s", "MB/s", ".1f"),
    ("peak_mb", "peak RSS [MB]", ".0f"),
    ("rise_mb", "rise over imports [MB]", ".0f"),
    ("ratio", "time / fast", ".2f"),
    ("memory_ratio", "rise / fast", ".2f"),
]

HEADER = "time [s],theta1 [deg],theta2 [deg],tip1 [mm],tip2 [mm],torque1 [N m],torque2 [N m],status"

FORMATS = ("%.3f", "%.6f", "%.6f", "%.5f", "%.5f", "%.4f", "%.6f")


def write_log(path: str, megabytes: float, block: int = 20_000) -> int:
    """Write the synthetic log (about `megabytes` MB); returns its rows."""
    rng = np.random.default_rng(20261207)
    rows = 0
    with open(path, "w") as f:
        f.write(f"# bench_large_logs.py: synthetic 200 Hz log, {megabytes:g} MB\n{HEADER}\n")
        while f.tell() < megabytes * 1e6:
            t = (rows + np.arange(block)) * 0.005
            columns = [
                t,
                30 * np.sin(t),
                20 * np.cos(1.3 * t),
                5 * np.sin(7 * t) + rng.normal(0, 0.01, block),
                3 * np.cos(9 * t),
                0.1 * np.sign(np.sin(t)),
                rng.normal(0, 0.01, block),
            ]
            cells = [np.char.mod(fmt, c) for fmt, c in zip(FORMATS, columns)]
            f.write("\n".join(",".join(r) for r in zip(*cells, ["ok"] * block)) + "\n")
            rows += block
    return rows


EXPERIMENT = """
[experiment]
name = "bench_large_logs"

[rig]
base = "two_link_flexible_arm"

[parameters]
"joint1.damping" = { guess = 1e-3, lower = 1e-6, upper = 1e-1 }

[[logs]]
name = "large"
file = "large.csv"
columns = { time = "time [s]", theta1 = "theta1 [deg]", theta2 = "theta2 [deg]", tip1 = "tip1 [mm]", \
tip2 = "tip2 [mm]", torque1 = "torque1 [N m]", torque2 = "torque2 [N m]" }
"""


def check_child(path: str) -> dict:
    """`identify check` of `EXPERIMENT` over the log `path`, in this process (its output
    discarded); the wall time includes the imports, as a user waits for them."""
    import contextlib
    import io

    toml = os.path.join(os.path.dirname(path), "experiment.toml")
    with open(toml, "w") as f:
        f.write(EXPERIMENT)
    start = time.perf_counter()
    from identify.cli import main

    with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.redirect_stderr(io.StringIO()) as err:
        code = main(["check", toml])
    if code:
        raise SystemExit(f"identify check exited {code}:\n{out.getvalue()}\n{err.getvalue()}")
    return {"seconds": time.perf_counter() - start, "rows": 0, "hash": "check"}


def child(run: str, path: str, tree: str | None) -> None:
    """Load `path` once in this process and print the measurements as JSON."""
    import resource

    if tree is not None:
        sys.path.insert(0, tree)
    else:
        sys.path.insert(0, ROOT)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if run == "check":
        scale = 1024 if sys.platform != "darwin" else 1
        result = check_child(path)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        print(json.dumps({**result, "peak_mb": peak * scale / 1e6, "rise_mb": (peak - base) * scale / 1e6}))
        return
    import identify

    if run == "careful":
        from identify._data import csv_log, csv_rows

        csv_log.read_rows = lambda *a, **k: csv_rows.read_rows(*a, **{**k, "fast": False})
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    log = identify.load_log(path)
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    digest = hashlib.sha1(log.t.tobytes())
    for channel in sorted(log.channels):
        digest.update((log.outputs | log.inputs)[channel].tobytes())
    scale = 1024 if sys.platform != "darwin" else 1  # ru_maxrss: kB on Linux, bytes on macOS
    print(
        json.dumps(
            {
                "seconds": seconds,
                "rows": len(log),
                "peak_mb": peak * scale / 1e6,
                "rise_mb": (peak - base) * scale / 1e6,
                "hash": digest.hexdigest(),
                "module": os.path.dirname(identify.__file__),
            }
        )
    )


def tree_of(commit: str, folder: str) -> str:
    """`identify` and `flexdyn` of `commit`, extracted under `folder`."""
    archive = subprocess.run(
        ["git", "-C", ROOT, "archive", commit, "identify", "flexdyn"], capture_output=True, check=True
    )
    subprocess.run(["tar", "-x", "-C", folder], input=archive.stdout, check=True)
    return folder


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mb", type=float, default=200.0, help="size of the synthetic log, MB")
    parser.add_argument("--repeats", type=int, default=1, help="rounds, each run loading once per round")
    parser.add_argument("--runs", default="fast,careful", help="comma-separated: fast, careful")
    parser.add_argument("--commit", default=None, help="also load with identify as of this git commit")
    parser.add_argument("--json", default=None, help="also write the results as JSON to this path")
    parser.add_argument("--child", nargs=3, metavar=("RUN", "PATH", "TREE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        run, path, tree = args.child
        return child(run, path, None if tree == "-" else tree)

    env = environment()
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "large.csv")
        start = time.perf_counter()
        rows = write_log(path, args.mb)
        size_mb = os.path.getsize(path) / 1e6
        print(f"wrote {size_mb:.1f} MB, {rows:,} rows in {time.perf_counter() - start:.1f} s", flush=True)
        runs = {name: "-" for name in args.runs.split(",")}
        if args.commit:
            os.makedirs(os.path.join(tmp, "tree"))
            runs[f"commit {args.commit}"] = tree_of(args.commit, os.path.join(tmp, "tree"))
        samples: dict[str, list[dict]] = {name: [] for name in runs}
        for _ in range(max(args.repeats, 1)):
            for name, tree in runs.items():
                kind = name if name in ("careful", "check") else "fast"
                cmd = [sys.executable, os.path.abspath(__file__), "--child", kind, path, tree]
                out = subprocess.run(cmd, capture_output=True, text=True)
                if out.returncode:
                    raise SystemExit(f"bench_large_logs: the {name} run failed:\n{out.stderr}")
                samples[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
                print(f"{name}: {samples[name][-1]['seconds']:.2f} s", flush=True)
    hashes = {s["hash"] for runs_ in samples.values() for s in runs_ if s["hash"] != "check"}
    if len(hashes) > 1:
        raise SystemExit(f"bench_large_logs: the runs read different values ({len(hashes)} hashes)")
    results = []
    for name, runs_ in samples.items():
        seconds = [s["seconds"] for s in runs_]
        results.append(
            dict(
                run=name,
                rows=runs_[0]["rows"] or rows,
                warm_s=statistics.median(seconds),
                min_s=min(seconds),
                mb_per_s=size_mb / statistics.median(seconds),
                peak_mb=max(s["peak_mb"] for s in runs_),
                rise_mb=max(s["rise_mb"] for s in runs_),
            )
        )
    fast = next((r for r in results if r["run"] == "fast"), results[0])
    for r in results:
        r["ratio"] = r["warm_s"] / fast["warm_s"]
        r["memory_ratio"] = r["rise_mb"] / fast["rise_mb"]
    publish(args.json, "large_logs", env, results, COLUMNS, size_mb=size_mb, samples=samples)


if __name__ == "__main__":
    sys.exit(main())

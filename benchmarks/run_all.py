"""Run every benchmark script (`benchmarks/bench_*.py`), each in its own process (so every
one pays its own compilation, as a user would), and print one table with the machine and
versions.

Usage: `python benchmarks/run_all.py [--repeats N] [--only NAME] [--json all.json]`

Each script must accept `--json PATH` and write `{"results": [row, ...], "columns": [...]}`
there (see `_common.py`); its own printed output is shown as it runs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _common import environment, format_environment, format_table, write_json  # noqa: E402

HERE = Path(__file__).resolve().parent

COLUMNS = [
    ("benchmark", "benchmark", ""),
    ("run", "run", ""),
    ("cold_s", "cold [s]", ".3f"),
    ("warm_s", "warm [s]", ".4f"),
    ("ratio", "warm / ref. run", ".2f"),
    ("speedup", "speed-up vs peer", ".1f"),
    ("steps", "steps", "d"),
    ("error_Q", "error", ".2e"),
]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Run all flexdyn benchmarks and print one table.")
    parser.add_argument("--repeats", type=int, default=None, help="warm runs per case, passed to every script")
    parser.add_argument("--only", default=None, help="run only scripts whose name contains this")
    parser.add_argument("--json", default=None, help="also write all results as JSON to this path")
    args = parser.parse_args(argv)

    scripts = sorted(p for p in HERE.glob("bench_*.py") if args.only is None or args.only in p.name)
    if not scripts:
        print("run_all: no benchmark scripts matched", file=sys.stderr)
        return 1
    rows, failures, per_script = [], [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for script in scripts:
            out = Path(tmp) / (script.stem + ".json")
            cmd = [sys.executable, str(script), "--json", str(out)]
            if args.repeats is not None:
                cmd += ["--repeats", str(args.repeats)]
            print(f"=== {script.name}", flush=True)
            start = time.perf_counter()
            proc = subprocess.run(cmd)
            elapsed = time.perf_counter() - start
            if proc.returncode != 0 or not out.exists():
                failures.append(script.name)
                print(f"run_all: {script.name} failed (exit status {proc.returncode})", file=sys.stderr)
                continue
            result = json.loads(out.read_text())
            per_script[script.name] = dict(result, elapsed_s=elapsed)
            rows += [dict(r, benchmark=script.stem.removeprefix("bench_")) for r in result["results"]]
            print(f"({script.name}: {elapsed:.1f} s including start-up)\n", flush=True)

    env = environment()
    print("=== all benchmarks")
    print(format_environment(env))
    print()
    print(format_table(rows, COLUMNS))
    if failures:
        print(f"\nFAILED: {', '.join(failures)}", file=sys.stderr)
    write_json(args.json, {"environment": env, "scripts": per_script, "results": rows, "failures": failures})
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

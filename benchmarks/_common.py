"""Helpers shared by the benchmark scripts (not a benchmark itself: only `bench_*.py` are run)."""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import time
from importlib import metadata


def cpu_model() -> str:
    """The CPU's marketing name, or the best the platform offers."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    if sys.platform == "darwin":
        try:
            out = subprocess.run(["sysctl", "-n", "machdep.cpu.brand_string"], capture_output=True, text=True)
            if out.returncode == 0 and out.stdout.strip():
                return out.stdout.strip()
        except OSError:
            pass
    return platform.processor() or platform.machine() or "unknown"


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def environment() -> dict:
    """Versions and machine, as every benchmark reports them."""
    env = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "logical_cores": os.cpu_count(),
        "usable_cores": usable_cores(),
    }
    for dist in ("jax", "jaxlib", "diffrax", "equinox", "numpy", "scipy", "flexdyn"):
        try:
            env[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            env[dist] = None
    try:
        import jax

        env["jax_backend"] = jax.default_backend()
        env["jax_devices"] = [str(d) for d in jax.devices()]
    except Exception:  # noqa: BLE001 - reporting only
        pass
    try:
        env["load_average_1min"] = os.getloadavg()[0]  # a busy machine inflates every timing
    except (AttributeError, OSError):
        pass
    return env


def format_environment(env: dict) -> str:
    versions = ", ".join(f"{k} {env.get(k)}" for k in ("jax", "jaxlib", "diffrax", "equinox", "numpy", "scipy"))
    load = f", load average {env['load_average_1min']:.1f}" if "load_average_1min" in env else ""
    return (
        f"Python {env['python']}; {versions}\n"
        f"CPU: {env['cpu']}, {env['usable_cores']} usable of {env['logical_cores']} logical cores"
        f"{load}; JAX backend {env.get('jax_backend', '?')}"
    )


def timed(fn):
    """(result, seconds) of one call; `fn` must block until its result is ready."""
    start = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - start


def median_time(fn, repeats: int) -> float:
    return statistics.median(timed(fn)[1] for _ in range(repeats))


def round_robin(calls: dict, rounds: int) -> dict:
    """Seconds of `rounds` calls of each function of `calls` (name -> fn), interleaved: each
    round calls every function once, in order. Runs compared by their ratio are then timed
    through the same spells of the machine (this VM runs some programs 2x slow for minutes
    at a time), instead of one run taking a slow spell alone. Each `fn` must block until its
    result is ready. Returns name -> list of seconds (summarise with `warm_summary`)."""
    samples = {name: [] for name in calls}
    for _ in range(max(int(rounds), 1)):
        for name, fn in calls.items():
            samples[name].append(timed(fn)[1])
    return samples


def warm_summary(seconds: list) -> dict:
    """`warm_s` (the median), `min_s` and `rounds` of a run's round-robin samples."""
    return dict(warm_s=statistics.median(seconds), min_s=min(seconds), rounds=len(seconds))


def format_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """A Markdown table; `columns` is (key, header, format spec) and missing values print as '-'."""

    def cell(row, key, spec):
        value = row.get(key)
        if value is None:
            return "-"
        return format(value, spec) if spec else str(value)

    body = [[cell(r, k, s) for k, _, s in columns] for r in rows]
    headers = [h for _, h, _ in columns]
    widths = [max(len(h), *(len(b[i]) for b in body)) if body else len(h) for i, h in enumerate(headers)]
    lines = [
        "| " + " | ".join(h.ljust(w) for h, w in zip(headers, widths)) + " |",
        "| " + " | ".join("-" * w for w in widths) + " |",
    ]
    lines += ["| " + " | ".join(c.rjust(w) for c, w in zip(b, widths)) + " |" for b in body]
    return "\n".join(lines)


def write_json(path, payload: dict) -> None:
    if path:
        with open(path, "w") as f:
            json.dump(payload, f, indent=2, default=float)
            f.write("\n")


def publish(json_path, benchmark: str, env: dict, rows: list[dict], columns, *, environment=True, note="", **extra):
    """Print the machine and versions (unless `environment` is False: printed earlier),
    a blank line and the results table; write the JSON `run_all.py` reads (`benchmark`,
    `environment`, `columns` (their keys), `results`, and any `extra` entries) to
    `json_path` if given. `note` is appended to the environment line (a peer's version)."""
    if environment:
        print(format_environment(env) + note)
        print()
    print(format_table(rows, columns))
    write_json(
        json_path,
        {"benchmark": benchmark, "environment": env, "columns": [c[0] for c in columns], "results": rows, **extra},
    )

"""Benchmark: fitting logs in which the rig rests before its input (`identify.log_onset`).

The 4-parameter flexible-arm scenario of `tests/identify/test_fit.py` (one flexible link,
horizontal plane; EI, joint damping, hub inertia, payload free; `theta1` and `tip1` at 4 ms,
1 % noise) with its two doublets delayed by `--rest` s of rest: the log is simulated whole
(the torque zero, then rising to the doublets' 0.05 N m over the sample before). Each seed's
log is fitted twice with `identify.fit`'s defaults (`estimate_noise=False`), guesses 20 % off
(alternating signs by seed):

- ours, whole log: the log as recorded, rest included (the horizons count from its onset;
  the early stages skip the rest, the last one simulates it);
- peer, rest cut: the same samples from the one before the input on, as if the recording
  had started there (what a user would otherwise do by hand).

Reported per run: fits within the accuracy bars (EI and hub inertia 1 %, damping and payload
5 %), the median warm wall time per fit (each seed's two fits alternate, so a slow spell of
the machine falls on both), and the ratio of the two. The first fit of each run compiles and
is reported apart.

Usage: `python benchmarks/bench_fit_rest.py [--seeds 8] [--rest 3.0] [--json out.json]`
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "..", "tests", "identify"))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

import numpy as np  # noqa: E402
from _common import environment, publish  # noqa: E402
from test_fit import BARS, CHANNELS, DT, T_END, TRUTH, Arm, doublets  # noqa: E402

import identify  # noqa: E402

COLUMNS = [
    ("run", "run", ""),
    ("within_bars", "fits within the bars", ""),
    ("first_s", "first fit (compile) [s]", ".1f"),
    ("warm_s", "warm per fit, median [s]", ".2f"),
    ("ratio", "warm / rest cut", ".2f"),
]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=8, help="noise seeds 1..N")
    parser.add_argument("--rest", type=float, default=3.0, help="rest before the input, s")
    parser.add_argument("--repeats", type=int, default=None, help="(unused: each seed is one fit per run)")
    parser.add_argument("--json", default=None, help="also write the results as JSON to this path")
    args = parser.parse_args(argv)
    env = environment()
    arm = Arm()
    t = np.arange(0.0, args.rest + T_END, DT)
    torque = doublets(t - args.rest)
    torque[t < args.rest] = 0.0
    k0 = int(np.flatnonzero(torque[:, 0] != 0.0)[0]) - 1  # the sample before the input
    runs = {"ours: whole log, rest included": [], "peer: rest cut by hand": []}
    ok = {name: 0 for name in runs}
    first = {}
    details = []
    for seed in range(1, args.seeds + 1):
        log = identify.simulate_log(
            arm.chain, t, torque=torque, channels=CHANNELS, noise=arm.noise, rng=np.random.default_rng(seed)
        )
        cut = identify.LogData(
            t=log.t[k0:] - log.t[k0], outputs={c: v[k0:] for c, v in log.outputs.items()}, torque=log.torque[k0:]
        )
        factors = (1.2, 0.8, 1.2, 0.8) if seed % 2 else (0.8, 1.2, 0.8, 1.2)
        params = [identify.Parameter(n, v * f, v * 1e-2, v * 1e2) for (n, v), f in zip(TRUTH.items(), factors)]
        for name, data in zip(runs, (log, cut)):
            start = time.perf_counter()
            problem = identify.make_problem(arm.chain, params, [data], noise=arm.noise)
            result = identify.fit(problem, params, estimate_noise=False)
            wall = time.perf_counter() - start
            errs = {n: result.value[n] / TRUTH[n] - 1.0 for n in TRUTH}
            good = bool(result.converged and all(abs(e) <= BARS[n] for n, e in errs.items()))
            ok[name] += good
            if name in first:
                runs[name].append(wall)
            else:
                first[name] = wall
            details.append(
                dict(run=name, seed=seed, within_bars=good, wall_s=wall, cost=float(result.cost), errors=errs)
            )
            print(f"  seed {seed} {name}: {'ok' if good else 'OFF'}, {wall:.1f} s, cost {result.cost:.6g}", flush=True)
    peer = statistics.median(runs["peer: rest cut by hand"])
    rows = []
    for name, walls in runs.items():
        warm = statistics.median(walls)
        rows.append(
            dict(
                run=name, within_bars=f"{ok[name]} of {args.seeds}", first_s=first[name], warm_s=warm, ratio=warm / peer
            )
        )
    print()
    print(
        f"bench_fit_rest: 1-link flexible arm, 4 parameters, {args.rest:g} s of rest then {T_END:g} s of doublets "
        f"({len(t)} samples x 2 channels), {args.seeds} noise seeds"
    )
    publish(args.json, "fit_rest", env, rows, COLUMNS, trials=details)


if __name__ == "__main__":
    main()

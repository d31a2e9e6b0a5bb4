"""Benchmark: multiple shooting against the growing horizon on a long open-loop log.

Scenario (`tests/identify/test_multiple_shooting.py`'s, `multiple_shooting_case.py`): the
flexible link of `tests/identify/test_fit.py` (horizontal plane, l 0.5 m, rho 0.2 kg/m,
EI 1 N m^2, one mode, modal damping ratio 0.02, hub 0.02 kg m^2, payload 0.05 kg, joint
damping 0.005 N m s) replayed open loop under a torque doublet of random sign and size
every second for `--duration` s (6 s), `theta1` and `tip1` logged at 4 ms with 1 % noise.
Free: EI, joint damping, hub inertia, payload mass (bounds truth x [1e-2, 1e2]); guess EI x
`--ei-factor` (0.25), the rest at the truth. Both runs from one start, no frequency
initialisation, no restarts: the comparison is of the two ways through the simulation.

- `growing`: `identify.fit`'s growing horizon (`n_stages=4`: 0.75, 1.5, 3, 6 s);
- `multiple`: `shooting="multiple"`, segments of `--segment` s (0.2), then the one
  single-shooting stage over the whole log.

Reported per run: Levenberg-Marquardt iterations (all stages), wall time (compilation
included: each is the first fit of its kind in the process), the final cost (sum of the
squared weighted residuals; the noise alone gives about the number of samples times
channels, 3000), and each parameter's error in its own standard errors and in %.

Usage: `python benchmarks/bench_multiple_shooting.py [--json out.json]`
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _common import environment, publish  # noqa: E402
from multiple_shooting_case import TRUTH, long_log, problem_of  # noqa: E402

import identify  # noqa: E402


def run(problem, **options) -> dict:
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = identify.fit(
            problem, estimate_noise=False, n_starts=1, frequency_init=False, max_restarts=0, **options
        )
    seconds = time.perf_counter() - start
    row = dict(
        iterations=sum(s.iterations for s in result.stages),
        wall_s=seconds,
        cost=result.stages[-1].cost,
        converged=result.converged,
    )
    for i, name in enumerate(result.names):
        row[f"{name} [SE]"] = (result.value[name] - TRUTH[name]) / result.std_errors[i]
        row[f"{name} [%]"] = 100 * (result.value[name] / TRUTH[name] - 1)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=6.0)
    parser.add_argument("--segment", type=float, default=0.2)
    parser.add_argument("--ei-factor", type=float, default=0.25)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    log, noise = long_log(args.duration)
    problem = problem_of(log, noise, {"link1.EI": args.ei_factor})
    rows = [
        dict(run="growing (n_stages=4)", **run(problem)),
        dict(run=f"multiple (segment={args.segment:g} s)", **run(problem, shooting="multiple", segment=args.segment)),
    ]
    columns = [("run", "run", ""), ("iterations", "iterations", "d"), ("wall_s", "wall [s]", ".1f")]
    columns += [("cost", "final cost", ".4g"), ("converged", "converged", "")]
    columns += [(f"{n} [%]", f"{n} error [%]", "+.3g") for n in TRUTH]
    columns += [(f"{n} [SE]", f"{n} [SE]", "+.3g") for n in TRUTH]
    publish(args.json, "multiple_shooting", environment(), rows, columns, duration_s=args.duration)


if __name__ == "__main__":
    main()

"""Initial guesses: the fit's starting variables, the multi-start design and stage, extra starts,
distinct optima and frequency-domain initialisation of stiffnesses.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .._model.parameters import theta_from_x, x_from_theta, z_from_x
from .._model.problem import Problem, guesses_of
from .._model.variables import Variables
from .frequency_init import STIFFNESS, initialise_stiffness
from .levenberg_marquardt import _solve
from .stage import Stage
from .steps import _Grid, _grid_step, _span_horizon, _stage_step

#: `_distinct`: two optima of the multi-start stage are the same when their costs agree to
#: this relative tolerance (starts that end in one basin of the short horizon agree to
#: ~1e-7 in cost while a direction it cannot see, such as a damping, may still differ)
DISTINCT_COST = 1e-4


def initial_variables(problem: Problem, x0) -> Variables:
    """`fit`'s variables `z` at the natural coordinates `x0`: `phys` (the sigmoid/log
    coordinates of `z_from_x`), `y0` (the free initial-state entries at their known values)
    and `offset` (the free sensor offsets, 0)."""
    return Variables(
        offset=jnp.zeros(len(problem.offset_free)),
        phys=jnp.asarray(z_from_x(problem, x0)),
        y0=jnp.asarray([problem.y0_known[l, s] for l, s in problem.y0_free], dtype=float),
    )


def multi_start(
    problem: Problem,
    z: Variables,
    x0: np.ndarray,
    extra: list,
    horizon: float,
    grid: _Grid,
    sigma,
    *,
    n_starts: int,
    spread: float,
    max_steps: int,
    cap: int,
    rtol: float,
    atol: float,
    keep: int,
    say: Callable,
) -> tuple[list, dict]:
    """`fit`'s multi-start stage: the first stage (`horizon`, s from each log's onset) fitted
    from `_starts`' `n_starts` points around `x0` and then the `extra` ones (natural
    coordinates), each with the budget `max_steps` and optimistix's first damping, the
    nuisances of `z` kept. Returns the distinct optima, best first, at most `keep`
    (`_distinct`), and the stage's record for `FitResult.stages`.

    The starts run one after another with the stages' compiled program (`cap`: its static
    loop bound): a vmapped call would be a second program to compile, and is not faster on
    the CPU."""
    step = _stage_step(problem, z, horizon, grid, sigma)
    xs = list(_starts(problem, x0, n_starts, spread)) + extra
    runs = [
        _solve(
            problem,
            dataclasses.replace(z, phys=jnp.asarray(z_from_x(problem, x))),
            sigma,
            jnp.asarray(horizon),
            step,
            jnp.asarray(max_steps),  # an array: traced, not a static argument
            jnp.asarray(0.0, dtype=float),  # optimistix's start: see `fit`'s `first_damping`
            cap,
            rtol,
            atol,
        )
        for x in xs
    ]
    costs = np.asarray([float(r[3]) for r in runs])
    order = np.argsort(np.where(np.isfinite(costs), costs, np.inf))
    candidates = _distinct([runs[int(i)][0] for i in order], costs[order])[:keep]
    best = int(order[0])
    stage = Stage(
        float(horizon),
        max(int(r[2]) for r in runs),
        float(costs[best]),
        runs[best][1],
        starts=len(xs),
        start_costs=tuple(float(c) for c in costs),
    )
    n_design = len(xs) - len(extra)
    which = f"start {best + 1}" if best < n_design else f"extra start {best - n_design + 1}"
    say(
        f"  horizon {horizon:8.3f} s: {len(xs)} starts, best cost {float(costs[best]):.6g} from {which} "
        f"(costs in order, the guess first: {', '.join(f'{float(c):.4g}' for c in costs)})"
    )
    return candidates, stage


def _distinct(zs: list, costs) -> list:
    """The multi-start stage's optima `zs` (best first, with their `costs`) without repeats:
    several starts often end at the same short-horizon optimum, and a restart from a
    repeat would grow the horizon into the same basin again. An optimum whose cost is
    within `DISTINCT_COST` of a better one's is dropped, as is a failed one (infinite)."""
    kept, kept_costs = [], []
    for z, c in zip(zs, costs):
        if np.isfinite(c) and all(abs(c - k) > DISTINCT_COST * abs(k) for k in kept_costs):
            kept.append(z)
            kept_costs.append(c)
    return kept or zs[:1]


def _stiffness_limits(problem: Problem):
    """SI bounds of the parameters, 0.1 % of each finite range inside (what a frequency
    initialisation may try), or None when no `link<i>.EI` is free."""
    if not any(STIFFNESS.fullmatch(n) for n in problem.names):
        return None
    lo, hi = np.asarray(problem.lower), np.asarray(problem.upper)
    span = hi - lo
    margin = np.where(np.isfinite(span), 1e-3 * span, 0.0)
    return tuple(np.asarray(theta_from_x(problem, jnp.asarray(b)), float) for b in (lo + margin, hi - margin))


def _z_rows(problem: Problem, thetas) -> np.ndarray:
    return np.stack([z_from_x(problem, x_from_theta(problem, theta)) for theta in thetas])


def _frequency_initialise(problem: Problem, x0: np.ndarray, say, safety: float = 0.5) -> np.ndarray:
    """`x0` (natural coordinates) with the free `link<i>.EI` guesses rescaled so that the
    model's simulated flexural channel matches the measured one's amplitude spectrum
    (`identify.frequency_init`). The simulations are `_grid_step`'s (`safety`: the fit's
    `grid_safety`, a static argument), the program the fit's stages use anyway."""
    x0 = np.asarray(x0, float)
    limits = _stiffness_limits(problem)
    if limits is None:
        return x0
    y0 = jnp.asarray([problem.y0_known[l, s] for l, s in problem.y0_free], dtype=float)
    offset = jnp.zeros(len(problem.offset_free))

    def simulate(thetas, span):
        z = Variables(offset=offset, phys=jnp.asarray(_z_rows(problem, thetas)[0]), y0=y0)
        _, ok, outputs = _grid_step(problem, z, _span_horizon(problem, span), safety)
        return np.asarray(outputs)[None], np.asarray(ok)[None]

    theta = np.asarray(theta_from_x(problem, jnp.asarray(x0)))
    return x_from_theta(problem, initialise_stiffness([problem], theta[None], limits, simulate, say)[0])


def _frequency_initialise_independent(problem: Problem, singles, stacked, z, x0, grid, safety: float, say):
    """`fit_independent`'s batch `z` with each log's own frequency initialisation of the
    free `link<i>.EI` (`_frequency_initialise`, every log from the common guess `x0`), the
    simulations of all logs in one call of the stages' vmapped `_grid_step` (`grid`) per
    EI factor tried. `z` is padded to the batch's device multiple and sharded
    (`flexdyn.batch`); the padding repeats the last log."""
    limits = _stiffness_limits(problem)
    if limits is None:
        return z
    n_logs, n_batch = len(singles), z.phys.shape[0]

    def batch_phys(thetas):
        rows = _z_rows(problem, thetas)
        rows = np.concatenate([rows, np.repeat(rows[-1:], n_batch - n_logs, axis=0)])
        return jax.device_put(jnp.asarray(rows, dtype=z.phys.dtype), z.phys.sharding)

    def simulate(thetas, span):
        _, ok, outputs = grid(
            stacked, dataclasses.replace(z, phys=batch_phys(thetas)), _span_horizon(problem, span), safety
        )
        return np.asarray(outputs)[:n_logs], np.asarray(ok)[:n_logs]

    theta = np.asarray(theta_from_x(problem, jnp.asarray(x0)))
    thetas = initialise_stiffness(singles, np.tile(theta, (n_logs, 1)), limits, simulate, say)
    return dataclasses.replace(z, phys=batch_phys(thetas))


def _extra_starts(problem: Problem, parameters, extra_starts) -> list:
    """`fit`'s `extra_starts` in natural coordinates (the guesses where a start names no
    value), each checked: known parameter names, finite values inside the bounds."""
    out = []
    guess = dict(zip(problem.names, guesses_of(problem, parameters)))
    for k, start in enumerate(extra_starts):
        unknown = sorted(set(start) - set(problem.names) - {name for name, _ in problem.per_log})
        if unknown:
            raise ValueError(
                f"fit: extra_starts[{k}] names {unknown}, which are not free parameters (free: {list(problem.names)})"
            )
        # (a per-log parameter's plain name starts every log's own value there)
        theta = [float(start.get(n, start.get(problem.base_name(n), guess[n]))) for n in problem.names]
        for n, v, lo, hi, lg in zip(problem.names, theta, problem.lower, problem.upper, problem.log_scale):
            x = math.log(v) if lg and v > 0 else v
            if not (np.isfinite(v) and (v > 0 or not lg) and lo <= x <= hi):
                raise ValueError(f"fit: extra_starts[{k}]: {n} = {v!r} is not a finite value inside its bounds")
        out.append(x_from_theta(problem, theta))
    return out


def _starts(problem: Problem, x0: np.ndarray, n_starts: int, spread: float) -> np.ndarray:
    """`n_starts` starting points in natural coordinates: the guess itself, then a
    deterministic low-discrepancy (Halton) design around it: log-scaled parameters within
    a factor `spread` of the guess, signed ones within +-50 % (+-1 when the guess is 0),
    clipped inside the bounds."""
    p = len(x0)
    primes = [2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53][:p] or [2]

    def halton(k, b):
        f, r = 1.0, 0.0
        while k > 0:
            f /= b
            r += f * (k % b)
            k //= b
        return r

    lo, hi = np.asarray(problem.lower), np.asarray(problem.upper)
    out = [np.asarray(x0, float)]
    for k in range(1, n_starts):
        u = np.array([2.0 * halton(k, primes[i % len(primes)]) - 1.0 for i in range(p)])
        width = np.array([np.log(spread) if problem.log_scale[i] else 0.5 * abs(x0[i]) or 1.0 for i in range(p)])
        x = x0 + u * width
        span = hi - lo
        margin = np.where(np.isfinite(span), 1e-3 * span, 0.0)
        out.append(np.clip(x, lo + margin, hi - margin))
    return np.stack(out)

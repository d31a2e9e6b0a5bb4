"""`fit_independent`: every log its own values of every free parameter, fitted in one batch."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import flexdyn as fd
from flexdyn import batch as fbatch

from .._data import noise_floor as nf
from .._data.channels import state_names
from .._model.parameters import Parameter, x_from_theta, x_from_z, z_from_x
from .._model.problem import Problem, check_same_parameters, guesses_of
from .._model.variables import Variables
from .jacobian import _covariance_at
from .levenberg_marquardt import _check_budgets, _check_damping, _solve
from .quality import (
    NOISE_AGREEMENT,
    NOISE_ROUNDS,
    _noise_range_text,
    _noise_to_estimate,
    _reestimate_sigma_per_log,
    _residual_ms,
    noise_floors,
)
from .result import FitResult, _finish
from .stage import Stage
from .starts import _frequency_initialise_independent
from .steps import (
    GRID_ERROR,
    GRID_RECHECK,
    BatchGrid,
    SimulationFailed,
    _default_horizons,
    _say_onsets,
    batch_grid,
    batch_stage_steps,
    batch_steps_off,
)

#: `_solve` over the batch: the problem, variables, noise levels and steps per log. The
#: Levenberg-Marquardt program stays a vmapped call on the sharded batch (not
#: `flexdyn.batch.sharded_vmap`): lineax's linear solve fails its structure check inside
#: `shard_map` (lineax issue #185).
_solve_batch = eqx.filter_vmap(_solve, in_axes=(0, 0, 0, None, 0, None, None, None, None, None))


def _split(problem: Problem) -> tuple[Problem, list[Problem]]:
    """The single-log problems of a multi-log problem, stacked along a leading axis (for
    `vmap`) and as a list. All logs must estimate the same nuisance entries."""
    L = problem.t.shape[0]
    per_log_y0 = [tuple(s for l, s in problem.y0_free if l == k) for k in range(L)]
    per_log_off = [tuple(c for l, c in problem.offset_free if l == k) for k in range(L)]
    for what, per_log, names in (
        ("fit_initial", per_log_y0, state_names(problem.chain)),
        ("offsets", per_log_off, problem.channels),
    ):
        for k in range(1, L):
            if per_log[k] != per_log[0]:
                first, other = ([names[i] for i in per_log[j]] for j in (0, k))
                raise ValueError(
                    f"fit_independent: the logs are fitted in one vmapped batch, so each must estimate the same "
                    f"{what} entries; log {problem.log_names[0]!r} has {what} {first}, "
                    f"log {problem.log_names[k]!r} has {other}"
                )
    fields = ("t", "valid", "measured", "present", "torque_t", "torque_v", "y0_known", "onset", "log_set")
    singles = []
    for k in range(L):
        singles.append(
            dataclasses.replace(
                problem,
                **{f: getattr(problem, f)[k : k + 1] for f in fields},
                **({} if problem.reference is None else {"reference": problem.reference[k : k + 1]}),
                y0_free=tuple((0, s) for s in per_log_y0[k]),
                offset_free=tuple((0, c) for c in per_log_off[k]),
                labels=(problem.log_names[k],),
            )
        )
    # (the singles' static parts agree: their log names compare equal, see `_LogLabels`)
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs) if eqx.is_array(xs[0]) else xs[0], *singles)
    return stacked, singles


def fit_independent(
    problem: Problem,
    parameters: Sequence[Parameter] | None = None,
    *,
    horizons: Sequence[float] | None = None,
    n_stages: int = 4,
    max_steps: int = 200,
    rtol: float = 1e-3,
    atol: float = 1e-10,
    grid_safety: float = 0.5,
    grid_error: float | None = GRID_ERROR,
    first_damping: float = 1e-3,
    frequency_init: bool = True,
    restart_poor_fit: bool = True,
    estimate_noise: Sequence[str] | bool | None = None,
    progress=None,
) -> list[FitResult]:
    """Independent fits of every log of `problem` (each log its own parameter values), all
    in one `vmap`ped call per stage: the batch runs in lockstep, each log with its own
    integration step. So every log must estimate the same `fit_initial` entries and
    `offsets` (a `ValueError` names the first two logs that differ). The first stage
    starts with the damping `first_damping` (as in `fit` with one start).
    `estimate_noise`: as in `fit` (default: the channels make_problem was given no noise
    for), but each log's own noise levels of these channels are re-estimated from its
    residuals and refitted, the whole batch at the full horizon, until every log's agree
    within `NOISE_AGREEMENT` (at most `NOISE_ROUNDS` passes); the other channels keep
    `problem`'s levels. Each result's `sigma` is its log's.
    `frequency_init`: each log's free `link<i>.EI` guess from its own flexural spectrum,
    as in `fit` (`identify.frequency_init`), all logs' simulations batched.
    `restart_poor_fit`: when some logs end with a channel above
    `identify.noise_floor.POOR_FIT` times its noise floor and others do not, the poor
    logs' horizons are grown again (the whole batch, in the same compiled programs) from
    the median of the other logs' parameters, and each poor log keeps the attempt that
    explains its data best (`identify.noise_floor.score`). When every log is poor (a
    model that misses an effect) nothing is retried.
    `grid_safety`, `grid_error`: as in `fit`, each log its own step.
    Returns one `FitResult` per log."""
    _check_damping(first_damping)
    _check_budgets(max_steps=max_steps)
    if problem.per_log:
        raise ValueError(
            f"fit_independent: {', '.join(repr(n) for n, _ in problem.per_log)} is fitted per log "
            "(Parameter.per_log); fit_independent fits every parameter per log already: make the problem with "
            "per_log=False"
        )
    parameters = problem.parameters if parameters is None else parameters
    check_same_parameters(problem, parameters, "fit_independent")
    fd.ensure_mapping_headroom()  # flexdyn.program_cache
    start = time.perf_counter()
    say = progress or (lambda msg: None)
    stacked, singles = _split(problem)
    L = len(singles)
    x0 = x_from_theta(problem, guesses_of(problem, parameters))
    z = _initial_batch(problem, singles, x0)
    # Spread the logs over all devices (`flexdyn.batch`): the batch is padded to a multiple
    # of the device count (repeating the last log) and placed with a NamedSharding over a
    # 1-D mesh of `jax.devices()`, so each vmapped stage is split across the devices. On
    # one device nothing is padded and this is the plain vmapped call. Only the first L
    # entries of each result are read.
    mesh = fbatch.batch_mesh()
    sigma0 = jnp.tile(jnp.asarray(problem.sigma), (L, 1))  # each log its own noise levels
    (stacked, z, sigma0), _ = fbatch.shard_batch((stacked, z, sigma0), mesh)
    estimate_noise = _noise_to_estimate(problem, estimate_noise)
    estimated = [j for j, c in enumerate(problem.channels) if c in estimate_noise]
    horizons = list(horizons) if horizons is not None else _default_horizons(problem, n_stages)
    _say_onsets(problem, horizons, say)
    batch = _Batch(
        problem=problem,
        singles=singles,
        grid=batch_grid(stacked, singles, mesh, grid_safety, grid_error),
        horizons=horizons,
        rounds=NOISE_ROUNDS if estimated else 1,
        estimated=estimated,
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
        first_damping=first_damping,
        say=say,
    )
    if frequency_init:
        z = _frequency_initialise_independent(problem, singles, stacked, z, x0, batch.grid.grid_step, grid_safety, say)
    fitted = _grow_batch(batch, z, sigma0)
    ms = _residual_ms_per_log(batch, fitted)
    fitted, ms = _restart_poor_logs(batch, fitted, ms, z, sigma0, restart_poor_fit)
    say("  computing standard errors (exact Jacobians at the optima) ...")
    x, covariances = _covariances(batch, fitted)
    wall = (time.perf_counter() - start) / L
    results = [
        _finish(
            singles[k],
            parameters,
            fitted.z.take(k),
            x[k],
            fitted.sigma[k],
            fitted.step[k],
            covariances[k][0],
            fitted.stages[k],
            wall,
            ms[k],
            covariances[k][1],
        )
        for k in range(L)
    ]
    return [dataclasses.replace(r, batch_size=L, sigma_estimated=tuple(estimate_noise)) for r in results]


def _initial_batch(problem: Problem, singles: list[Problem], x0) -> Variables:
    """The batch's variables `z` at the common guess `x0` (natural coordinates), one row per
    log: each log's free initial-state entries at its known values, its offsets 0."""
    L = len(singles)
    return Variables(
        offset=jnp.tile(jnp.zeros(len(singles[0].offset_free)), (L, 1)),
        phys=jnp.tile(jnp.asarray(z_from_x(problem, x0)), (L, 1)),
        y0=jnp.stack([jnp.asarray([q.y0_known[0, s] for _, s in q.y0_free], dtype=float) for q in singles]),
    )


@dataclasses.dataclass(frozen=True)
class _Batch:
    """The logs of one `fit_independent` call and the settings its stages share."""

    problem: Problem
    singles: list[Problem]  # `_split`
    grid: BatchGrid  # each log's constant step (`steps.batch_stage_steps`), on the sharded batch
    horizons: list[float]
    rounds: int  # passes of the noise re-estimation (`NOISE_ROUNDS`, or 1)
    estimated: list[int]  # the channels (indices) whose noise levels are re-estimated per log
    max_steps: int
    rtol: float
    atol: float
    first_damping: float
    say: Callable


class _BatchFit(NamedTuple):
    """Where a growing horizon of the whole batch ended: the variables `z`, noise levels
    `(B, C)`, constant steps `(B,)` and linearisation (on the host, `_solve`) of the last
    stage, and each log's stage records (`FitResult.stages`). `B`: the logs, padded."""

    z: Variables  # batch-first
    sigma: jax.Array
    step: jax.Array
    lin: list
    stages: list[list[dict]]


def _grow_batch(batch: _Batch, z, sigma, label: str = "") -> _BatchFit:
    """The growing horizon for the whole batch from `z` with noise levels `sigma` `(B, C)`,
    then the noise re-estimation rounds at the full horizon. `label` prefixes the progress
    messages."""
    L, horizons, grid, say = len(batch.singles), batch.horizons, batch.grid, batch.say
    stages = [[] for _ in range(L)]
    for rnd in range(batch.rounds):
        for k_stage, h in enumerate(horizons if rnd == 0 else horizons[-1:]):
            step, _, _ = batch_stage_steps(grid, z, sigma, h, k_stage)
            tau = jnp.asarray(batch.first_damping if rnd == 0 and k_stage == 0 else 0.0, dtype=float)
            z, lin = _stage_batch(batch, z, sigma, h, step, tau, stages, label)
        if grid.error:  # the steps checked again at the optimum (`GRID_RECHECK`, as in `fit`)
            off, tight = batch_steps_off(grid, z, sigma, h, step, len(horizons))
            if off:
                say(
                    f"  {label}integration steps of log(s) {[batch.singles[k].log_names[0] for k in off]} are over "
                    f"{GRID_RECHECK * grid.error:g} noise levels off at their optimum: the last stage again at "
                    "their tight steps"
                )
                step = jnp.where(jnp.isin(jnp.arange(step.shape[0]), jnp.asarray(off)), tight, step)
                z, lin = _stage_batch(batch, z, sigma, h, step, jnp.asarray(0.0, dtype=float), stages, label)
        lin = [np.asarray(a) for a in lin]  # one host transfer, not one per log
        if rnd + 1 < batch.rounds:
            ms = _residual_ms_per_log(batch, _BatchFit(z, sigma, step, lin, stages))
            new = _reestimate_sigma_per_log(ms, sigma, batch.estimated)
            change = float(np.max(np.abs(np.log(new[:L] / np.asarray(sigma)[:L]))))
            if rnd > 0 and change < math.log1p(NOISE_AGREEMENT):
                say(f"  {label}noise re-estimated again: every log's within {100 * NOISE_AGREEMENT:g} % of its weights")
                break
            sigma = jax.device_put(jnp.asarray(new), sigma.sharding)
            say(
                f"  {label}noise re-estimated per log: "
                + _noise_range_text(batch.problem.channels, new[:L], batch.estimated)
            )
    return _BatchFit(z, sigma, step, lin, stages)


def _stage_batch(batch: _Batch, z, sigma, h, step, tau, stages: list[list[dict]], label: str):
    """One stage of the whole batch at horizon `h` with the logs' steps `step` and first
    damping `tau`; each log's record is appended to `stages`. Returns `z` and the
    linearisation."""
    z, result, steps, cost, lin = _solve_batch(
        batch.grid.stacked,
        z,
        sigma,
        jnp.asarray(h),
        step,
        batch.max_steps,
        tau,
        batch.max_steps,
        batch.rtol,
        batch.atol,
    )
    L = len(batch.singles)
    for k in range(L):
        stages[k].append(Stage(float(h), int(steps[k]), float(cost[k]), jax.tree_util.tree_map(lambda a: a[k], result)))
    batch.say(f"  {label}horizon {h:8.3f} s: {int(jnp.max(steps)):3d} iterations (slowest of {L} logs)")
    return z, lin


def _residual_ms_per_log(batch: _Batch, fitted: _BatchFit) -> list:
    """Each log's `_residual_ms` at `fitted` (every sample: the last stage's horizon)."""
    z, sigma, step, lin = fitted.z, fitted.sigma, fitted.step, fitted.lin
    return [
        _residual_ms(
            single,
            z.take(k),
            sigma[k],
            step[k],
            (tuple(a[k] for a in lin), batch.horizons[-1]),
        )
        for k, single in enumerate(batch.singles)
    ]


def _restart_poor_logs(
    batch: _Batch, fitted: _BatchFit, ms: list, z_start: dict, sigma0, restart: bool
) -> tuple[_BatchFit, list]:
    """`fit_independent`'s `restart_poor_fit` (`restart`): a log left far above its noise
    floor while others fit theirs has its horizon grown again from the good logs' median
    parameters (a wrong basin is that log's alone; a model that misses an effect leaves
    every log poor, and nothing is retried), and keeps the new fit where it explains its
    data better. The same compiled
    programs: the batch keeps its size, the good logs restart where they were and keep
    their first results. Returns the fit and each log's `_residual_ms`."""
    problem, singles, say = batch.problem, batch.singles, batch.say
    L = len(singles)
    floors = [noise_floors(q) for q in singles]
    scores = np.asarray([nf.score(ms[k], *floors[k]) for k in range(L)])
    poor = [k for k in range(L) if any(q["poor"] for q in nf.goodness(problem.channels, ms[k], *floors[k]).values())]
    good = [k for k in range(L) if k not in poor]
    if not (restart and poor and good):
        return fitted, ms
    say(
        f"  log(s) {', '.join(problem.log_names[k] for k in poor)} left far above the noise floor: "
        f"growing the horizon again from the median of the other {len(good)} log(s)' parameters"
    )
    z, sigma = fitted.z, fitted.sigma
    phys = np.asarray(z.phys).copy()
    phys[poor] = np.median(phys[good], axis=0)
    y0 = np.asarray(z.y0).copy()
    y0[poor] = np.asarray(z_start.y0)[poor]
    off = np.asarray(z.offset).copy()
    off[poor] = np.asarray(z_start.offset)[poor]
    z2 = jax.tree_util.tree_map(
        lambda new, old: jax.device_put(new, old.sharding), Variables(offset=off, phys=phys, y0=y0), z
    )
    # the poor logs start again from the problem's noise levels too (their re-estimated
    # ones are their poor residuals')
    redo = np.zeros(sigma.shape[0], bool)
    redo[poor] = True
    sigma_start = jax.device_put(jnp.where(jnp.asarray(redo)[:, None], sigma0, sigma), sigma.sharding)
    again = _grow_batch(batch, z2, sigma_start, "again: ")
    ms2 = _residual_ms_per_log(batch, again)
    better = [k for k in poor if nf.score(ms2[k], *floors[k]) < scores[k]]
    say(f"  kept the new fit of {len(better)} of {len(poor)} log(s)")
    if not better:
        return fitted, ms
    pick = np.zeros(z.phys.shape[0], bool)
    pick[better] = True
    z = jax.tree_util.tree_map(
        lambda v, v2: jax.device_put(
            np.where(pick.reshape(-1, *[1] * (np.ndim(v) - 1)), np.asarray(v2), np.asarray(v)), v.sharding
        ),
        z,
        again.z,
    )
    step = jnp.where(jnp.asarray(pick), again.step, fitted.step)
    sigma = jnp.where(jnp.asarray(pick)[:, None], again.sigma, sigma)
    lin = [np.where(pick.reshape(-1, *[1] * (a.ndim - 1)), a2, a) for a, a2 in zip(fitted.lin, again.lin)]
    stages, ms = list(fitted.stages), list(ms)
    for k in better:
        stages[k], ms[k] = stages[k] + again.stages[k], ms2[k]
    return _BatchFit(z, sigma, step, lin, stages), ms


def _covariances(batch: _Batch, fitted: _BatchFit) -> tuple[jax.Array, list]:
    """Each log's natural coordinates `(L, P)` and `_covariance_at` (covariance and blocks)
    at its optimum; a `RuntimeError` names the logs whose simulation failed there."""
    singles, z = batch.singles, fitted.z
    x = jnp.stack([x_from_z(singles[k], z.phys[k]) for k in range(len(singles))])
    covariances, failed = [], []
    for k, single in enumerate(singles):
        try:
            covariances.append(
                _covariance_at(
                    single,
                    x[k],
                    z.take(k),
                    fitted.sigma[k],
                    fitted.step[k],
                    tuple(a[k] for a in fitted.lin),
                    batch.horizons[-1],
                )
            )
        except SimulationFailed:
            failed.append(batch.problem.log_names[k])
    if failed:
        raise RuntimeError(
            f"fit_independent: the simulation of log(s) {failed} at the fitted parameters failed; "
            "check bounds and solver settings"
        )
    return x, covariances

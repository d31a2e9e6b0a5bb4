"""`fit_independent`: every log its own values of every free parameter, fitted in one batch."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import flexdyn as fd

from .._data import noise_floor as nf
from .._data.channels import state_names
from .._model.parameters import Parameter, x_from_theta, x_from_z, z_from_x
from .._model.problem import Problem, check_same_parameters, guesses_of
from .jacobian import _covariance_at, _SimulationFailed
from .levenberg_marquardt import _check_budgets, _check_damping, _result_name, _solve
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
from .starts import _frequency_initialise_independent
from .steps import (
    GRID_COARSEN,
    GRID_ERROR,
    GRID_RECHECK,
    _coarser_steps,
    _default_horizons,
    _grid_errors,
    _grid_step,
    _padded_steps,
    _say_onsets,
    aligned_step,
)


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
    `problem`'s levels. Each result's `sigma` is its
    log's. Review: with make_problem's default weights (1 % of each channel's RMS) and the
    weights not re-estimated (as before), every log was fitted 5-9x above its noise floor.
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
    z1 = {
        "phys": jnp.asarray(z_from_x(problem, x0)),
        "y0": None,
        "offset": jnp.zeros(len(singles[0].offset_free)),
    }
    z = {
        "phys": jnp.tile(z1["phys"], (L, 1)),
        "y0": jnp.stack([jnp.asarray([q.y0_known[0, s] for _, s in q.y0_free], dtype=float) for q in singles]),
        "offset": jnp.tile(z1["offset"], (L, 1)),
    }
    # Spread the logs over all devices (`flexdyn.batch`): the batch is padded to a multiple
    # of the device count (repeating the last log) and placed with a NamedSharding over a
    # 1-D mesh of `jax.devices()`, so each vmapped stage is split across the devices. On
    # one device nothing is padded and this is the plain vmapped call. Only the first L
    # entries of each result are read.
    from flexdyn import batch as fbatch

    mesh = fbatch.batch_mesh()
    sigma0 = jnp.tile(jnp.asarray(problem.sigma), (L, 1))  # each log its own noise levels
    (stacked, z, sigma0), _ = fbatch.shard_batch((stacked, z, sigma0), mesh)
    estimate_noise = _noise_to_estimate(problem, estimate_noise)
    estimated = [j for j, c in enumerate(problem.channels) if c in estimate_noise]
    rounds = NOISE_ROUNDS if estimated else 1
    horizons = list(horizons) if horizons is not None else _default_horizons(problem, n_stages)
    _say_onsets(problem, horizons, say)
    # The stage-step simulations run each device's share on its own
    # (`flexdyn.batch.sharded_vmap`): XLA's partitioning of the vmapped program replicated
    # a division in it (6 "[SPMD] Involuntary full rematerialization ... _grid_step/div"
    # warnings, 3 flexible-pendulum logs on 4 CPU devices; none since, same results). The
    # Levenberg-Marquardt program stays a vmapped call on the sharded batch (6 such
    # warnings of its own remain): lineax's linear solve fails its structure check inside
    # `shard_map` (jax 0.10; lineax issue #185, "pytree does not match out_structure").
    grid = fbatch.sharded_vmap(_grid_step, (0, 0, None, None), mesh)
    errors_of = fbatch.sharded_vmap(_grid_errors, (0, 0, None, 0, 0, 0, None), mesh)

    def stage_steps(z, sigma, h, k_stage, coarsen=True):
        """Each log's constant step for a stage at horizon `h` (`_stage_step`, per log:
        aligned with its torque samples, coarsened within `grid_error`); padding entries
        repeat the last log. Also each log's tight step and the adaptive outputs."""
        adaptive, ok, reference = grid(stacked, z, jnp.asarray(h), grid_safety)
        if not bool(jnp.all(ok)):
            failed = [singles[k].log_names[0] for k in range(L) if not bool(ok[k])]
            raise RuntimeError(
                f"fit_independent: the simulation of log(s) {failed} at their current parameters failed "
                f"(stage {k_stage + 1}, horizon {float(h):g} s)"
            )
        n = adaptive.shape[0]
        tight = [float(aligned_step(singles[min(k, L - 1)], adaptive[k])) for k in range(n)]
        chosen = list(tight)
        tried = [_coarser_steps(singles[min(k, L - 1)], adaptive[k], tight[k]) for k in range(n)]
        if grid_error and coarsen and any(tried):
            # (a log with nothing to try pads with its coarsest factor, unaligned: not read)
            padded = jnp.stack(
                [_padded_steps(tried[k], tried[k][0] if tried[k] else tight[k] * GRID_COARSEN[0]) for k in range(n)]
            )
            errors = np.asarray(
                errors_of(stacked, z, jnp.asarray(h), padded, reference, sigma, jnp.asarray(grid_error, dtype=float))
            )
            for k in range(n):
                passing = [step for step, e in zip(tried[k], errors[k]) if e <= grid_error]
                chosen[k] = passing[0] if passing else tight[k]
        return jnp.asarray(chosen, dtype=adaptive.dtype), jnp.asarray(tight, dtype=adaptive.dtype), reference

    solve = eqx.filter_vmap(_solve, in_axes=(0, 0, 0, None, 0, None, None, None, None, None))
    if frequency_init:
        z = _frequency_initialise_independent(problem, singles, stacked, z, x0, grid, grid_safety, say)

    def grow(z, sigma, label=""):
        """The growing horizon for the whole batch from `z` with noise levels `sigma`
        `(L', C)`, then the noise re-estimation rounds at the full horizon: the last
        stage's `z`, noise levels, steps, linearisation (on the host) and every log's stage
        records."""
        stages = [[] for _ in range(L)]
        for rnd in range(rounds):
            for k_stage, h in enumerate(horizons if rnd == 0 else horizons[-1:]):
                step, _, _ = stage_steps(z, sigma, h, k_stage)
                tau = jnp.asarray(first_damping if rnd == 0 and k_stage == 0 else 0.0, dtype=float)
                z, lin = stage(z, sigma, h, step, tau, stages, label)
            if grid_error:  # the steps checked again at the optimum (`GRID_RECHECK`, as in `fit`)
                _, tight, reference = stage_steps(z, sigma, h, len(horizons), coarsen=False)
                padded = jnp.tile(step[:, None], (1, len(GRID_COARSEN)))
                errors = np.asarray(
                    errors_of(stacked, z, jnp.asarray(h), padded, reference, sigma, jnp.asarray(jnp.inf, dtype=float))
                )[:, 0]
                off = [
                    k
                    for k in range(L)
                    if float(step[k]) > float(tight[k]) * (1 + 1e-9) and not errors[k] <= GRID_RECHECK * grid_error
                ]
                if off:
                    say(
                        f"  {label}integration steps of log(s) {[singles[k].log_names[0] for k in off]} are over "
                        f"{GRID_RECHECK * grid_error:g} noise levels off at their optimum: the last stage again at "
                        "their tight steps"
                    )
                    step = jnp.where(jnp.isin(jnp.arange(step.shape[0]), jnp.asarray(off)), tight, step)
                    z, lin = stage(z, sigma, h, step, jnp.asarray(0.0, dtype=float), stages, label)
            lin = [np.asarray(a) for a in lin]  # one host transfer, not one per log
            if rnd + 1 < rounds:
                new = _reestimate_sigma_per_log(quality(z, sigma, step, lin), sigma, estimated)
                change = float(np.max(np.abs(np.log(new[:L] / np.asarray(sigma)[:L]))))
                if rnd > 0 and change < math.log1p(NOISE_AGREEMENT):
                    say(
                        f"  {label}noise re-estimated again: every log's within {100 * NOISE_AGREEMENT:g} % "
                        "of its weights"
                    )
                    break
                sigma = jax.device_put(jnp.asarray(new), sigma.sharding)
                say(f"  {label}noise re-estimated per log: " + _noise_range_text(problem.channels, new[:L], estimated))
        return z, sigma, step, lin, stages

    def stage(z, sigma, h, step, tau, stages, label):
        """One stage of the whole batch at horizon `h` with the logs' steps `step`; each
        log's record is appended to `stages`."""
        z, result, steps, cost, lin = solve(
            stacked, z, sigma, jnp.asarray(h), step, max_steps, tau, max_steps, rtol, atol
        )
        for k in range(L):
            stages[k].append(
                {
                    "horizon_s": float(h),
                    "iterations": int(steps[k]),
                    "cost": float(cost[k]),
                    "result": _result_name(jax.tree_util.tree_map(lambda a: a[k], result)),
                }
            )
        say(f"  {label}horizon {h:8.3f} s: {int(jnp.max(steps)):3d} iterations (slowest of {L} logs)")
        return z, lin

    def quality(z, sigma, step, lin):
        """Each log's `_residual_ms` at `z` (every sample: the last stage's horizon)."""
        return [
            _residual_ms(
                singles[k],
                {key: v[k] for key, v in z.items()},
                sigma[k],
                step[k],
                (tuple(a[k] for a in lin), horizons[-1]),
            )
            for k in range(L)
        ]

    z_start = z
    z, sigma, step, lin, stages = grow(z, sigma0)
    ms = quality(z, sigma, step, lin)
    floors = [noise_floors(q) for q in singles]
    scores = np.asarray([nf.score(ms[k], *floors[k]) for k in range(L)])
    poor = [k for k in range(L) if any(q["poor"] for q in nf.goodness(problem.channels, ms[k], *floors[k]).values())]
    good = [k for k in range(L) if k not in poor]
    if restart_poor_fit and poor and good:
        # A log left far above its noise floor while others fit theirs: grow its horizon
        # again from the good logs' median parameters (a wrong basin is that log's alone;
        # a model that misses an effect leaves every log poor, and nothing is retried).
        # The same compiled programs: the batch keeps its size, the good logs restart
        # where they were and keep their first results.
        say(
            f"  log(s) {', '.join(problem.log_names[k] for k in poor)} left far above the noise floor: "
            f"growing the horizon again from the median of the other {len(good)} log(s)' parameters"
        )
        phys = np.asarray(z["phys"]).copy()
        phys[poor] = np.median(phys[good], axis=0)
        y0 = np.asarray(z["y0"]).copy()
        y0[poor] = np.asarray(z_start["y0"])[poor]
        off = np.asarray(z["offset"]).copy()
        off[poor] = np.asarray(z_start["offset"])[poor]
        z2 = {key: jax.device_put(v, z[key].sharding) for key, v in (("phys", phys), ("y0", y0), ("offset", off))}
        # the poor logs start again from the problem's noise levels too (their re-estimated
        # ones are their poor residuals')
        redo = np.zeros(sigma.shape[0], bool)
        redo[poor] = True
        sigma_start = jax.device_put(jnp.where(jnp.asarray(redo)[:, None], sigma0, sigma), sigma.sharding)
        z2, sigma2, step2, lin2, stages2 = grow(z2, sigma_start, "again: ")
        ms2 = quality(z2, sigma2, step2, lin2)
        better = [k for k in poor if nf.score(ms2[k], *floors[k]) < scores[k]]
        say(f"  kept the new fit of {len(better)} of {len(poor)} log(s)")
        if better:
            pick = np.zeros(z["phys"].shape[0], bool)
            pick[better] = True
            z = {
                key: jax.device_put(
                    np.where(pick.reshape(-1, *[1] * (np.ndim(v) - 1)), np.asarray(z2[key]), np.asarray(v)), v.sharding
                )
                for key, v in z.items()
            }
            step = jnp.where(jnp.asarray(pick), step2, step)
            sigma = jnp.where(jnp.asarray(pick)[:, None], sigma2, sigma)
            lin = [np.where(pick.reshape(-1, *[1] * (a.ndim - 1)), a2, a) for a, a2 in zip(lin, lin2)]
            for k in better:
                stages[k], ms[k] = stages[k] + stages2[k], ms2[k]
    say("  computing standard errors (exact Jacobians at the optima) ...")
    x = jnp.stack([x_from_z(singles[k], z["phys"][k]) for k in range(L)])
    cov_blocks, failed = [], []
    for k in range(L):
        try:
            cov_blocks.append(
                _covariance_at(
                    singles[k],
                    x[k],
                    {key: v[k] for key, v in z.items()},
                    sigma[k],
                    step[k],
                    tuple(a[k] for a in lin),
                    horizons[-1],
                )
            )
        except _SimulationFailed:
            failed.append(problem.log_names[k])
    if failed:
        raise RuntimeError(
            f"fit_independent: the simulation of log(s) {failed} at the fitted parameters failed; "
            "check bounds and solver settings"
        )
    wall = (time.perf_counter() - start) / L
    results = [
        _finish(
            singles[k],
            parameters,
            {key: v[k] for key, v in z.items()},
            x[k],
            sigma[k],
            step[k],
            cov_blocks[k][0],
            stages[k],
            wall,
            ms[k],
            cov_blocks[k][1],
        )
        for k in range(L)
    ]
    return [dataclasses.replace(r, batch_size=L, sigma_estimated=tuple(estimate_noise)) for r in results]

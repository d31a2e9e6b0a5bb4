r"""Model discrepancy: show what the fitted simulation gets wrong, name the cause, extend
the model, and measure the gain on held-out data.

`diagnose(experiment)` (or `diagnose_logs(...)` on in-memory logs):

1. **Baseline.** Fit the experiment's model (`identify.fit`), holding data out: the
   experiment's validation logs; else, with several logs, the last one; else a time split
   (the last 30 % of the log is a held-out segment whose initial state is estimated).
2. **Evidence** (`identify.evidence`): residual RMS per channel and time window, residual
   spectrum peaks against the model's modes, decay envelope law, frequency drift,
   whiteness, correlation of the residual with features of the motion.
3. **Candidates** (`identify.catalogue`): every applicable catalogue entry (the others are
   listed with the reason in `Diagnosis.not_tried`) is fitted starting from the baseline
   optimum (the baseline's parameters and nuisances refitted with it; several starting
   magnitudes per entry). The continuous entries share one
   model in which every extension is present at its neutral value, so they are fitted
   together in one `vmap`ped Levenberg-Marquardt call (one compilation for all of them);
   the structural ones (`missing_mode`, `joint_elasticity`, `geometric_stiffening`) are
   models of their own.
4. **Scores.** For each candidate with `k` new parameters, on the fit data (`N` weighted
   residuals, noise levels fixed at the baseline's): the Bayesian information criterion
   change `dBIC = N ln(RSS_c / RSS_0) + k ln N`, and the F-test p-value of the
   nested-model comparison; on the held-out data (parameters fixed, only each held-out
   log's own initial state/offsets re-estimated, and its own values of per-log
   parameters, `Parameter.per_log`): the RMS gain `RMS_0 / RMS_c`.
   A candidate is **accepted** when `dBIC < -bic_threshold` (default 10: "very strong"
   evidence on Kass and Raftery's scale) **and** its held-out gain is at least
   `min_gain` (default 1.1); the accepted candidate with the lowest dBIC wins. If none
   is accepted, no cause is named and the evidence is shown.
5. **Pairs.** When no entry is accepted alone but the best continuous one fits the data
   far better (dBIC < -bic_threshold) and fails on the held-out data, it is fitted
   together with each other continuous entry (screened like single entries); a pair is
   accepted by the same two tests, with k = both entries' parameters, and both are named
   (`Cause.together_with`). Two effects can be needed at once: on the real single
   pendulum air drag alone fits the large swings and mispredicts the small ones, dry
   friction alone fits nothing; together they generalise.
6. **Stacking.** After a win, the search runs again from the extended model (the
   accepted effects' parameters stay free), up to `max_effects` rounds. The extended
   model is first refitted alone to convergence (from the same start the next round's
   candidates get), so that a later candidate is credited only with what its own
   parameters add. A structural winner changes the model's coordinates, which the joint
   model cannot hold: the search goes on (`diagnose_logs` again) from the structural
   model as a new baseline, with every accepted effect's parameters free, the accepted
   labels excluded (but `missing_mode`: a link may miss several modes, so the model that
   gained one is offered the next), and the remaining rounds; the two searches are then
   reported as one (`_stacked`). A structural candidate is refitted in a later round only if the cost it
   took off the model of its last round would pass the BIC test against the current one
   (`_promising`): each is a model of its own, the expensive part. None is fitted when
   the current model's held-out residual (the baseline's in the first round) is already
   at its own noise floor (`held_out_headroom`): no candidate could then reach the
   held-out gain `min_gain` (`Diagnosis.notes` says so). A structural candidate whose model holds the current one
   as a limit (`catalogue.NESTED_LIMIT`: an elastic joint stiff enough is the rigid one)
   but whose fit ends above it stopped in a local minimum; the notes say so, since its
   rejection is then no evidence against the effect (`_stuck_above_nested`). So do they
   for a continuous candidate whose fit ends above the model it extends at its neutral
   values, for a baseline with parameters its fit logs do not determine (no
   interval: `identify.covariance`), a degeneracy every candidate inherits, and for a
   last round whose best fit predicts the held-out logs worse
   (`_fits_but_does_not_predict`: with a sensor calibration candidate, per-log offsets
   are the usual cure).

The result (`Diagnosis`) holds the baseline fit, the evidence, every candidate's scores,
the accepted causes with their parameters and 95 % intervals (from the exact Jacobian
of the final extended fit), and the gain per channel, next to each channel's noise floor
on the held-out logs, estimated from their samples without any model
(`identify.noise_floor`): what a model that explains the data reaches. A channel whose
extended model's held-out residual is still above `noise_floor.POOR_FIT` (2) floors is
reported as left unexplained (`Diagnosis.left_unexplained`). `identify.write_report`
writes the JSON and Markdown report with plots.
"""

from __future__ import annotations

import dataclasses
import math
import time
import types
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from scipy import stats

import flexdyn as fd
from flexdyn._checks import error_reason

from . import catalogue as cat, covariance, evidence as ev, measurement as meas, noise_floor as nf
from .fit import (
    Z95,
    FitResult,
    Parameter,
    Problem,
    SimulationFailed,
    _at_bounds,
    _initial_states,
    _offsets,
    _predict_jit,
    _residuals_from,
    _x_from_z,
    _z_from_x,
    aligned_step,
    exp_natural,
    fit,
    fitted_outputs,
    make_problem,
)
from .residuals import log_blocked, log_jacobian

# ---------------------------------------------------------------------------
# Held-out split
# ---------------------------------------------------------------------------


def split_logs(fit_logs, validation_logs, fraction: float = 0.7):
    """`(fit_logs, held_out_logs, description)`: the validation logs if any; else the last
    of several logs; else a time split of the single log at `fraction` of its length."""
    fit_logs, validation_logs = list(fit_logs), list(validation_logs)
    if validation_logs:
        names = ", ".join(v.name for v in validation_logs)
        return fit_logs, validation_logs, f"whole logs held out (the experiment's validation logs: {names})"
    if len(fit_logs) >= 2:
        return fit_logs[:-1], fit_logs[-1:], f"whole log held out (the last log, {fit_logs[-1].name})"
    (log,) = fit_logs
    k = int(fraction * len(log.t))
    t = np.asarray(log.t, float)
    first = dataclasses.replace(
        log,
        t=t[:k],
        outputs={c: np.asarray(v)[:k] for c, v in log.outputs.items()},
        torque=None if log.torque is None else np.asarray(log.torque)[:k],
        name=f"{log.name}[:{k}]",
    )
    rest_initial = _segment_initial(t[k:], {c: np.asarray(v)[k:] for c, v in log.outputs.items()})
    # the held-out segment starts mid-motion: its link angles and rates are estimated (from
    # the guesses above), with whatever else the log already estimated at its start
    rest_fit = tuple(dict.fromkeys((*log.fit_initial, *rest_initial)))
    second = dataclasses.replace(
        log,
        t=t[k:],
        outputs={c: np.asarray(v)[k:] for c, v in log.outputs.items()},
        torque=None if log.torque is None else np.asarray(log.torque)[k:],
        initial=rest_initial,
        fit_initial=rest_fit,
        name=f"{log.name}[{k}:]",
    )
    desc = (
        f"time split: the first {100 * fraction:.0f} % of {log.name} fits, the last {100 * (1 - fraction):.0f} % "
        f"(t >= {t[k]:.3g} s) is held out, its initial state estimated"
    )
    return [first], [second], desc


def _segment_initial(t, outputs, n: int = 9) -> dict:
    """Initial-state guesses of a segment from its measured link angles: angle and rate at
    `t[0]` from a least-squares quadratic through the first `n` samples (a mean or a line
    would be biased by the rate and the acceleration of a swinging link)."""
    init = {}
    n = min(len(t), n)
    for c, v in outputs.items():
        if c.startswith("theta") or c.startswith("alpha"):
            deg = min(2, n - 1)
            coef = np.polyfit(np.asarray(t[:n]) - t[0], np.asarray(v[:n], float), deg)
            init[c] = float(coef[-1])
            init[f"{c}_rate"] = float(coef[-2]) if deg >= 1 else 0.0
    return init


# ---------------------------------------------------------------------------
# The joint model of all continuous candidates
# ---------------------------------------------------------------------------

SLOTS = 4  # extension parameters one fit can free at a time (accepted + candidate)


class _Joint(eqx.Module):
    """The superset problem and the layout of its parameter vector: the baseline's free
    parameters (first `nb`), then every extension parameter."""

    problem: Problem
    neutral: jax.Array  # (n_ext,) neutral values of the extension parameters
    nb: int = eqx.field(static=True)


def _theta(j: _Joint, xb, xe, idx, logf):
    p = j.problem
    tb = [exp_natural(xb[i]) if p.log_scale[i] else xb[i] for i in range(j.nb)]
    tb = jnp.stack(tb) if tb else jnp.zeros((0,))
    safe = jnp.where(logf, xe, 0.0)
    ve = jnp.where(logf, exp_natural(safe), xe)
    te = jnp.concatenate([j.neutral, jnp.zeros(1)]).at[idx].set(ve)[:-1]
    return jnp.concatenate([tb, te])


def _bounds(j: _Joint):
    return types.SimpleNamespace(lower=j.problem.lower[: j.nb], upper=j.problem.upper[: j.nb])


def _unpack(args):
    j, idx, logf, sigma, step = args
    return j.problem, lambda v: _theta(j, _x_from_z(_bounds(j), v["zb"]), v["xe"], idx, logf), sigma, None, step


def _residual(v, args):
    problem, theta_of, sigma, horizon, step = _unpack(args)
    return _residuals_from(problem, theta_of(v), v["y0"], v["offset"], sigma, horizon, step)[0]


_residual_lm = log_blocked(_unpack)  # same value, one forward-mode pass per log per LM step


@eqx.filter_jit
def _fit_batch(j: _Joint, v0, idx, logf, sigma, step, max_steps: int):
    """Levenberg-Marquardt for a batch of (start, slot layout) pairs, vmapped."""
    solver = optx.LevenbergMarquardt(rtol=1e-4, atol=1e-10, norm=optx.rms_norm)

    def one(v0, idx, logf):
        args = (j, idx, logf, sigma, step)
        sol = optx.least_squares(_residual_lm, solver, v0, args=args, max_steps=max_steps, throw=False)
        r = _residual(sol.value, args)
        return sol.value, jnp.sum(r**2), sol.stats["num_steps"]

    return jax.vmap(one)(v0, idx, logf)


@eqx.filter_jit
def _jacobian(j: _Joint, xb, xe, y0, off, idx, logf, sigma, step):
    """Residuals and their Jacobian w.r.t. (xb, xe, y0, offsets), columns in that order."""
    theta_of = lambda w: _theta(j, w["xb"], w["xe"], idx, logf)  # noqa: E731
    jac = log_jacobian(j.problem, theta_of, {"xb": xb, "xe": xe}, y0, off, sigma, None, step)
    return jac.r.reshape(-1), jac.dense(len(j.problem.y0_free), len(j.problem.offset_free))


_predict = _predict_jit  # shared with identify.fit.fitted_outputs: one compiled program


Z_SATURATION = 6.0


def _unsaturated(j: _Joint, zb):
    """`zb` with every bounded coordinate pulled back to at most `Z_SATURATION` inside its
    transform's linear range. A baseline parameter that the misspecified baseline pushed
    onto its bound sits where the sigmoid (softplus) is flat (z ~ -50: dx/dz ~ 1e-22), and
    Levenberg-Marquardt cannot move it back when the extension makes the bound no longer
    optimal (seen: a sensor gain error drove the pendulum's hub inertia onto its lower
    bound; with the gain free the true inertia was unreachable). At |z| = 6 the parameter
    moves by at most 0.25 % of its (log-)range and regains a usable gradient."""
    lo, hi = np.asarray(j.problem.lower[: j.nb]), np.asarray(j.problem.upper[: j.nb])
    z = np.asarray(zb, float).copy()
    low = np.isfinite(lo) & (z < -Z_SATURATION)
    high = np.isfinite(hi) & (z > Z_SATURATION)
    z[low] = -Z_SATURATION
    z[high] = Z_SATURATION
    return jnp.asarray(z)


MAX_REFINEMENTS = 8

#: The candidates are fitted at the baseline's tight constant step (`identify.fit`'s
#: `grid_error=None`), which a candidate may need finer: dry friction is a stiff damper at
#: rest. At the best candidate's fit, when its outputs at that step are more than this many
#: noise levels off, the candidates' fits go on at the coarsest of the step over
#: `STEP_DIVISORS` within it, and so does the search (`_finer_step`). Measured on the
#: shipped example (`identify/examples/pendulum_friction`, friction model, N = 1602): at the
#: baseline's 8.9 ms the friction model was 0.33 noise levels off, its cost at the optimum
#: 32 too high (1634 against 1602: a BIC shift of 32), and two runs ended 10 apart in cost
#: and 0.8 standard errors apart in the friction torque. At 0.06 noise levels (5.5 ms) the
#: fitted values were 0.1-0.17 standard errors from those at a 10x finer step (cost 0.8
#: apart): this bar keeps a candidate's values within ~0.1 of their standard errors.
STEP_RECHECK = 0.05
#: `_finer_step`: the steps tried, as divisors of the round's step, coarsest first ...
STEP_DIVISORS = (2, 4, 8)
#: ... against the outputs at the step over this (Tsit5 is fifth order: 16x finer is ~1e6
#: times more accurate, a reference without an adaptive solve of its own to compile; on
#: the friction model, whose error falls irregularly with the step, the reference at
#: 0.55 ms was 9e-5 noise levels off one at 0.14 ms)
REFERENCE_DIVISOR = 16

#: `_refine` and `reconverge` continue one or a few fits of a round. Padded to the round's
#: batch size they reuse its compiled program, but every padded copy costs as much as a
#: fit (on CPU a vmapped member is a fit of its own). When the round's batch call took longer
#: than this (seconds: compiling plus running), they run at the smallest batch size that holds
#: them instead (`_few_size`), paying one compilation (10-60 s on 2 cores) to save the copies.
#: Seen on the spinning link (`identify/examples/spinning_link`): 3 rounds of 1 unconverged
#: fit padded to 6 took 225 s each, the round's call 339 s. Below it (the pendulum examples:
#: calls of 5-20 s, mostly compilation), a second program would cost more than the copies.
FEW_SIZE_AFTER_S = 60.0


def _few_size(n: int, size: int, call_s: float) -> int:
    """The batch size for continuing `n` fits of a round whose batch size was `size` and
    whose batch call took `call_s` seconds (`FEW_SIZE_AFTER_S`)."""
    if call_s <= FEW_SIZE_AFTER_S:
        return size
    return min(size, next(b for b in (1, 3, 6, 12, 24, size) if b >= n))


def _refine(
    joint, vs, costs, steps, best, owners, idx, logf, sigma, step, max_steps, size, cost_cur, N, say, predicted=None
):
    """Continue the fits of the candidates that improve on the current model (dBIC < 0)
    but ran out of Levenberg-Marquardt steps, `max_steps` at a time (the same compiled
    program), until each converges or its dBIC moves by less than 0.1 per round (at most
    `MAX_REFINEMENTS` rounds; `size`: the round's `(batch size, seconds its call took)`,
    `_few_size`). A winner's scores and 95 % intervals must be those of its
    optimum: seen, a sensor-gain candidate whose fit moved the pendulum's hub inertia 5.3
    in log from its bound needed 40 steps, and at 25 its held-out prediction was 2.6x
    worse than the baseline's. Candidates drifting to their neutral value (dBIC > 0 and no
    prediction below 0: a log-scale parameter sliding towards zero never "converges") and
    those far behind the best one (dBIC above half the lowest) are left alone: they cannot
    win.

    `predicted`: label -> the cost the screening's Gauss-Newton step predicted. A fit that
    ran out of steps short of it counts as a contender at the predicted dBIC: seen on the
    real pendulum, dry friction predicted 3656 against the baseline's 9167 (the best
    prediction of the round) ended 25 steps at 9193, above the model it extends, and was
    never continued."""
    by_label = {c.label: c for c in owners}
    predicted = predicted or {}

    def dbic(cost, lab):
        return N * math.log(max(cost, 1e-300) / cost_cur) + len(by_label[lab].params) * math.log(N)

    for _ in range(MAX_REFINEMENTS):
        reached = {b: dbic(costs[b], lab) for lab, b in best.items()}
        # a fit short of its prediction is judged by the prediction; the bar is set by the
        # fits (a screening step's prediction can be optimistic, and must not lift the bar)
        judged = {b: min(reached[b], dbic(predicted.get(lab, np.inf), lab)) for lab, b in best.items()}
        lowest = min(reached.values(), default=0.0)
        # only the contenders: those within half the best candidate's dBIC of it
        more = [b for b in best.values() if steps[b] >= max_steps and judged[b] < 0 and judged[b] <= 0.5 * lowest]
        if not more:
            break
        n = _few_size(len(more), *size)
        say(f"  continuing {len(more)} unconverged fit(s) for {max_steps} more steps (batch of {n}) ...")
        sel = np.asarray(more, dtype=int)
        v0 = {k: v[sel] for k, v in vs.items()}
        out, c2, s2 = _fit_batch(joint, _pad(v0, n), _pad(idx[sel], n), _pad(logf[sel], n), sigma, step, max_steps)
        c2, s2 = np.asarray(c2, dtype=float), np.asarray(s2)
        moved = False
        for i, b in enumerate(more):
            if np.isfinite(c2[i]) and c2[i] < costs[b]:
                improving = N * (costs[b] - c2[i]) / costs[b] >= 0.1
                moved |= improving
                vs = {k: v.at[b].set(out[k][i]) for k, v in vs.items()}
                costs[b] = c2[i]
                # a start that stopped improving counts as converged
                steps[b] = s2[i] if improving else 0
            else:
                steps[b] = 0
        if not moved:
            break
    return vs, costs


@dataclasses.dataclass(frozen=True)
class _HeldOut:
    """`detection_limits`: the held-out logs at the model of the search's end."""

    joint: _Joint  # the joint model on the held-out problem
    y0: jax.Array  # their initial-state entries and offsets, refitted at that model
    offset: jax.Array
    used: np.ndarray
    cost: float  # their weighted cost at that model
    xb: jax.Array  # the held-out problem's baseline entries there (natural coordinates)
    # for each of them, its entry among the fit's baseline entries; -1: a held-out log's own
    # value of a per-log parameter (`Parameter.per_log`), refitted there like a nuisance
    source: tuple[int, ...]


def detection_limits(
    j: _Joint, current: dict, candidates, ext_names, used, sigma, step, bic_threshold: float, held: _HeldOut, min_gain
):
    """The smallest value of each parameter of each continuous candidate that would have
    been named had it been in the logs, linearised at the model `current` (the search's
    final one: `v`, `cost`, `layout`, `idx`, `logf`): `{label: {parameter: (limit,
    criterion)}}` (the limit in the parameter's SI unit, an offset from its neutral value;
    the criterion that sets it, "BIC" or "held-out gain"; inf where the logs cannot tell
    the parameter from the model's own to first order).

    An effect of size `a` in a parameter whose weighted-residual Jacobian column (at its
    neutral value) is `j` adds `a^2 |P j|^2` to the cost of a model without it, `P` the
    projector onto what the other columns cannot reproduce (the Gauss-Newton prediction
    the screening uses). On the fit logs the other columns are every free parameter of the
    model and of the candidate, initial state and offset; the BIC test, `N ln(1 - drop /
    C) + k ln N < -bic_threshold`, asks `|a| >= sqrt(C (1 - exp(-(bic_threshold + k ln
    N) / N))) / |P j|`, C the model's cost, k the candidate's parameters. A model without
    the effect fitted to such logs moves its own parameters to absorb part of it (`-a c`,
    `c` the coefficients of that projection), and on the held-out logs, where only their
    own initial states and offsets (and own values of per-log parameters) are refitted, it
    misses `a h`, `h = P_h (j_h - J_h c)` (`J_h`, `c`: the parameters they share);
    the held-out gain `sqrt((C_h + a^2 |h|^2) / C_h) >= min_gain` asks `|a| >=
    sqrt((min_gain^2 - 1) C_h) / |h|`, C_h the model's held-out cost. The limit is the
    larger. Noise moves the realised drop and gain about these values: an effect at its
    limit is named about half the time. The linearisation holds while the effect is small
    against the motion (a dead band or a delay comparable with the motion's time scale is
    not). Oracle: the search itself (tests/identify/test_diagnose.py): dry friction hidden
    in simulated pendulum logs at 1.5x its limit is named, at 0.67x not (over 12 seeds:
    12/12, 0/12; at 1.0x 7/12)."""
    nb = j.nb
    n_layout = len(current["layout"])
    v = current["v"]
    xb = _x_from_z(_bounds(j), v["zb"])
    N = int(np.sum(used))
    out = {}

    def seen(column, others):
        """|P column|, P the projector onto what `others` cannot reproduce; the coefficients."""
        coef, *_ = np.linalg.lstsq(others, column, rcond=None)
        norm = float(np.linalg.norm(column - others @ coef))
        # (below round-off of the column: the other parameters reproduce it)
        return (norm if norm > 1e-9 * float(np.linalg.norm(column)) else 0.0), coef

    for c in candidates:
        if n_layout + len(c.params) > SLOTS:
            continue
        idx = np.asarray(current["idx"]).copy()
        logf = np.asarray(current["logf"]).copy()
        xe = np.asarray(v["xe"], float).copy()
        for s, n in enumerate(c.params, start=n_layout):
            idx[s] = ext_names.index(n)
            logf[s] = False
            xe[s] = float(j.neutral[ext_names.index(n)])
        idx, logf, xe = jnp.asarray(idx), jnp.asarray(logf), jnp.asarray(xe)
        J = np.asarray(_jacobian(j, xb, xe, v["y0"], v["offset"], idx, logf, sigma, step)[1])[used]
        Jh = np.asarray(_jacobian(held.joint, held.xb, xe, held.y0, held.offset, idx, logf, sigma, step)[1])
        Jh = Jh[held.used]
        nh = held.joint.nb
        # held-out columns: the shared ones, paired with the fit's; a held-out log's own
        # values (`_HeldOut.source` -1) are refitted there, with its nuisances
        shared_h = [i for i, src in enumerate(held.source) if src >= 0]
        nuisance_h = [i for i, src in enumerate(held.source) if src < 0] + list(range(nh + SLOTS, Jh.shape[1]))
        k = len(c.params)
        drop = current["cost"] * -math.expm1(-(bic_threshold + k * math.log(N)) / N)
        excess = (min_gain**2 - 1.0) * held.cost
        per = {}
        for s, n in enumerate(c.params, start=n_layout):
            col = nb + s
            model = [i for i in range(nb + SLOTS) if i != col]  # the model's parameters
            fit_seen, coef = seen(J[:, col], J[:, model + list(range(nb + SLOTS, J.shape[1]))])
            # held out: the effect less what the model's parameters absorbed of it on the
            # fit logs (those the held-out logs share), less what the held-out logs' own
            # unknowns absorb
            of_model = dict(zip(model, coef[: len(model)]))
            cols_h = shared_h + [nh + t for t in range(SLOTS) if t != s]
            coef_h = np.asarray(
                [of_model[held.source[i]] for i in shared_h] + [of_model[nb + t] for t in range(SLOTS) if t != s]
            )
            ho_seen, _ = seen(Jh[:, nh + s] - Jh[:, cols_h] @ coef_h, Jh[:, nuisance_h])
            a_bic = math.sqrt(drop) / fit_seen if fit_seen > 0 else math.inf
            a_gain = math.sqrt(excess) / ho_seen if ho_seen > 0 else math.inf
            per[n] = (a_bic, "BIC") if a_bic >= a_gain else (a_gain, "held-out gain")
        out[c.label] = per
    return out


def _pad(tree, size: int):
    """Pad the leading axis of every leaf to `size` by repeating its first row."""

    def pad(a):
        a = jnp.asarray(a)
        n = a.shape[0]
        if n >= size:
            return a
        return jnp.concatenate([a, jnp.repeat(a[:1], size - n, axis=0)], axis=0)

    return jax.tree_util.tree_map(pad, tree)


@eqx.filter_jit
def _cost(j: _Joint, v, idx, logf, sigma, step):
    return _residual(v, (j, idx, logf, sigma, step))


@eqx.filter_jit
def _screen(j: _Joint, xb, xes, y0, off, idx, logf, sigma, step):
    """Residuals and exact Jacobians at a batch of starting points (vmapped)."""
    return jax.vmap(lambda xe, i, lf: _jacobian(j, xb, xe, y0, off, i, lf, sigma, step))(xes, idx, logf)


class _Own(eqx.Module):
    """The held-out logs' own values of the per-log parameters (`Parameter.per_log`),
    re-estimated with their nuisances as `identify.evaluate_held_out` does: their entries
    `pos` of the held-out problem's parameter vector, the bounds of their natural
    coordinates (`lower`, `upper`; `identify.fit`'s transform) and which are log-scale."""

    pos: jax.Array  # (n_own,) int
    lower: jax.Array
    upper: jax.Array
    log_scale: tuple[bool, ...] = eqx.field(static=True)

    @staticmethod
    def of(problem: Problem) -> _Own:
        pos = sorted(i for _, index in problem.per_log for i in index)
        return _Own(
            jnp.asarray(pos, dtype=int),
            jnp.asarray(np.asarray(problem.lower)[pos], dtype=float),
            jnp.asarray(np.asarray(problem.upper)[pos], dtype=float),
            tuple(problem.log_scale[i] for i in pos),
        )

    def theta(self, theta, z):
        """`theta` with the own entries at the transformed coordinates `z`."""
        if not self.log_scale:
            return theta
        x = _x_from_z(self, z)
        values = jnp.stack([exp_natural(x[i]) if lg else x[i] for i, lg in enumerate(self.log_scale)])
        return theta.at[self.pos].set(values)

    def z_of(self, values) -> jax.Array:
        """The transformed coordinates of own values (SI)."""
        values = np.asarray(values, float)
        x = np.where(np.asarray(self.log_scale, bool), np.log(np.maximum(values, 1e-300)), values)
        return jnp.asarray(_z_from_x(self, x), dtype=float)


def _held_unpack(args):
    problem, theta, own, sigma, step = args
    return problem, lambda v: own.theta(theta, v["own"]), sigma, None, step


def _held_residual(v, args):
    problem, theta, own, sigma, step = args
    return _residuals_from(problem, own.theta(theta, v["own"]), v["y0"], v["offset"], sigma, None, step)[0]


_held_residual_lm = log_blocked(_held_unpack)


@eqx.filter_jit
def _held_out_batch(problem: Problem, thetas, v0, own: _Own, sigma, step, max_steps: int):
    """Weighted held-out residuals for a batch of parameter vectors (the held-out
    problem's), each held-out log's own unknowns re-estimated: its nuisances (`v0["y0"]`
    initial state entries, `v0["offset"]` offsets) and its own values of the per-log
    parameters (`v0["own"]`, at `own`'s entries). Returns the residuals, the re-estimated
    unknowns and the parameter vectors with the own values in."""
    solver = optx.LevenbergMarquardt(rtol=1e-4, atol=1e-10, norm=optx.rms_norm)

    def one(theta):
        args = (problem, theta, own, sigma, step)
        if v0["y0"].size + v0["offset"].size + v0["own"].size:
            v = optx.least_squares(_held_residual_lm, solver, v0, args=args, max_steps=max_steps, throw=False).value
        else:
            v = v0
        return _held_residual(v, args), v, own.theta(theta, v["own"])

    return jax.vmap(one)(thetas)


def _held_out_start(problem: Problem, own: _Own, base) -> dict:
    """The held-out unknowns' start: the logs' own initial-state values, zero offsets and,
    for each own value of a per-log parameter, the median of the fit logs' values
    (`base`: the baseline `FitResult`)."""
    names = [name for name, index in problem.per_log for _ in index]
    order = np.argsort([i for _, index in problem.per_log for i in index]).astype(int)
    medians = [float(np.median(list(base.per_log[n].values()))) for n in names]
    return {
        "y0": jnp.asarray([problem.y0_known[l, s] for l, s in problem.y0_free], dtype=float),
        "offset": jnp.zeros(len(problem.offset_free)),
        "own": own.z_of(np.asarray(medians, float)[order]) if names else jnp.zeros(0),
    }


# ---------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------


@dataclasses.dataclass
class Score:
    """One candidate's fit and scores (SI)."""

    name: str
    where: str
    params: dict  # name -> value
    cost: float
    delta_bic: float
    p_value: float
    held_out_rms: dict  # channel -> RMS (SI)
    held_out_gain: float
    accepted: bool
    k: int
    # not fitted: its cost and dBIC are those one Gauss-Newton step predicts (`_screen`), and
    # `screen_reason` says why that ranked it out
    screened: bool = False
    screen_reason: str = ""
    # structural candidates (a model of their own): name -> {std_error, ci95} of the new
    # parameters, from that model's fit (continuous ones get theirs from the joint model)
    intervals: dict = dataclasses.field(default_factory=dict)
    # two entries fitted together (the pair search): their labels; else empty
    members: tuple = ()
    # the standard error of `held_out_gain` from the held-out samples (`gain_standard_error`)
    held_out_gain_se: float = float("nan")

    @property
    def label(self) -> str:
        return cat.pair_label(self.members) if self.members else f"{self.name}:{self.where}"


@dataclasses.dataclass
class Cause:
    """An accepted model extension with its fitted parameters and 95 % intervals."""

    name: str
    where: str
    description: str
    parameters: dict  # name -> {value, std_error, ci95, unit}
    delta_bic: float
    held_out_gain: float
    # the other causes accepted together with this one (a pair found by the pair search;
    # `delta_bic` and `held_out_gain` are then the pair's)
    together_with: list = dataclasses.field(default_factory=list)
    # fitted values outside what the component plausibly does (`catalogue.implausible`)
    warnings: list = dataclasses.field(default_factory=list)
    held_out_gain_se: float = float("nan")  # `Score.held_out_gain_se`

    def marginal(self, min_gain: float) -> bool:
        """Whether the held-out gain is within two standard errors of the bar it passed."""
        return bool(np.isfinite(self.held_out_gain_se) and self.held_out_gain - min_gain < 2 * self.held_out_gain_se)


#: what `Diagnosis.detection_limits` are, as the summary and the report say it
DETECTION_LIMITS_MEANING = (
    "the smallest effect of each candidate not named that these logs would have let the search name, "
    "linearised at the final model (`identify.diagnose.detection_limits`; on simulated pendulum logs, dry "
    "friction at its limit was named in 7 of 12 trials, at 1.5x in 12 of 12, at 0.67x in none)"
)


def _limit_text(p: dict) -> str:
    """A detection limit as text: `0.0012 N m`, or `1 +- 0.0047` about a non-zero neutral value."""
    unit = f" {p['unit']}" if p["unit"] and p["unit"] != "1" else ""
    if p.get("neutral", 0.0) == 0.0:
        return f"{p['value']:.2g}{unit}"
    return f"{p['neutral']:g} +- {p['value']:.2g}{unit}"


@dataclasses.dataclass
class Diagnosis:
    """What `diagnose` found (see `summary()` and `to_dict()`)."""

    split: str
    baseline: FitResult
    evidence: dict
    rounds: list  # per round: list of Score (sorted by dBIC)
    causes: list  # Cause, in the order accepted
    held_out: dict  # {'baseline': {ch: rms}, 'extended': {ch: rms}, 'gain': {ch: ratio}, 'gain_total': ...}
    delta_bic_total: float
    fraction_explained: float
    # None when the baseline's held-out residual is not above the noise level (e.g. noise
    # "estimate"d from the baseline's own residual): there is no excess to explain
    fraction_of_excess_explained: float | None
    extended_chain: fd.Chain
    extended_measurement: meas.Measurement
    extended_parameters: dict
    outputs: dict  # per held-out and fit log: t, measured, baseline, extended
    modal_frequencies_hz: list
    wall_time: float
    # every parameter of the extended model (baseline and extensions): name -> {value,
    # std_error, ci95}, from the exact Jacobian of its final fit
    extended_intervals: dict = dataclasses.field(default_factory=dict)
    # weighted costs (sums of squared residuals over the noise) of the baseline and the
    # extended model on the fit and held-out data; N (`n_fit`, `n_held_out`) and the
    # number of added parameters `k`: what the totals are computed from
    costs: dict = dataclasses.field(default_factory=dict)
    # what the baseline model assumes that the logs may break (`evidence.stiffening_checks`:
    # a flexible link spinning or hanging enough to need geometric stiffening)
    model_checks: list = dataclasses.field(default_factory=list)
    # what the search decided not to try, and why: `{'round': n, 'text': ...}` (candidates
    # not refitted in round n, counted over the whole search)
    notes: list = dataclasses.field(default_factory=list)
    # the catalogue entries not tried at all, and why: name -> reason (an entry that does
    # not apply to the rig or the logs, one the caller excluded, one already in the model)
    not_tried: dict = dataclasses.field(default_factory=dict)
    # the smallest effect of each continuous candidate not named that these logs would have
    # let the search name (BIC test and held-out gain), linearised at the final model
    # (`detection_limits`): label -> {parameter: {"value", "criterion", "unit", "neutral"}},
    # "value" the offset from the neutral value (inf: not seen to first order)
    detection_limits: dict = dataclasses.field(default_factory=dict)
    # the held-out gain a cause had to reach (`diagnose_logs`' `min_gain`)
    min_gain: float = 1.1
    # the per-log parameters (`Parameter.per_log`) of the extended model: name -> {log:
    # value (SI)}, the fit logs' fitted with it (also in `extended_parameters` as
    # `name[log]`, with intervals), the held-out logs' refitted there like their initial
    # states (what the held-out scores were computed at)
    per_log: dict = dataclasses.field(default_factory=dict)
    # which logs of `per_log` are held out
    held_out_logs: tuple = ()

    def marginal_text(self, c) -> str:
        """What a cause's marginal held-out gain (`Cause.marginal`) means."""
        return (
            f"its held-out gain {c.held_out_gain:.4f}x is within two standard errors ({c.held_out_gain_se:.2g} "
            f"each) of the {self.min_gain:g}x bar it passed: as likely a chance pass as an effect; confirm it on "
            "more held-out data (or a noisy input column may be what it fits)"
        )

    @property
    def named(self) -> list[str]:
        return [c.name for c in self.causes]

    @property
    def left_unexplained(self) -> list[str]:
        """The channels whose held-out residual under the extended model is above
        `identify.noise_floor.POOR_FIT` times the held-out data's model-free noise floor."""
        floor = self.held_out.get("noise_floor", {})
        return [c for c, rms in self.held_out["extended"].items() if c in floor and rms > nf.POOR_FIT * floor[c]]

    @property
    def excess_explained_text(self) -> str:
        """`fraction_of_excess_explained` as text ("n/a ..." when there is no excess)."""
        if self.fraction_of_excess_explained is None:
            return "n/a, the baseline's held-out residual is not above the noise level"
        return f"{self.fraction_of_excess_explained:.3f}"

    @property
    def baseline_converged(self) -> bool:
        """Whether the baseline fit's solver converged (a parameter on its bound does not
        count against it here: in a diagnosis that is often the missing effect's symptom,
        and `notes` says so). `identify diagnose` exits 3 when it did not."""
        return self.baseline.stages[-1]["result"] == "successful"

    @property
    def extended_at_bounds(self) -> list[str]:
        """The baseline's parameters whose value in the extended model lies on one of
        their bounds (judged as `FitResult.at_bounds` is). Found in review: the real
        pendulum's `joint1.damping` went to its lower bound once air drag took over the
        damping, and nothing said so."""
        if not self.causes:
            return []
        problem = self.baseline.problem
        xs = []
        for name, log, value in zip(problem.names, problem.log_scale, self.baseline.values):
            v = float(self.extended_parameters.get(name, value))
            xs.append(math.log(v) if log and v > 0 else (-math.inf if log else v))
        return _at_bounds(problem, np.asarray(xs))

    def at_bound_lines(self) -> list[str]:
        """A sentence per parameter of `extended_at_bounds`."""
        return [
            f"{n} = {float(self.extended_parameters[n]):.5g} ended on a bound in the extended model: what it stood for "
            "in the baseline may now be carried by the named cause(s) (its interval is then meaningless), or its "
            "bound is too narrow (widen it if that is physical)"
            for n in self.extended_at_bounds
        ]

    def detection_limit_lines(self) -> list[str]:
        """One line per candidate not named: the smallest effect that would have been
        named, per parameter, and the criterion that sets it."""
        out = []
        for lab, per in self.detection_limits.items():
            parts = [
                f"{n} {_limit_text(p)} ({p['criterion']})"
                if math.isfinite(p["value"])
                else f"{n}: not seen apart from the model's own parameters (to first order)"
                for n, p in per.items()
            ]
            out.append(f"{lab}: {'; '.join(parts)}")
        return out

    def summary(self) -> str:
        lines = [f"held-out data: {self.split}", ""]
        if self.causes:
            lines.append("accepted causes:")
            for c in self.causes:
                lines.append(
                    f"  {c.name} at {c.where} ({c.description}): dBIC {c.delta_bic:.1f}, "
                    f"held-out gain {c.held_out_gain:.2f}x"
                    + (f" (SE {c.held_out_gain_se:.2g})" if np.isfinite(c.held_out_gain_se) else "")
                    + (f" (together with {', '.join(c.together_with)}: the pair's scores)" if c.together_with else "")
                )
                for n, p in c.parameters.items():
                    lines.append(
                        f"    {n} = {p['value']:.{covariance.digits(p['value'], p['std_error'])}g}"
                        + (f" {p['unit']}" if p["unit"] and p["unit"] != "1" else "")  # (a gain's "1" read as a typo)
                        + f" (SE {p['std_error']:.2g}, 95 % CI {covariance.interval_text(*p['ci95'])})"
                    )
                for w in c.warnings:
                    lines.append(f"    IMPLAUSIBLE: {w}")
                if c.marginal(self.min_gain):
                    lines.append(f"    MARGINAL: {self.marginal_text(c)}")
        else:
            lines.append("no catalogue entry explains the residual significantly (see the evidence and the scores)")
        for line in self.at_bound_lines():
            lines.append(f"on a bound: {line}")
        for check in self.model_checks:
            if check["flagged"]:
                lines.append(f"model check: {check['message']}")
        lines.append("")
        floor = self.held_out.get("noise_floor", {})
        lines.append(
            "held-out RMS per channel (baseline -> extended, gain; the data's model-free noise floor, "
            "identify.noise_floor):"
        )
        from .report import display_unit

        for c in self.held_out["baseline"]:
            k, unit = display_unit(c)  # (review: the console's values had no unit; SI rad beside report.md's deg)
            lines.append(
                f"  {c} ({unit}): {k * self.held_out['baseline'][c]:.4g} -> {k * self.held_out['extended'][c]:.4g} "
                f"({self.held_out['gain'][c]:.2f}x)" + (f"; floor {k * floor[c]:.4g}" if c in floor else "")
            )
        for c in self.left_unexplained:
            ratio = self.held_out["extended"][c] / floor[c]
            lines.append(
                f"  {c}: the {'extended' if self.causes else 'baseline'} model's held-out residual is still "
                f"{ratio:.3g} times the noise floor: an effect is left unexplained (or the noise is not white, "
                "or the logged input is noisy: noise on a torque column drives the model, not the rig)"
            )
        for name, by_log in self.per_log.items():
            unit = _unit(self.baseline.problem, name)
            unit = f" ({unit})" if unit and unit != "1" else ""
            fitted = ", ".join(f"{log} {v:.5g}" for log, v in by_log.items() if log not in self.held_out_logs)
            held = ", ".join(f"{log} {v:.5g}" for log, v in by_log.items() if log in self.held_out_logs)
            lines.append(
                f"per log: {name}{unit}: {fitted} (fitted)" + (f"; {held} (held out, refitted there)" if held else "")
            )
        lines.append(
            f"total dBIC {self.delta_bic_total:.1f}; fraction of the held-out residual explained "
            f"{self.fraction_explained:.3f} (of its excess over the noise: {self.excess_explained_text})"
        )
        lines.extend(f"note: {note_text(n)}" for n in self.notes)
        if self.not_tried:
            lines.append("not tried:")
            lines.extend(f"  {n}: {why}" for n, why in self.not_tried.items())
        if self.detection_limits:
            lines.append(f"detection limits ({DETECTION_LIMITS_MEANING}):")
            lines.extend(f"  {text}" for text in self.detection_limit_lines())
        for r, scores in enumerate(self.rounds, start=1):
            lines.append("")
            lines.append(f"round {r}: candidates (best first)")
            w = max([34] + [len(s.label) for s in scores])  # a pair's label is long
            lines.append(f"  {'candidate':<{w}} {'dBIC':>10} {'p-value':>9} {'held-out gain':>14}  accepted")
            verdict = round_verdicts(scores)
            for s in scores:
                if s.screened:
                    lines.append(f"  {s.label:<{w}} {s.delta_bic:>10.1f}   (predicted; not fitted: {s.screen_reason})")
                    continue
                lines.append(
                    f"  {s.label:<{w}} {s.delta_bic:>10.1f} {s.p_value:>9.2g} {s.held_out_gain:>13.3f}x  "
                    f"{verdict[s.label]}"
                )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "split": self.split,
            "baseline": self.baseline.to_dict(),
            "evidence": self.evidence,
            "rounds": [[dataclasses.asdict(s) for s in scores] for scores in self.rounds],
            "causes": [dataclasses.asdict(c) for c in self.causes],
            "named": self.named,
            "held_out": self.held_out,
            "delta_bic_total": self.delta_bic_total,
            "fraction_explained": self.fraction_explained,
            "fraction_of_excess_explained": self.fraction_of_excess_explained,
            "extended_parameters": self.extended_parameters,
            "extended_intervals": self.extended_intervals,
            "baseline_converged": self.baseline_converged,
            "extended_at_bounds": self.extended_at_bounds,
            "costs": self.costs,
            "model_checks": self.model_checks,
            "notes": self.notes,
            "not_tried": self.not_tried,
            "detection_limits": self.detection_limits,
            "per_log": self.per_log,
            "held_out_logs": list(self.held_out_logs),
            "modal_frequencies_hz": self.modal_frequencies_hz,
            "wall_time_s": self.wall_time,
        }


# ---------------------------------------------------------------------------
# The search
# ---------------------------------------------------------------------------


def _best_starts(vs, costs, steps, owners) -> tuple:
    """A candidate batch's results trimmed to its `len(owners)` starts (host copies of the
    costs and step counts) and each candidate's best start, `{label: index}`."""
    B = len(owners)
    vs = {k: v[:B] for k, v in vs.items()}
    costs = np.asarray(costs, dtype=float)[:B].copy()
    steps = np.asarray(steps)[:B].copy()
    best = {}
    for b, c in enumerate(owners):
        if np.isfinite(costs[b]) and (c.label not in best or costs[b] < costs[best[c.label]]):
            best[c.label] = b
    return vs, costs, steps, best


def _finer_step(problem: Problem, theta, y0_free, step, sigma) -> tuple:
    """At physical parameters `theta` (and free initial-state entries `y0_free`): how far,
    in noise levels `sigma`, the outputs at the constant `step` are off (the largest
    deviation over the used samples; inf when the simulation fails), and the step to go
    on at: None when that is within `STEP_RECHECK`, else the coarsest of `step /
    STEP_DIVISORS` within it (the reference's step if none is). Each step is aligned with
    the torque samples (`identify.fit.aligned_step`).

    First the Richardson estimate from the outputs at `step` and `step / 2` (fifth order:
    `|y(h) - y(h/2)| 32/31`); within a quarter of the bar, that is the answer (three
    simulations' worth). Otherwise each step is compared with the outputs at
    `step / REFERENCE_DIVISOR`."""
    y0s = _initial_states(problem, y0_free)
    mask = np.asarray(problem.valid[:, :, None] & problem.present[:, None, :])
    sigma = np.asarray(sigma)

    def outputs(h):
        pred, ok = _predict(problem, theta, y0s, None, jnp.asarray(float(h), dtype=jnp.float64))
        return np.asarray(pred) if bool(jnp.all(ok)) else None

    def apart(a, b):
        if a is None or b is None:
            return float("inf")
        return float(np.max(np.where(mask, np.abs(a - b) / sigma, 0.0)))

    at_step = outputs(step)
    estimate = apart(at_step, outputs(aligned_step(problem, float(step) / 2))) * 32 / 31
    if estimate <= STEP_RECHECK / 4:
        return estimate, None
    finest = aligned_step(problem, float(step) / REFERENCE_DIVISOR)
    reference = outputs(finest)
    if reference is None:
        return float("nan"), None
    off = apart(at_step, reference)
    if not off > STEP_RECHECK:
        return off, None
    for d in STEP_DIVISORS:
        h = aligned_step(problem, float(step) / d)
        if apart(outputs(h), reference) <= STEP_RECHECK:
            return off, h
    return off, finest


def _used(problem: Problem) -> np.ndarray:
    return np.asarray(problem.valid[:, :, None] & problem.present[:, None, :]).reshape(-1)


def _rms_per_channel(problem: Problem, r: np.ndarray, sigma: np.ndarray) -> dict:
    """Per-channel RMS (SI) of weighted residuals `r` (flattened (L, T, C))."""
    L, T, C = problem.measured.shape
    r = np.asarray(r).reshape(L, T, C) * sigma[None, None, :]
    mask = np.asarray(problem.valid[:, :, None] & problem.present[:, None, :])
    return {c: float(np.sqrt(np.mean(r[:, :, k][mask[:, :, k]] ** 2))) for k, c in enumerate(problem.channels)}


def _modal_frequencies(chain: fd.Chain) -> list[float]:
    try:
        from .cli import natural_frequencies

        return natural_frequencies(chain)[0]
    except Exception:  # a rig without a stable equilibrium has no modal table
        return []


def diagnose_logs(
    chain: fd.Chain,
    parameters,
    fit_logs,
    held_out_logs,
    noise: dict | None = None,
    *,
    split: str = "",
    catalogue=cat.NAMES,
    exclude=(),
    measurement: meas.Measurement | None = None,
    max_effects: int = 3,
    pair_search: bool = True,
    bic_threshold: float = 10.0,
    min_gain: float = 1.1,
    max_steps: int = 25,
    n_fit: int | None = 3,
    rtol: float = 1e-8,
    fit_options: dict | None = None,
    progress=None,
) -> Diagnosis:
    """Diagnose in-memory logs (`LogData`); see the module docstring. `parameters` are the
    baseline's free `Parameter`s; `noise` maps channels to known standard deviations;
    `measurement` is the baseline's sensor and actuator model (default: ideal).
    `catalogue` names the entries to try; `exclude` lists candidate labels not to try
    (`name:where`, e.g. `coulomb_friction:joint1`)."""
    start = time.perf_counter()
    say = progress or (lambda msg: None)
    unknown = set(catalogue) - set(cat.NAMES)
    if unknown:
        raise ValueError(f"diagnose: unknown catalogue entries {sorted(unknown)}; the catalogue has {list(cat.NAMES)}")
    for label in exclude:
        if str(label).split(":", 1)[0] not in cat.NAMES:
            raise ValueError(
                f"diagnose: exclude: {label!r} is not a candidate label (name:where, e.g. 'coulomb_friction:joint1'; "
                f"the names are {list(cat.NAMES)})"
            )
    if not held_out_logs:
        raise ValueError("diagnose: no held-out data (give validation logs, or at least one log to split)")
    noise = dict(noise or {})
    parameters = list(parameters)
    say("baseline fit ...")
    measurement = meas.Measurement() if measurement is None else measurement
    base_problem = make_problem(
        chain, parameters, fit_logs, noise, rtol=rtol, atol=1e-2 * rtol, measurement=measurement
    )
    estimate = [c for c in base_problem.channels if noise.get(c) is None]
    # the baseline misses an effect on purpose: no restarts for its poor fit (`fit`)
    # `grid_error=None`: the tight integration step (`identify.fit.GRID_ERROR`), which the
    # candidates' fits reuse: a candidate's fit moves into stiffer models (dry friction is a
    # stiff damper at rest, an elastic joint's stiffness ranges over a factor 3 either
    # side) than the baseline's optimum at which a coarser step would be checked.
    options = {"restart_poor_fit": False, "grid_error": None, **(fit_options or {})}
    base = fit(base_problem, parameters, estimate_noise=estimate or False, progress=progress, **options)
    sigma = np.asarray([base.sigma[c] for c in base_problem.channels])
    sigma_j = jnp.asarray(sigma)
    notes = _baseline_notes(base.names, base.std_errors, base.values)  # `Diagnosis.notes`
    notes += _convergence_notes(base.stages[-1]["result"], base.at_bounds)
    for n in notes:
        say(f"  warning: {n['text']}")
    step = base.step
    fitted_chain = base.chain
    modal = _modal_frequencies(fitted_chain)

    # the joint model of every continuous candidate
    channels = base_problem.channels
    driven = sorted(
        {
            j
            for log in list(fit_logs) + list(held_out_logs)
            if log.torque is not None
            for j in range(np.asarray(log.torque).reshape(len(log.t), -1).shape[1])
            if np.any(np.asarray(log.torque).reshape(len(log.t), -1)[:, j] != 0)
        }
    )
    t0 = np.asarray(fit_logs[0].t, float)
    dt_sample = float(np.median(np.diff(t0)))
    torque_rms = float(
        np.sqrt(
            np.mean(
                np.concatenate(
                    [np.asarray(log.torque, float).ravel() ** 2 for log in fit_logs if log.torque is not None]
                    or [np.zeros(1)]
                )
            )
        )
    )
    rate_rms = 1.0
    for c in channels:
        if c.startswith("theta") or c.startswith("alpha"):
            rate_rms = float(
                np.sqrt(
                    np.mean(
                        [
                            np.mean(np.gradient(np.asarray(log.outputs[c]), np.asarray(log.t)) ** 2)
                            for log in fit_logs
                            if c in log.outputs
                        ]
                    )
                )
            )
            break
    offsets_fitted = {c for c in channels if all(c in log.offsets for log in fit_logs if c in log.outputs)}
    # the frequency a structural guess aims at: 2x the model's highest mode, at most
    # Nyquist (a joint mode far above it stiffens the problem for nothing; the structural
    # fit's multi-start covers a factor 3 in stiffness either side). Measured on the arm
    # (joint_elasticity, seed 1, true k = 44.5 N m/rad, joint mode ~2x the link's): from a
    # guess at 4x (k = 137) with 4 starts within 2x, the fit stayed at k = 137 (dBIC -223,
    # held-out gain 1.13x); from 2x (k = 34) with 8 starts within 3x it reached 44.50
    # (95 % CI [44.46, 44.54]) at the noise floor.
    positive_modes = [f for f in modal if f > 0]
    max_f = min(0.5 / dt_sample, 2.0 * max(positive_modes)) if positive_modes else 0.5 / dt_sample
    # geometric stiffening is offered where the model check (below, on every log) would
    # flag it from the baseline's motion on the fit logs
    stiffening_links = set()
    if any(link.n_modes > 0 and not link.geometric_stiffening for link in fitted_chain.links):
        stiffening_links = {
            check["link"]
            for check in ev.stiffening_checks_of(fitted_chain, fitted_outputs(base), key="simulated")
            if check["flagged"]
        }
    offered = cat.candidates(
        fitted_chain,
        channels,
        driven,
        torque_rms=torque_rms,
        rate_rms=rate_rms,
        sample_interval=dt_sample,
        channel_rms={},
        offsets_fitted=offsets_fitted,
        max_frequency_hz=max_f,
        stiffening_links=stiffening_links,
    )
    free = {p.name for p in parameters}
    # (an entry whose parameters are already free in the baseline is in the model)
    cands = [c for c in offered if c.name in catalogue and c.label not in exclude and not set(c.params) & free]
    not_tried = _not_tried(
        catalogue, offered, cands, exclude, cat.not_applicable(fitted_chain, driven, stiffening_links)
    )
    sup_chain, sup_meas = cat.superset(chain, measurement, channels, driven)
    ext_names = []
    for c in cands:
        if not c.structural:
            ext_names.extend(n for n in c.params if n not in ext_names)
    ext_params = [
        Parameter(
            n, 0.0 if (meas.is_signed(n) if meas.is_measurement_parameter(n) else fd.is_signed(sup_chain, n)) else 1.0
        )
        for n in ext_names
    ]
    sup_problem = make_problem(
        sup_chain, parameters + ext_params, fit_logs, dict(zip(channels, sigma)), measurement=sup_meas
    )
    neutral = []
    for n in ext_names:
        neutral.append(
            float(meas.get_parameter(sup_meas, n))
            if meas.is_measurement_parameter(n)
            else float(fd.get_parameter(sup_chain, n))
        )
    # the baseline's entries: its shared parameters and each fit log's own value of a
    # per-log one (`Parameter.per_log`), in `base_problem.names` order, then the extensions
    nb = len(base_problem.names)
    joint = _Joint(sup_problem, jnp.asarray(neutral, dtype=float), nb)
    ho_problem = make_problem(
        sup_chain, parameters + ext_params, held_out_logs, dict(zip(channels, sigma)), measurement=sup_meas
    )
    if ho_problem.channels != channels:
        raise ValueError(f"diagnose: held-out logs record channels {ho_problem.channels}, the fit logs {channels}")
    # The held-out problem's parameter vector: the shared entries from the fit's (`ho_src`)
    # and each held-out log's own values of the per-log parameters, re-estimated there
    # (`_Own`) from the fit logs' median, like its initial state and offsets.
    ho_own = _Own.of(ho_problem)
    own_set = set(np.asarray(ho_own.pos).tolist())
    ho_src = np.asarray(
        [0 if i in own_set else sup_problem.names.index(n) for i, n in enumerate(ho_problem.names)], dtype=int
    )
    ho_v0 = _held_out_start(ho_problem, ho_own, base)
    used = _used(sup_problem)
    N = int(used.sum())
    ho_used = _used(ho_problem)
    n_ho = int(ho_used.sum())
    zb0 = jnp.asarray(base.z["phys"])
    v_base = {
        "zb": zb0,
        "xe": jnp.zeros(SLOTS),
        "y0": jnp.asarray(base.z["y0"]),
        "offset": jnp.asarray(base.z["offset"]),
    }
    dummy = len(ext_names)

    def layout(names_vals):
        """Slot index, log flags and starting natural values for [(name, value), ...]."""
        idx = np.full(SLOTS, dummy, int)
        logf = np.zeros(SLOTS, bool)
        x = np.zeros(SLOTS)
        for s, (n, val, is_log) in enumerate(names_vals):
            idx[s] = ext_names.index(n)
            logf[s] = is_log
            x[s] = np.log(val) if is_log else val
        return idx, logf, x

    def theta_of(v, idx, logf):
        xb = _x_from_z(_bounds(joint), v["zb"])
        return _theta(joint, xb, v["xe"], jnp.asarray(idx), jnp.asarray(logf))

    # Batches are padded to fixed sizes so that every round reuses the compiled programs.
    ho_batch = (n_fit or len(cands)) + 1

    def held_out(thetas, *, nuisances=False):
        """Weighted held-out residuals (used entries) at a batch of the fit's parameter
        vectors; `nuisances=True`: also the held-out unknowns re-estimated there, and the
        held-out problem's parameter vectors (`"theta"`)."""
        n = thetas.shape[0]
        thetas_ho = jnp.asarray(thetas)[:, ho_src]
        r, w, th = _held_out_batch(ho_problem, _pad(thetas_ho, ho_batch), ho_v0, ho_own, sigma_j, step, max_steps)
        r = np.asarray(r)[:n][:, ho_used]
        return (r, {**{k: v[:n] for k, v in w.items()}, "theta": th[:n]}) if nuisances else r

    # baseline in the joint model (all extensions neutral): its cost equals the baseline fit's
    idx0, logf0, _ = layout([])
    theta_base = theta_of(v_base, idx0, logf0)
    # (the joint model with every extension neutral is the baseline model: same cost)
    cost0 = float(base.cost)
    ho0 = held_out(theta_base[None])[0]
    say(f"baseline: cost {cost0:.6g} over {N} residuals; held-out weighted RMS {np.sqrt(np.mean(ho0**2)):.4g}")

    def score_continuous(remaining, v_start):
        """Fit the continuous candidates `remaining` (multi-start, screened when there are
        more than `n_fit`) from the model state `v_start`, each extending the current
        model; score them against it. Returns the scores and the fits (to extend from)."""
        nonlocal step  # made finer where the best candidate needs it (`STEP_RECHECK`)
        fd.ensure_mapping_headroom()  # each candidate batch compiles programs of its own
        batch, owners = [], []
        for c in remaining:
            for s in c.starts:
                names_vals = list(current["layout"]) + [(n, val, lg) for n, val, lg in zip(c.params, s, c.log_scale)]
                if len(names_vals) > SLOTS:
                    continue
                batch.append(layout(names_vals))
                owners.append(c)
        if not batch:
            return [], None
        idx = jnp.asarray(np.stack([b[0] for b in batch]))
        logf = jnp.asarray(np.stack([b[1] for b in batch]))
        xe = np.stack([b[2] for b in batch])
        remaining = [c for c in remaining if c in owners]
        if n_fit is not None and len(remaining) > n_fit:
            # Screening: one Gauss-Newton step from every start (exact Jacobians, all the
            # free parameters), predicting each candidate's cost; only the `n_fit` most
            # promising candidates get the full multi-start fit.
            xb_cur = _x_from_z(_bounds(joint), v_start["zb"])
            B = len(batch)
            size = max(screen_size.get("B", B), B)
            screen_size.setdefault("B", B)
            rs, Js = _screen(
                joint,
                xb_cur,
                _pad(jnp.asarray(xe), size),
                v_start["y0"],
                v_start["offset"],
                _pad(idx, size),
                _pad(logf, size),
                sigma_j,
                step,
            )
            rs, Js = np.asarray(rs)[:B, used], np.asarray(Js)[:B, used, :]
            predicted, per_start = {}, []
            for b, c in enumerate(owners):
                delta, *_ = np.linalg.lstsq(Js[b], -rs[b], rcond=None)
                pred = float(np.sum((rs[b] + Js[b] @ delta) ** 2))
                per_start.append(pred)
                predicted[c.label] = min(predicted.get(c.label, np.inf), pred)
            # fully fit the most promising, and only those predicted to pass the BIC test
            n_par = {c.label: len(c.params) for c in remaining}
            promising = [
                lab
                for lab in predicted
                if N * math.log(max(predicted[lab], 1e-300) / current["cost"]) + n_par[lab] * math.log(N) < 0.0
            ]
            # ... and among those, the ones promising at least 10 % of the best one's reduction
            # (a second, smaller effect is searched for in the next round)
            why_out = {lab: "predicted not to lower the BIC" for lab in predicted if lab not in promising}
            if promising:
                best_drop = current["cost"] - min(predicted[lab] for lab in promising)
                small = [lab for lab in promising if current["cost"] - predicted[lab] < 0.1 * best_drop]
                why_out.update(
                    {
                        lab: "under 10 % of the best one's predicted drop; screened again once that is accepted"
                        for lab in small
                    }
                )
                promising = [lab for lab in promising if lab not in small]
            keep = sorted(promising, key=predicted.get)[:n_fit]
            why_out.update(
                {
                    lab: f"ranked below the {n_fit} most promising (n_fit={n_fit})"
                    for lab in promising
                    if lab not in keep
                }
            )
            say(
                "  screening (one Gauss-Newton step per start), predicted costs: "
                + ", ".join(f"{lab} {predicted[lab]:.6g}" for lab in sorted(predicted, key=predicted.get))
            )
            # the two most promising starts of each kept candidate
            sel = []
            for lab in keep:
                mine = sorted((b for b, c in enumerate(owners) if c.label == lab), key=lambda b: per_start[b])
                sel.extend(mine[:2])
            screened_out = [c for c in remaining if c.label not in keep]
            owners = [owners[b] for b in sel]
            sel_i = np.asarray(sel, dtype=int)
            idx, logf, xe = idx[sel_i], logf[sel_i], xe[sel_i]
            remaining = [c for c in remaining if c.label in keep]
        else:
            screened_out, predicted, why_out = [], {}, {}
        B = len(owners)
        scores = []
        fits = None
        rms_cur = float(np.sqrt(np.mean(current["ho"] ** 2)))
        if B == 0:
            say("  no continuous candidate is predicted to improve the fit significantly")
        else:
            v0 = {
                "zb": jnp.tile(_unsaturated(joint, v_start["zb"]), (B, 1)),
                "xe": jnp.asarray(xe),
                "y0": jnp.tile(v_start["y0"], (B, 1)),
                "offset": jnp.tile(v_start["offset"], (B, 1)),
            }
            say(f"round {rnd + 1}: fitting {len(remaining)} candidates ({B} starts) in one vmapped call ...")
            size = next(b for b in (3, 6, 12, 24, 10**9) if b >= B) if B <= 24 else B
            t_call = time.perf_counter()
            vs, costs, steps = _fit_batch(
                joint, _pad(v0, size), _pad(idx, size), _pad(logf, size), sigma_j, step, max_steps
            )
            costs = np.asarray(costs, dtype=float)  # waits for the call
            call_s = time.perf_counter() - t_call
            vs, costs, steps, best = _best_starts(vs, costs, steps, owners)
            finer = step_check(vs, costs, best, owners, idx, logf)
            if finer is not None:  # the fits go on from where they are, at the finer step
                step = finer
                t_call = time.perf_counter()
                vs, costs, steps = _fit_batch(
                    joint, _pad(vs, size), _pad(idx, size), _pad(logf, size), sigma_j, step, max_steps
                )
                costs = np.asarray(costs, dtype=float)
                call_s = time.perf_counter() - t_call  # (what a continuation at this step costs)
                vs, costs, steps, best = _best_starts(vs, costs, steps, owners)
            size = (size, call_s)
            vs, costs = _refine(
                joint,
                vs,
                costs,
                steps,
                best,
                owners,
                idx,
                logf,
                sigma_j,
                step,
                max_steps,
                size,
                current["cost"],
                N,
                say,
                predicted=predicted,
            )
            labels = [c.label for c in remaining if c.label in best]
            bs = [best[lab] for lab in labels]
            thetas = jnp.stack(
                [theta_of({k: v[b] for k, v in vs.items()}, np.asarray(idx[b]), np.asarray(logf[b])) for b in bs]
            )
            ho = held_out(thetas)
            fits = {"vs": vs, "best": best, "idx": idx, "logf": logf, "ho": ho, "labels": labels, "size": size}
            for lab, b, r_ho in zip(labels, bs, ho):
                c = next(x for x in remaining if x.label == lab)
                k = len(c.params)
                cost_c = float(costs[b])
                dbic = N * math.log(max(cost_c, 1e-300) / current["cost"]) + k * math.log(N)
                p_total = nb + current["k"] + k + len(sup_problem.y0_free) + len(sup_problem.offset_free)
                dof = max(N - p_total, 1)
                F = ((current["cost"] - cost_c) / k) / (cost_c / dof) if cost_c > 0 else np.inf
                p_value = float(stats.f.sf(F, k, dof)) if np.isfinite(F) else 0.0
                rms_c = float(np.sqrt(np.mean(r_ho**2)))
                gain = rms_cur / rms_c if rms_c > 0 else np.inf
                limit = ", ".join(f"{n} = {neutral[ext_names.index(n)]:g}" for n in c.params)
                stuck = _stuck_above_nested(c, cost_c, current["cost"], bic_threshold, limit=limit)
                if stuck:
                    say(f"  round {rnd + 1}: {stuck}")
                    notes.append({"round": rnd + 1, "text": stuck})
                theta_b = np.asarray(thetas[bs.index(b)])
                values = {n: float(theta_b[nb + ext_names.index(n)]) for n in c.params}
                scores.append(
                    Score(
                        c.name,
                        c.where,
                        values,
                        cost_c,
                        float(dbic),
                        p_value,
                        _rms_per_channel(ho_problem, _pad_used(r_ho, ho_used), sigma),
                        float(gain),
                        bool(dbic < -bic_threshold and gain >= min_gain),
                        k,
                        members=tuple(m.label for m in c.members),
                        held_out_gain_se=gain_standard_error(np.asarray(current["ho"]), np.asarray(r_ho)),
                    )
                )
        for c in screened_out:
            k = len(c.params)
            cost_c = min(predicted[c.label], current["cost"])
            dbic = N * math.log(max(cost_c, 1e-300) / current["cost"]) + k * math.log(N)
            scores.append(
                Score(
                    c.name,
                    c.where,
                    {},
                    cost_c,
                    float(dbic),
                    float("nan"),
                    {},
                    float("nan"),
                    False,
                    k,
                    screened=True,
                    screen_reason=why_out[c.label],
                    members=tuple(m.label for m in c.members),
                )
            )
        return scores, fits

    def step_check(vs, costs, best, owners, idx, logf):
        """The finer step to fit the round's candidates at (`STEP_RECHECK`), or None:
        checked at the optimum of the best candidate, when it would pass the BIC test."""
        k = {c.label: len(c.params) for c in owners}
        dbic = {
            lab: N * math.log(max(costs[b], 1e-300) / current["cost"]) + k[lab] * math.log(N) for lab, b in best.items()
        }
        if not dbic or not min(dbic.values()) < -bic_threshold:
            return None
        top = min(dbic, key=dbic.get)
        b = best[top]
        v = {key: val[b] for key, val in vs.items()}
        theta = theta_of(v, np.asarray(idx[b]), np.asarray(logf[b]))
        off, finer = _finer_step(joint.problem, theta, v["y0"], step, sigma_j)
        if finer is None:
            return None
        text = (
            f"the integration step {float(step) * 1e3:.3g} ms is {off:.3g} noise levels off at {top}'s fit "
            f"(against {REFERENCE_DIVISOR}x finer): the candidates' fits go on, and the search, at "
            f"{float(finer) * 1e3:.3g} ms"
        )
        say(f"  round {rnd + 1}: {text}")
        notes.append({"round": rnd + 1, "text": text})
        return jnp.asarray(float(finer), dtype=jnp.float64)

    def reconverge(cur, sized):
        """The accepted model refitted alone (no new parameter), from its baseline
        parameters pulled off their bounds (`_unsaturated`, as every candidate of the next
        round starts), until its cost stops falling: the reference the next round's
        candidates are scored against. Without it, a candidate of the next round gets the
        credit for whatever this refit gains: seen, after a sensor high-pass was accepted
        (held-out 40x), a calibration gain fitted at 0.9999 [0.9997, 1.0001] "improved" the
        fit by dBIC -4370 and was named as a second effect."""
        v = {k: jnp.asarray(val)[None] for k, val in cur["v"].items()}
        v["zb"] = _unsaturated(joint, v["zb"][0])[None]
        idx_c, logf_c = jnp.asarray(cur["idx"])[None], jnp.asarray(cur["logf"])[None]
        cost, moved = cur["cost"], False
        size = _few_size(1, *sized)
        for _ in range(MAX_REFINEMENTS):
            out, c2, s2 = _fit_batch(
                joint, _pad(v, size), _pad(idx_c, size), _pad(logf_c, size), sigma_j, step, max_steps
            )
            c2 = float(np.asarray(c2)[0])
            if not (np.isfinite(c2) and c2 < cost):
                break
            gained = N * math.log(cost / max(c2, 1e-300))
            v = {k: jnp.asarray(val)[:1] for k, val in out.items()}
            cost, moved = c2, True
            if gained < 0.1 or int(np.asarray(s2)[0]) < max_steps:
                break
        if not moved or N * math.log(cur["cost"] / max(cost, 1e-300)) < 0.1:
            return cur
        say(f"  the accepted model refitted alone: cost {cur['cost']:.6g} -> {cost:.6g}")
        v1 = {k: val[0] for k, val in v.items()}
        theta = theta_of(v1, np.asarray(cur["idx"]), np.asarray(cur["logf"]))
        return {**cur, "v": v1, "cost": cost, "ho": held_out(theta[None])[0]}

    accepted: list[tuple[cat.Candidate, dict]] = []  # continuous causes and their fitted values
    current = {"v": v_base, "cost": cost0, "ho": ho0, "layout": [], "k": 0}
    rounds = []
    causes_scores = []
    screen_size: dict = {}
    struct_promising: set = set()
    struct_drop: dict = {}  # structural label -> (cost drop when last fitted, k)
    struct_models: dict = {}  # structural label -> its fitted model (this round's)
    stack_on = None  # a structural winner with rounds left: the search goes on from its model
    structural = _StructuralFits(
        base,
        parameters,
        sup_meas,
        list(fit_logs),
        list(held_out_logs),
        channels,
        sigma,
        N,
        rtol,
        bic_threshold,
        min_gain,
        max_f,
        0.5 / dt_sample,
        say,
    )
    for rnd in range(max_effects):
        done = {a.label for a, _ in accepted}
        remaining = [c for c in cands if c.label not in done and not c.structural]
        if not remaining:
            break
        scores, fits = score_continuous(remaining, current["v"])
        rms_cur = float(np.sqrt(np.mean(current["ho"] ** 2)))
        if rnd == 0:
            # a baseline already at the noise leaves no candidate the held-out gain: the
            # continuous ones cost one vmapped call and fill the report's table, but each
            # structural one is a model of its own to compile and fit
            struct_promising = _with_headroom(
                {x.label for x in cands if x.structural and x.label not in done},
                ho_problem,
                current["ho"],
                min_gain,
                1,
                notes,
                say,
            )
        # A continuous candidate that passes and takes the held-out residual to the noise
        # leaves a structural one nothing to win: it could at best tie, and would not be
        # refitted from that model either. Review (a two-link arm with hidden dry friction
        # in joint 2): after the friction fitted, the structural entries took 100-130 s each
        # on one core (missing modes, stiffening), the diagnosis over 19 minutes.
        pending = {x.label for x in cands if x.structural and x.label not in done} & struct_promising
        if pending and fits is not None:
            struct_promising = _after_continuous_at_noise(
                pending, scores, fits, ho_problem, min_gain, rnd + 1, notes, say
            )
        # structural candidates of this round: all of them from the baseline (unless it is
        # at the noise); in later rounds only those that improved significantly on the
        # model of the previous round (each is a model of its own, compiled and fitted
        # separately: the expensive part)
        for c in [x for x in cands if x.structural and x.label not in done and x.label in struct_promising]:
            s = structural.score(c, current, rms_cur)
            if isinstance(s, str):  # its fit failed: said, not dropped in silence
                evidence = getattr(s, "evidence", "no evidence either way")
                text = f"{c.label}: its fit failed ({s}); not scored; {evidence}"
                say(f"  round {rnd + 1}: {text}")
                notes.append({"round": rnd + 1, "text": text})
            else:
                scores.append(s[0])
                struct_models[c.label] = s[1]
                stuck = _stuck_above_nested(c, s[0].cost, current["cost"], bic_threshold)
                if stuck:
                    say(f"  round {rnd + 1}: {stuck}")
                    notes.append({"round": rnd + 1, "text": stuck})
        # Pair search. When no single entry is accepted but the best continuous one fits
        # the data far better (dBIC < -bic_threshold) and still fails on the held-out data,
        # the cause may be two effects that only work together. Seen on the real single
        # pendulum: air drag alone halves the fit cost (dBIC -4884) but predicts the
        # smaller held-out swings worse (0.87x); dry friction alone ends at zero; the two
        # together (viscous damping then ends at zero) predict them 2x better. The leader,
        # from its own fit, is paired with every other continuous entry; the pairs go
        # through the same screening (one Gauss-Newton step), fit and scores as single
        # entries, with k = both entries' parameters.
        pair_fits = None
        leaders = [
            s
            for s in scores
            if not s.accepted
            and not s.screened
            and not s.members
            and s.delta_bic < -bic_threshold
            and any(c.label == s.label and not c.structural for c in cands)
        ]
        if pair_search and leaders and not any(s.accepted for s in scores):
            lead_s = min(leaders, key=lambda s: s.delta_bic)
            lead = next(c for c in cands if c.label == lead_s.label)
            lead_start = tuple(lead_s.params[n] for n in lead.params)
            pairs = [
                cat.pair(lead, lead_start, c)
                for c in remaining
                if c.label != lead.label and len(current["layout"]) + len(lead.params) + len(c.params) <= SLOTS
            ]
            if pairs:
                say(
                    f"  no single entry accepted; pairing {lead.label} (dBIC {lead_s.delta_bic:.1f}) "
                    f"with {len(pairs)} others ..."
                )
                lb = fits["best"][lead.label]
                v_lead = {k: fits["vs"][k][lb] for k in ("zb", "y0", "offset")}
                pair_scores, pair_fits = score_continuous(pairs, v_lead)
                scores.extend(pair_scores)
        scores.sort(key=lambda s: s.delta_bic)
        rounds.append(scores)
        # The cost each structural candidate took off the model of this round: in the next
        # round it is refitted only if that drop would pass the BIC test there (each refit is
        # a model of its own: 20-300 s on two cores). The test is on the absolute drop, not
        # this round's dBIC: a large effect masks a small one in a log-ratio. Seen: a 1.5 deg
        # base tilt (cost 4.7e7 over 2404 residuals) hid a joint of 40 N m/rad; elasticity
        # took 1.1e5 off (dBIC +10) and, not refitted after the tilt, was missed (the tilted
        # model ended at cost 16067, 6.7x the noise).
        struct_drop.update(
            {
                s.label: (current["cost"] - s.cost, s.k)
                for s in scores
                if any(c.label == s.label and c.structural for c in cands)
            }
        )
        winners = [s for s in scores if s.accepted]
        width = max([32] + [len(s.label) for s in scores[:5]])
        verdicts = round_verdicts(scores)
        for s in scores[:5]:
            verdict = verdicts[s.label].upper() if verdicts[s.label] == "named" else verdicts[s.label]
            outcome = (
                f"(predicted by one Gauss-Newton step; not fitted: {s.screen_reason})"
                if s.screened
                else f"held-out gain {s.held_out_gain:6.3f}x {verdict}"
            )
            say(f"  {s.label:<{width}} dBIC {s.delta_bic:10.1f}  {outcome}")
        if not winners:
            hint = _fits_but_does_not_predict(scores, bic_threshold, min_gain, offsets_fitted)
            if hint:
                say(f"  round {rnd + 1}: {hint}")
                notes.append({"round": rnd + 1, "text": hint})
            break
        w = winners[0]
        if w.members:
            wc = next(p for p in pairs if p.label == w.label)
            f = pair_fits
        else:
            wc = next(x for x in cands if x.label == w.label)
            f = fits
        for m in wc.members or (wc,):
            accepted.append((m, {"score": w, "with": [o.label for o in wc.members if o is not m]}))
        causes_scores.append(w)
        if wc.structural:
            # A structural winner changes the model's coordinates: the joint model of this
            # search cannot hold it. The search goes on from its model as a new baseline
            # (below, `_stacked`).
            model = struct_models[wc.label]
            again = _promising(struct_drop, w.cost, N, bic_threshold) - {wc.label}
            if wc.name in cat.REPEATABLE:
                again |= {wc.label}
            again = _with_headroom(
                again, model["held_out_problem"], model["held_out_residual"], min_gain, rnd + 2, notes, say
            )
            stack_on = (model, rnd + 1, again)
            break
        b = f["best"][w.label]
        current = {
            "v": {k: v[b] for k, v in f["vs"].items()},
            "cost": w.cost,
            "ho": f["ho"][f["labels"].index(w.label)],
            "layout": list(current["layout"]) + [(n, w.params[n], lg) for n, lg in zip(wc.params, wc.log_scale)],
            "k": current["k"] + w.k,
            "idx": np.asarray(f["idx"][b]),
            "logf": np.asarray(f["logf"][b]),
        }
        if rnd + 1 < max_effects:
            current = reconverge(current, f["size"])
        struct_promising = _promising(struct_drop, current["cost"], N, bic_threshold)
        struct_promising = _with_headroom(struct_promising, ho_problem, current["ho"], min_gain, rnd + 2, notes, say)

    # the extended model: parameters, intervals, gain
    causes = []
    ext_values = {}
    # every parameter of the extended model (baseline and extensions) with its 95 % interval
    ext_intervals = {
        n: {
            "value": float(base.values[i]),
            "std_error": float(base.std_errors[i]),
            "ci95": [float(base.ci_low[i]), float(base.ci_high[i])],
        }
        for i, n in enumerate(base.names)
    }
    if current["layout"]:
        v = current["v"]
        idx_c, logf_c = current["idx"], current["logf"]
        xb = _x_from_z(_bounds(joint), v["zb"])
        r, J = _jacobian(
            joint, xb, v["xe"], v["y0"], v["offset"], jnp.asarray(idx_c), jnp.asarray(logf_c), sigma_j, step
        )
        r, J = np.asarray(r)[used], np.asarray(J)[used]
        # (an undetermined parameter gets an infinite error, as in the fit: `identify.covariance`)
        se_nat = covariance.dense((), (), r, J).std_errors
        natural = [
            (n, float(xb[i]), float(se_nat[i]), base_problem.log_scale[i]) for i, n in enumerate(base_problem.names)
        ]
        natural += [(n, float(v["xe"][s]), float(se_nat[nb + s]), lg) for s, (n, _, lg) in enumerate(current["layout"])]
        for n, x, se, lg in natural:
            val = math.exp(x) if lg else x
            lo, hi = (math.exp(x - Z95 * se), math.exp(x + Z95 * se)) if lg else (x - Z95 * se, x + Z95 * se)
            ext_intervals[n] = {"value": val, "std_error": val * se if lg else se, "ci95": [lo, hi]}
        for n, _, _ in current["layout"]:
            ext_values[n] = {**ext_intervals[n], "unit": _unit(sup_problem, n)}
    for wc, info in accepted:
        sc = info["score"]
        if wc.structural:
            # replaced by the intervals of the stacked search's baseline fit (`_stacked`)
            nan = {"std_error": float("nan"), "ci95": [float("nan")] * 2}
            params = {
                n: {"value": val, **sc.intervals.get(n, nan), "unit": _unit_chain(n)} for n, val in sc.params.items()
            }
        else:
            params = {n: ext_values[n] for n in wc.params}
        causes.append(
            Cause(
                wc.name,
                wc.where,
                cat.DESCRIPTION[wc.name],
                params,
                sc.delta_bic,
                sc.held_out_gain,
                held_out_gain_se=sc.held_out_gain_se,
                together_with=list(info.get("with", [])),
                warnings=cat.implausible(
                    wc.name,
                    {n: p["value"] for n, p in params.items()},
                    torque_scale=cat.characteristic_torque(fitted_chain, torque_rms),
                    log_duration=min(float(np.ptp(np.asarray(log.t, float))) for log in fit_logs),
                    lowest_mode_hz=min(positive_modes) if positive_modes else None,
                ),
            )
        )
    rms_base = _rms_per_channel(ho_problem, _pad_used(ho0, ho_used), sigma)
    rms_ext = _rms_per_channel(ho_problem, _pad_used(current["ho"], ho_used), sigma)
    ho_cost0 = float(ho0 @ ho0)
    ho_cost1 = float(current["ho"] @ current["ho"])
    k_total = sum(s.k for s in causes_scores)
    costs = {
        "fit": {"baseline": cost0, "extended": float(current["cost"])},
        "held_out": {"baseline": ho_cost0, "extended": ho_cost1},
        "n_fit": N,
        "n_held_out": n_ho,
        "k": int(k_total),
    }
    extended_params = dict(base.value)
    if current["layout"]:
        theta_ext = np.asarray(theta_of(current["v"], current["idx"], current["logf"]))
        extended_params = {n: float(theta_ext[i]) for i, n in enumerate(base_problem.names)}
        extended_params.update({n: d["value"] for n, d in ext_values.items()})
    # (a per-log parameter keeps the rig's value in the extended chain, as `FitResult.chain`:
    # each log's own is among `extended_parameters`, `name[log]`)
    own_names = set(base_problem.names) - set(base_problem.shared_names)
    chain_vals, meas_vals = meas.split_values({n: v for n, v in extended_params.items() if n not in own_names})
    ext_chain = fd.with_parameters(sup_chain, chain_vals)
    ext_meas = meas.with_parameters(sup_meas, meas_vals)
    traces = _traces(joint, ho_problem, v_base, current, theta_of, idx0, logf0, step, held_out)
    # the held-out logs' unknowns at the final model (each log's own per-log values, the
    # detection limits' linearisation point): one held-out fit for both
    final = {**current, "idx": current.get("idx", idx0), "logf": current.get("logf", logf0)}
    w_final = None
    if base_problem.per_log or stack_on is None:
        _, w_final = held_out(theta_of(final["v"], final["idx"], final["logf"])[None], nuisances=True)
    per_log = {}
    if base_problem.per_log:
        theta_ho = np.asarray(w_final["theta"][0])
        for name, index in base_problem.per_log:
            per_log[name] = {log: extended_params[f"{name}[{log}]"] for log in base_problem.log_names}
            (index_ho,) = [ix for n, ix in ho_problem.per_log if n == name]
            per_log[name].update({log: float(theta_ho[i]) for log, i in zip(ho_problem.log_names, index_ho)})
    # evidence: what the baseline gets wrong, on the fit and the held-out logs
    outs = {
        name: {
            "t": e["t"],
            "measured": e["measured"],
            "simulated": e["baseline"],
            "residual": {c: e["baseline"][c] - e["measured"][c] for c in e["measured"]},
        }
        for name, e in traces.items()
    }
    torques = {}
    for problem in (sup_problem, ho_problem):
        for l, name in enumerate(problem.log_names):
            tv = np.asarray(problem.torque_v[l])[: len(traces[name]["t"]), 0]
            if np.any(tv != 0):
                torques[name] = tv
    evidence = ev.evidence(outs, base.sigma, modal, torques)
    model_checks = ev.stiffening_checks_of(fitted_chain, traces)
    limits = {}
    if stack_on is None:  # (else the search from the structural model reports them)
        done = {a.label for a, _ in accepted}
        say("detection limits of the candidates not named ...")
        w = w_final
        nb_ho = len(ho_problem.names) - len(ext_names)
        theta_ho = np.asarray(w["theta"][0])[:nb_ho]
        held = _HeldOut(
            _Joint(ho_problem, joint.neutral, nb_ho),
            w["y0"][0],
            w["offset"][0],
            ho_used,
            float(current["ho"] @ current["ho"]),
            jnp.asarray(np.where(np.asarray(ho_problem.log_scale[:nb_ho]), np.log(np.abs(theta_ho)), theta_ho)),
            tuple(-1 if i in own_set else int(ho_src[i]) for i in range(nb_ho)),
        )
        limits = detection_limits(
            joint,
            final,
            [c for c in cands if not c.structural and c.label not in done],
            ext_names,
            used,
            sigma_j,
            step,
            bic_threshold,
            held,
            min_gain,
        )
        limits = {
            lab: {
                n: {
                    "value": a,
                    "criterion": why,
                    "unit": _unit(sup_problem, n),
                    "neutral": neutral[ext_names.index(n)],
                }
                for n, (a, why) in per.items()
            }
            for lab, per in limits.items()
        }
    diag = Diagnosis(
        min_gain=min_gain,
        split=split,
        baseline=base,
        evidence=evidence,
        rounds=rounds,
        causes=causes,
        held_out=_held_out_summary(rms_base, rms_ext, ho_cost0, ho_cost1, _floor_per_channel(ho_problem)),
        delta_bic_total=0.0,
        fraction_explained=0.0,
        fraction_of_excess_explained=None,
        extended_chain=ext_chain,
        extended_measurement=ext_meas,
        extended_parameters=extended_params,
        outputs=traces,
        modal_frequencies_hz=modal,
        wall_time=0.0,
        extended_intervals=ext_intervals,
        costs=costs,
        model_checks=model_checks,
        notes=notes,
        not_tried=not_tried,
        detection_limits=limits,
        per_log=per_log,
        held_out_logs=tuple(ho_problem.log_names),
    )
    if stack_on is not None:
        # A structural change was accepted: the search goes on from its model, a new
        # baseline with every accepted effect's parameters free (its fit from the
        # structural candidate's optimum, single shooting). `max_effects` counts on; with
        # no round left the new baseline is only refitted: the extended model is then the
        # structural model with every parameter free, its intervals from that fit.
        model, rounds_used, promising = stack_on
        say(f"the search goes on from the model with {accepted[-1][0].label} ...")
        struct_chain = model["chain"]
        inner_params = list(model["parameters"]) + [Parameter(n, val) for n, val, _ in current["layout"]]
        # accepted entries are not tried again, but for one that can be applied again to
        # its own result (`catalogue.REPEATABLE`: one more mode on the link that gained one;
        # in `promising` unless the model is at the noise)
        skip = set(exclude) | {a.label for a, _ in accepted if a.name not in cat.REPEATABLE}
        skip |= {c.label for c in cands if c.structural and c.label not in promising}
        inner = diagnose_logs(
            struct_chain,
            inner_params,
            _with_extra_state(fit_logs, struct_chain),
            _with_extra_state(held_out_logs, struct_chain),
            dict(zip(channels, sigma)),
            measurement=model["measurement"],
            split=split,
            catalogue=catalogue,
            exclude=sorted(skip),
            max_effects=max_effects - rounds_used,
            pair_search=pair_search,
            bic_threshold=bic_threshold,
            min_gain=min_gain,
            max_steps=max_steps,
            n_fit=n_fit,
            rtol=rtol,
            fit_options={
                **options,
                "horizons": None,
                "n_stages": 1,
                "n_starts": 1,
                "max_restarts": 0,
                "frequency_init": False,
                "first_damping": 0.0,  # a warm start (the accepted model's values)
                "extra_starts": (),
            },
            progress=(lambda msg: say("  " + msg)) if progress else None,
        )
        diag = _stacked(diag, inner)
    return _with_totals(diag, time.perf_counter() - start)


def _not_tried(catalogue, offered, cands, exclude, inapplicable: dict) -> dict:
    """`Diagnosis.not_tried`: each entry of `catalogue` with no candidate in `cands`, and
    why (`catalogue.not_applicable`, excluded by the caller, or its parameters already free
    in the baseline), in catalogue order."""
    out = {}
    for name in catalogue:
        if any(c.name == name for c in cands):
            continue
        mine = [c for c in offered if c.name == name]
        if not mine:
            out[name] = inapplicable.get(name, "not offered on this rig and these logs")
        elif all(c.label in exclude for c in mine):
            out[name] = f"excluded by the caller ({', '.join(c.label for c in mine)})"
        else:
            out[name] = "its parameters are free in the baseline already (it is part of the model)"
    return out


def _with_headroom(labels: set, problem: Problem, r_used, min_gain: float, rnd: int, notes: list, say) -> set:
    """`labels`, the structural candidates to fit in round `rnd` (from 1; in round 1 all
    of them, from the baseline), or none when the current model's held-out residual
    `r_used` leaves no room for `min_gain` (`_no_headroom`; the decision goes to
    `notes`)."""
    if not labels:
        return labels
    full, why = _no_headroom(problem, r_used, min_gain)
    if not full:
        return labels
    if rnd == 1:
        text = f"{', '.join(sorted(labels))} not fitted: the baseline is at the noise; {why}"
    else:
        text = f"{', '.join(sorted(labels))} not refitted: the model of the previous round is at the noise; {why}"
    say(f"  round {rnd}: {text}")
    notes.append({"round": rnd, "text": text})
    return set()


def _after_continuous_at_noise(labels: set, scores, fits, problem, min_gain: float, rnd: int, notes, say) -> set:
    """`labels`, the structural candidates still to fit in round `rnd`, or none when an
    accepted continuous candidate of the round (the best by dBIC) brings the held-out
    residual to the noise (`_no_headroom` of its held-out residual; the decision goes to
    `notes`)."""
    passing = [s for s in scores if s.accepted and not s.members and s.label in fits["labels"]]
    fitted = [s for s in scores if not s.screened and not s.members]
    # review: a two-link arm's round printed nothing for 15 minutes of structural fits, and
    # its continuous results (dry friction screened 20x ahead) only after them
    structural = f"fitting the structural candidates ({', '.join(sorted(labels))}; each a model of its own)"
    if not passing:
        lead = min(fitted, key=lambda s: s.delta_bic, default=None)
        say(
            f"  round {rnd}: no continuous candidate passes"
            + (
                f" (best: {lead.label}, dBIC {lead.delta_bic:.1f}, held-out gain {lead.held_out_gain:.3f}x)"
                if lead is not None
                else ""
            )
            + f": {structural}"
        )
        return labels
    best = min(passing, key=lambda s: s.delta_bic)
    full, why = _no_headroom(problem, fits["ho"][fits["labels"].index(best.label)], min_gain)
    if not full:
        ratio = held_out_headroom(problem, fits["ho"][fits["labels"].index(best.label)]).ratio
        say(
            f"  round {rnd}: {best.label} passes (dBIC {best.delta_bic:.1f}, held-out gain {best.held_out_gain:.3f}x) "
            f"but leaves the held-out residual at {ratio:.3g} times its noise floor: {structural}"
        )
        return labels
    text = (
        f"{', '.join(sorted(labels))} not fitted: {best.label} passes and brings the held-out residual to the "
        f"noise (with it, {why.replace('no candidate can reach', 'nothing can add')}); a structural model could "
        "at best tie with it"
    )
    say(f"  round {rnd}: {text}")
    notes.append({"round": rnd, "text": text})
    return set()


#: `_stuck_above_nested`: an excess below this fraction of the current cost is the
#: optimiser's precision, not a local minimum (seen on the spinning-link example, whose
#: baseline misfit is large: a sensor high-pass ended at 104508119 against 104508062)
STUCK_RELATIVE = 1e-4


def _stuck_above_nested(c, cost: float, cost_current: float, bic_threshold: float, limit: str | None = None) -> str:
    """A note when candidate `c`, whose model holds the current one as a limit, ended its
    fit with a cost (chi-square units, fit data) more than `bic_threshold` (and more than
    `STUCK_RELATIVE` of it) above the current model's: its fit stopped in a local minimum
    (or ran out of steps), and its dBIC is no evidence against the effect. Else ''. The limit: `limit` (a continuous
    candidate: its parameters at their neutral values), else the structural change's
    (`catalogue.NESTED_LIMIT`: an elastic joint stiff enough is the rigid one)."""
    limit = limit if limit is not None else cat.NESTED_LIMIT.get(c.name)
    if limit is None or not cost > cost_current + max(bic_threshold, STUCK_RELATIVE * cost_current):
        return ""
    return (
        f"{c.label}: its fit ended above the model it extends (cost {cost:.1f} against "
        f"{cost_current:.1f}), which it holds as a limit ({limit}): a local minimum, not "
        "evidence against the effect"
    )


#: `_baseline_notes`: a 95 % half-width above this fraction of the value marks a baseline
#: parameter as poorly determined
POORLY_DETERMINED = 0.5


def _baseline_notes(names, std_errors, values=None) -> list:
    """`Diagnosis.notes` of the baseline fit (round 0): the parameters its fit logs do not
    determine (no interval: `identify.covariance`; their degeneracy is every candidate's,
    whose fit then wanders along it), and those they determine poorly (a 95 % half-width,
    1.96 SE, above `POORLY_DETERMINED` of the value: the logs carry little information
    (short, small motions, much noise), and an effect of similar size may go unnoticed:
    naming no cause then does not say there is none)."""
    notes = []
    undetermined = [n for n, se in zip(names, std_errors) if not np.isfinite(se)]
    if undetermined:
        text = (
            f"the fit logs do not determine the baseline's {', '.join(undetermined)} (they see only a "
            "combination of them; see the fit's identifiability warning): fix one parameter of each combination, "
            "or the candidates' fits inherit the degeneracy"
        )
        notes.append({"round": 0, "text": text})
    if values is not None:
        poor = [
            f"{n} +-{100 * 1.96 * se / abs(v):.0f} %"
            for n, v, se in zip(names, values, std_errors)
            if np.isfinite(se) and 1.96 * se > POORLY_DETERMINED * abs(v)
        ]
        if poor:
            notes.append(
                {
                    "round": 0,
                    "text": f"the fit logs determine the baseline's {', '.join(poor)} only (95 %): unless such a "
                    "value is negligible in the model, they carry little information (short logs, small "
                    "motions or much noise), and a missing effect of comparable size can go undetected; longer "
                    "or richer logs give the search more power",
                }
            )
    return notes


def _fits_but_does_not_predict(scores, bic_threshold: float, min_gain: float, offsets_fitted) -> str:
    """A note when the round's best fit (lowest dBIC, below `-bic_threshold`) predicts the
    held-out logs worse than the model it extends, by as much as acceptance asks it to
    predict them better (held-out gain below `1 / min_gain`): it absorbs something
    particular to the fit logs. A sensor calibration candidate on a channel without per-log offsets is the
    usual case (seen on the real pendulum: an encoder offset that differs between logs).
    Else ''."""
    fitted = [s for s in scores if not s.screened and np.isfinite(s.held_out_gain)]
    if not fitted:
        return ""
    s = min(fitted, key=lambda x: x.delta_bic)
    if not (s.delta_bic < -bic_threshold and s.held_out_gain < 1.0 / min_gain):
        return ""
    text = (
        f"{s.label} fits the fit logs better (dBIC {s.delta_bic:.1f}) but predicts the held-out logs worse "
        f"({s.held_out_gain:.3f}x), so it is not named: what it fits does not carry over to other logs "
        "(something particular to the fit logs, or a small error of the model that it makes up for there)"
    )
    for label in s.members or (s.label,):
        name, _, channel = label.partition(":")
        if name == "sensor_gain_offset" and channel not in offsets_fitted:
            text += (
                f"; an offset of {channel} that differs between logs is one such thing: give each log its own "
                f'(offsets = ["{channel}"] in its [[logs]] entry)'
            )
    return text


def _convergence_notes(result: str, at_bounds) -> list:
    """`Diagnosis.notes` of a baseline fit that did not converge (`result`: its last
    stage's solver result, "successful", "max_steps_reached" or "failed") or ended with
    parameters `at_bounds` (found in review: `identify diagnose` said nothing of either and
    exited 0). A fit stopped short of its optimum makes every candidate look better than it
    is: part of each candidate's cost drop is the baseline's own fit finishing. A parameter
    on its bound is often the missing effect's symptom (a damping pushed to zero by the
    friction the model lacks), so it is said, not refused."""
    notes = []
    if result != "successful":
        notes.append(
            {
                "round": 0,
                "text": f"the baseline fit did not converge (its solver ended: {result}): every candidate is "
                "scored against a model short of its optimum, so part of its dBIC and held-out gain may be the "
                "baseline's fit finishing; check it with `identify fit` on the same logs, give it more steps "
                "(`diagnose_logs(fit_options={'max_steps': ...})`) or better guesses (`[[starts]]`), and run again",
            }
        )
    if at_bounds:
        notes.append(
            {
                "round": 0,
                "text": f"the baseline's {', '.join(at_bounds)} ended on a bound: the bound, not the data, set "
                "its value; often the symptom of the effect the model lacks (see the named causes and the "
                "extended model's values), otherwise a bound too narrow",
            }
        )
    return notes


def note_text(note: dict) -> str:
    """A `Diagnosis.notes` entry as printed: where it arose (round 0: the baseline) and what it says."""
    where = "baseline" if note["round"] == 0 else f"round {note['round']}"
    return f"{where}: {note['text']}"


def _promising(drops: dict, cost: float, n: int, bic_threshold: float) -> set:
    """The structural candidates whose cost drop `drops[label] = (drop, k)`, taken off a
    model of the previous round, would pass the BIC test against a model of cost `cost`:
    `N ln(cost / (cost - drop)) > bic_threshold + k ln N`."""
    return {
        label for label, (drop, k) in drops.items() if drop > cost * -math.expm1(-(bic_threshold + k * math.log(n)) / n)
    }


#: `held_out_headroom`: the relative standard error of the order-4 noise floor of `n` white
#: samples is `FLOOR_SE / sqrt(n)` (`held_out_headroom`'s docstring)
FLOOR_SE = 1.146
#: `held_out_headroom`: the lags (samples) of the residual's autocorrelation checked
WHITE_LAGS = 4


@dataclasses.dataclass(frozen=True)
class Headroom:
    """`held_out_headroom`: a held-out residual against its own noise floor."""

    ratio: float  # its RMS over its model-free noise floor
    floor_se: float  # the floor's relative standard error
    autocorrelation: tuple  # at lags 1..WHITE_LAGS samples, pooled over logs and channels
    n: int  # the samples behind the autocorrelation

    def at_the_noise(self, min_gain: float, margin_se: float) -> bool:
        """Whether no model can take `min_gain` off this residual's RMS: the ratio below
        `min_gain` less `margin_se` standard errors of the floor, and the residual white
        (every autocorrelation within `margin_se + 1` of its white-noise standard error
        `1 / sqrt(n)`)."""
        white = all(abs(a) * math.sqrt(self.n) < margin_se + 1.0 for a in self.autocorrelation)
        return white and self.ratio < min_gain * (1.0 - margin_se * self.floor_se)


def held_out_headroom(problem: Problem, r_used: np.ndarray) -> Headroom:
    """How far a model's held-out weighted residual `r_used` (the residuals of `problem`'s
    logs that count, `_used`) is above the noise: the ratio of its RMS to its own
    model-free noise floor (`identify.noise_floor`, the floor of the residual traces,
    pooled over logs and channels by their samples), that floor's relative standard
    error, and the residual's autocorrelation at the first `WHITE_LAGS` lags.

    A better model's held-out RMS cannot fall below the noise, so when the ratio is below
    `min_gain` (less a margin for the floor's error) no candidate can reach the held-out
    gain `min_gain`. The floor is taken of the residual, not of the measured traces: the
    measured floor carries the signal's leakage (`A (2 sin(pi f dt))^4 / sqrt(140)` for a
    sine, 8e-4 A at 20 samples per period, which on the spinning link's tip is 40 % of
    the noise), the residual's only the misfit's. A slow misfit leaks next to nothing, but
    one near the Nyquist frequency passes the 4th difference almost whole (above a third
    of the sampling rate, more than its RMS): the floor cannot tell it from noise, its
    autocorrelation can (a misfit of a fraction `w` of the residual's variance at
    frequency `f` adds `w cos(2 pi f k dt)` at lag `k`, and no `f` is small at all four
    lags). Noise that is not white gives a smaller floor and a non-zero autocorrelation:
    refits are then kept.

    Standard error: the normalised 4th differences of white noise have the lag
    correlations `(-1)^m C(8, 4 + m) / C(8, 4)` (-0.8, 0.4, -0.114, 0.014), so the mean of
    their squares has variance `(2 / n) (1 + 2 sum rho^2) = 5.25 / n` relative to
    `sigma^4`, and the floor a relative error of `1.146 / sqrt(n)` (`FLOOR_SE`; `n` the
    differences, `ORDER` fewer than the samples per log and channel)."""
    L, T, C = problem.measured.shape
    used = _used(problem)
    r = _pad_used(np.asarray(r_used, float), used).reshape(L, T, C)
    floor, count = nf.channel_floors(problem.t, r, problem.valid, problem.present)
    n = float(np.sum(count))
    n_pseudo = float(np.sum(np.clip(count - nf.ORDER, 0, None)))  # the floor's differences
    if n_pseudo == 0:
        return Headroom(float("inf"), float("inf"), (), 0)
    f2 = float(np.sum(count * np.square(floor)) / n)
    ms = float(np.mean(np.square(r_used)))
    ratio = math.sqrt(ms / f2) if f2 > 0 else float("inf")
    # autocorrelation of each log's channel over its valid samples, pooled
    lagged, total = np.zeros(WHITE_LAGS), 0.0
    valid, present = np.asarray(problem.valid, bool), np.asarray(problem.present, bool)
    for l in range(L):
        for c in range(C):
            if present[l, c]:
                x = r[l, valid[l], c]
                total += float(x @ x)
                lagged += [float(x[:-k] @ x[k:]) if x.size > k else 0.0 for k in range(1, WHITE_LAGS + 1)]
    auto = tuple(float(v) for v in lagged / total) if total > 0 else (0.0,) * WHITE_LAGS
    return Headroom(ratio, FLOOR_SE / math.sqrt(n_pseudo), auto, int(n))


#: `held_out_headroom`: the margin, in standard errors, by which a held-out residual must be
#: below `min_gain` floors (and its autocorrelations near 0) before later rounds stop
#: refitting candidates
FLOOR_MARGIN_SE = 3.0


def _no_headroom(problem: Problem, r_used, min_gain: float) -> tuple[bool, str]:
    """Whether a model's held-out residual `r_used` leaves no room for a held-out gain of
    `min_gain` (`held_out_headroom`), and the reason in words."""
    h = held_out_headroom(problem, r_used)
    limit = min_gain * (1.0 - FLOOR_MARGIN_SE * h.floor_se)
    text = (
        f"its held-out residual is {h.ratio:.3f} times its own noise floor (SE {100 * h.floor_se:.1f} %), "
        f"below {limit:.3f}, and white (autocorrelation at most {max(map(abs, h.autocorrelation), default=0):.3f} "
        f"at lags 1-{WHITE_LAGS}): no candidate can reach the held-out gain of {min_gain:g}"
    )
    return h.at_the_noise(min_gain, FLOOR_MARGIN_SE), text


def _held_out_summary(rms_base: dict, rms_ext: dict, cost_base: float, cost_ext: float, floor: dict) -> dict:
    """`floor`: each channel's model-free noise floor on the held-out logs (`_floor_per_channel`),
    what the best model could reach."""
    return {
        "baseline": rms_base,
        "extended": rms_ext,
        "gain": {c: rms_base[c] / rms_ext[c] if rms_ext[c] > 0 else float("inf") for c in rms_base},
        "gain_total": math.sqrt(cost_base / cost_ext) if cost_ext > 0 else float("inf"),
        "noise_floor": floor,
    }


def _floor_per_channel(problem: Problem) -> dict:
    """Per channel, the model-free noise floor of the problem's logs (SI; `identify.noise_floor`,
    the sample-weighted RMS over the logs)."""
    floor, count = nf.channel_floors(problem.t, problem.measured, problem.valid, problem.present)
    f2 = nf.pooled(np.square(floor), count)
    return {c: float(np.sqrt(v)) for c, v in zip(problem.channels, f2) if not np.isnan(v)}


def _with_totals(diag: Diagnosis, wall_time: float) -> Diagnosis:
    """`diag` with the totals computed from its `costs`: dBIC of the extended model against
    the baseline (`N ln(RSS_ext / RSS_0) + k ln N`), the fraction of the held-out residual
    explained, and of its excess over the noise (expected cost `N_held_out`)."""
    c = diag.costs
    n, k = c["n_fit"], c["k"]
    fit0, fit1 = c["fit"]["baseline"], c["fit"]["extended"]
    ho0, ho1 = c["held_out"]["baseline"], c["held_out"]["extended"]
    dbic = n * math.log(max(fit1, 1e-300) / fit0) + k * math.log(n) if diag.causes else 0.0
    excess = ho0 - c["n_held_out"]
    return dataclasses.replace(
        diag,
        delta_bic_total=float(dbic),
        fraction_explained=float(1.0 - ho1 / ho0) if ho0 > 0 else 0.0,
        fraction_of_excess_explained=float((ho0 - ho1) / excess) if excess > 0 else None,
        wall_time=wall_time,
    )


def _stacked(outer: Diagnosis, inner: Diagnosis) -> Diagnosis:
    """A search that ended on a structural change (`outer`) continued by the search from
    that structural model (`inner`, whose baseline is it, every accepted effect's
    parameters free). Rounds and causes are concatenated; the causes `outer` accepted
    report their parameters from the final extended model; the extended model, its costs
    and held-out RMS are `inner`'s, compared with `outer`'s baseline."""
    causes = [
        dataclasses.replace(
            c,
            parameters={
                n: {**inner.extended_intervals[n], "unit": p["unit"]} if n in inner.extended_intervals else p
                for n, p in c.parameters.items()
            },
        )
        for c in outer.causes
    ]
    outputs = {}
    for name, e in outer.outputs.items():
        ie = inner.outputs[name]
        outputs[name] = {**e, "extended": ie.get("extended", ie["baseline"])}
    costs = {
        **outer.costs,
        "fit": {"baseline": outer.costs["fit"]["baseline"], "extended": inner.costs["fit"]["extended"]},
        "held_out": {"baseline": outer.costs["held_out"]["baseline"], "extended": inner.costs["held_out"]["extended"]},
        "k": outer.costs["k"] + inner.costs["k"],
    }
    return dataclasses.replace(
        outer,
        rounds=outer.rounds + inner.rounds,
        causes=causes + inner.causes,
        # the inner search's rounds continue the outer's count
        # (the inner search's baseline notes are about the model after the outer rounds; one
        # the outer search already made is not repeated)
        notes=outer.notes
        + [
            {**n, "round": n["round"] + len(outer.rounds)}
            for n in inner.notes
            if not (n["round"] == 0 and any(o["text"] == n["text"] for o in outer.notes))
        ],
        # not tried by either search (the inner one may try what the outer could not)
        not_tried={n: why for n, why in outer.not_tried.items() if n in inner.not_tried},
        held_out=_held_out_summary(
            outer.held_out["baseline"],
            inner.held_out["extended"],
            costs["held_out"]["baseline"],
            costs["held_out"]["extended"],
            outer.held_out["noise_floor"],
        ),
        extended_chain=inner.extended_chain,
        extended_measurement=inner.extended_measurement,
        extended_parameters=inner.extended_parameters,
        extended_intervals=inner.extended_intervals,
        per_log=inner.per_log,
        outputs=outputs,
        costs=costs,
        detection_limits=inner.detection_limits,
    )


def _pad_used(r_used, used):
    full = np.zeros(used.shape[0])
    full[used] = r_used
    return full


def _unit(problem: Problem, name: str) -> str:
    from .fit import parameter_unit

    return parameter_unit(problem, name)


def _unit_chain(name: str) -> str:
    return {"stiffness": "N m/rad", "rotor_inertia": "kg m^2"}.get(name.rsplit(".", 1)[-1], "")


def _traces(joint, ho_problem, v_base, current, theta_of, idx0, logf0, step, held_out) -> dict:
    """Measured, baseline and extended outputs (SI) on the fit and held-out logs, for plots."""
    out = {}
    variants = [("baseline", v_base, idx0, logf0)]
    if current["layout"]:
        variants.append(("extended", current["v"], current["idx"], current["logf"]))
    for role, problem in (("fit", joint.problem), ("held-out", ho_problem)):
        for name, v, idx, logf in variants:
            theta = theta_of(v, idx, logf)
            if role == "fit":
                y0s, off = _initial_states(problem, v["y0"]), _offsets(problem, v["offset"])
            else:
                _, w = held_out(theta[None], nuisances=True)
                y0s, off = _initial_states(problem, w["y0"][0]), _offsets(problem, w["offset"][0])
                theta = w["theta"][0]  # (the held-out problem's: its logs' own per-log values in)
            pred, _ = _predict(problem, theta, y0s, None, step)
            pred = np.asarray(pred + off[:, None, :])
            valid, present = np.asarray(problem.valid), np.asarray(problem.present)
            for l, log in enumerate(problem.log_names):
                k = valid[l]
                entry = out.setdefault(log, {"role": role, "t": np.asarray(problem.t[l])[k], "measured": {}})
                for j, c in enumerate(problem.channels):
                    if present[l, j]:
                        entry["measured"][c] = np.asarray(problem.measured[l, k, j])
                        entry.setdefault(name, {})[c] = pred[l, k, j]
    return out


@dataclasses.dataclass(frozen=True)
class _StructuralFits:
    """What every structural candidate's fit shares in one diagnosis: the baseline
    (`base`, its free `parameters`), the superset measurement model (`measurement`), the
    fit and held-out logs, the channels and their noise `sigma`, the `N` residuals the
    information criterion counts, and the acceptance thresholds."""

    base: object  # the baseline's `FitResult`
    parameters: list
    measurement: meas.Measurement
    fit_logs: list
    held_out_logs: list
    channels: tuple
    sigma: np.ndarray
    N: int
    rtol: float
    bic_threshold: float
    min_gain: float
    max_frequency_hz: float
    nyquist_hz: float
    say: Callable[[str], None]

    def score(self, c, current: dict, rms_cur: float):
        return _structural_score(self, c, current, rms_cur)


def gain_standard_error(r_base, r_ext) -> float:
    """The standard error of a held-out gain `sqrt(mean(r_base^2) / mean(r_ext^2))` from
    its paired samples (the same held-out samples under the two models; NaN if they do not
    pair up). Delta method: `log gain^2 = log mean(a) - log mean(b)` (`a = r_base^2`,
    `b = r_ext^2`) has variance `var(a / mean(a) - b / mean(b)) / n_eff`, with `n_eff = n
    (1 - rho) / (1 + rho)` for a lag-1 autocorrelation `rho >= 0` of that difference (a
    residual correlated in time holds fewer independent samples). Review: a false cause
    passed the 1.1x bar at 1.1002x on ~1,000 held-out samples, well within the gain's own
    scatter (the summary now marks such a cause as marginal)."""
    a, b = np.square(np.asarray(r_base, float)), np.square(np.asarray(r_ext, float))
    if a.shape != b.shape or a.size < 10 or not (a.mean() > 0 and b.mean() > 0):
        return float("nan")
    d = a / a.mean() - b / b.mean()
    dc = d - d.mean()
    var = float(np.mean(dc**2))
    if var == 0.0:
        return 0.0
    rho = min(max(float(np.mean(dc[1:] * dc[:-1])) / var, 0.0), 0.99)
    n_eff = d.size * (1.0 - rho) / (1.0 + rho)
    gain = math.sqrt(a.mean() / b.mean())
    return 0.5 * gain * math.sqrt(var / n_eff)


def round_verdicts(scores) -> dict:
    """Label -> `"named"` for a round's first accepted candidate (the one the search
    names), `"passes, not named (the named one is better)"` for the others that pass both
    tests, `""` else: what the console, the summary and the report show (review: two rows
    said "ACCEPTED"/"yes" and one cause was named)."""
    named = next((s.label for s in scores if s.accepted), None)
    return {
        s.label: ("named" if s.label == named else "passes, not named (the named one is better)") if s.accepted else ""
        for s in scores
    }


class _FailedTowardRigid(str):
    """A structural candidate's failure reason (a `str`) whose fit drifted to the model
    the candidate extends; `.evidence`: what that says, for the note."""

    def __new__(cls, reason: str, evidence: str):
        out = super().__new__(cls, reason)
        out.evidence = evidence
        return out


def _rigid_limit(c, error, nyquist_hz: float) -> str | None:
    """For a `joint_elasticity` fit that failed because its simulation needed more steps
    than allowed (`identify.fit.SimulationFailed`): when the joint mode at the values where
    it failed is far above the logs' Nyquist frequency, the evidence that the fit was
    making the joint rigid (None otherwise). The joint mode is at least
    `sqrt(k / J_rotor) / (2 pi)` (the rotor on its spring against a locked link; a free
    link raises it: `omega^2 = k (1/J_rotor + 1/J_link)`).

    Found on a driven rigid pendulum whose logs hide dry friction: the elastic-joint fit
    took the stiffness from 2.7e-3 to 87 N m/rad and the rotor inertia from 1.5e-5 to
    8.6e-8 kg m^2, a joint mode of >= 5 kHz against a 100 Hz Nyquist frequency, and the
    adaptive solve ran out of steps; the note said "no evidence either way"."""
    if c.name != "joint_elasticity" or not isinstance(error, SimulationFailed):
        return None
    if not any("limit of" in why for why in error.logs.values()):
        return None
    k = error.values.get(f"{c.where}.stiffness")
    rotor = error.values.get(f"{c.where}.rotor_inertia")
    if k is None or rotor is None or not (k > 0 and rotor > 0):
        return None
    f_joint = math.sqrt(k / rotor) / (2 * math.pi)
    if f_joint < 10 * nyquist_hz:
        return None
    return (
        f"the fit was making the joint rigid: where its simulation ran out of steps, the joint mode is at least "
        f"{f_joint:.3g} Hz ({c.where}.stiffness {k:.3g} N m/rad, rotor inertia {rotor:.3g} kg m^2), "
        f"{f_joint / nyquist_hz:.0f}x the logs' Nyquist frequency {nyquist_hz:.3g} Hz: evidence against an elastic "
        "joint the logs resolve"
    )


def _structural_score(setting: _StructuralFits, c, current: dict, rms_cur: float):
    """Fit a structural candidate as a model of its own (baseline parameters refitted from
    the baseline's values, accepted continuous effects kept at their fitted values).
    Returns `(score, model)` (`model`: the fitted chain, its measurement, the free
    parameters at their fitted values, the fit, the held-out weighted cost), or, when the
    fit failed, the reason (a string, for `Diagnosis.notes`; found on the spinning-link
    example: a failed candidate was only printed, and missing from the report)."""
    base, parameters, sup_meas = setting.base, setting.parameters, setting.measurement
    channels, sigma, N, rtol, say = setting.channels, setting.sigma, setting.N, setting.rtol, setting.say
    fit_logs, held_out_logs = setting.fit_logs, setting.held_out_logs
    bic_threshold, min_gain, max_f = setting.bic_threshold, setting.min_gain, setting.max_frequency_hz
    values = {n: val for n, val, _ in current["layout"]}
    base_chain = base.chain
    struct_chain, new = cat.structural_model(base_chain, c, max_frequency_hz=max_f)
    m = sup_meas
    if values:
        chain_vals, meas_vals = meas.split_values(values)
        struct_chain, _ = cat.superset(struct_chain, meas.Measurement(), channels, [])
        struct_chain = fd.with_parameters(struct_chain, chain_vals)
        m = meas.with_parameters(sup_meas, meas_vals)
    params = [
        dataclasses.replace(p, guess=float(np.clip(_value_of(base, p.name), p.lower or -np.inf, p.upper or np.inf)))
        for p in parameters
    ]
    params += [Parameter(n, g) for n, g in new.items()]
    noise = dict(zip(channels, sigma))
    say(f"  structural candidate {c.label}: fitting its own model ...")
    try:
        problem = make_problem(
            struct_chain,
            params,
            _with_extra_state(fit_logs, struct_chain),
            noise,
            measurement=m,
            rtol=rtol,
            atol=1e-2 * rtol,
        )
        res = fit(
            problem,
            params,
            horizons=None,
            n_stages=2,
            n_starts=8 if new else 1,
            first_damping=0.0,  # without new parameters, a warm start from the baseline's values
            start_spread=3.0,
            estimate_noise=False,
            frequency_init=False,
            restart_poor_fit=False,
            max_steps=60,
            grid_error=None,  # as the baseline's (`diagnose_logs`)
            # (a per-log parameter's guess is one value for all logs: start them at their own too)
            extra_starts=_own_starts(base),
        )
        fitted = fd.with_parameters(struct_chain, res.shared_value)
        # the held-out logs' own values of the per-log parameters are their only free ones
        own = [
            dataclasses.replace(p, guess=_value_of(res, p.name), per_log=True)
            for p in params
            if getattr(p, "per_log", False)
        ]
        ho_problem = make_problem(
            fitted,
            own,
            _with_extra_state(held_out_logs, struct_chain),
            noise,
            measurement=m,
            rtol=rtol,
            atol=1e-2 * rtol,
        )
        ho_own = _Own.of(ho_problem)
        v0 = _held_out_start(ho_problem, ho_own, res)
        thetas = jnp.zeros((1, len(ho_problem.names)))  # (every entry is an own value)
        r_ho, _, _ = _held_out_batch(ho_problem, thetas, v0, ho_own, jnp.asarray(sigma), res.step, 25)
    except (RuntimeError, ValueError) as e:
        reason = error_reason(e)
        say(f"  structural candidate {c.label} failed: {reason}")
        rigid = _rigid_limit(c, e, setting.nyquist_hz)
        return reason if rigid is None else _FailedTowardRigid(reason, rigid)
    k = len(new)
    k_eff = max(k, 1)
    dbic = N * math.log(max(res.cost, 1e-300) / current["cost"]) + k * math.log(N)
    dof = max(N - len(problem.names) - len(problem.y0_free) - len(problem.offset_free), 1)
    F = ((current["cost"] - res.cost) / k_eff) / (res.cost / dof)
    p_value = float(stats.f.sf(F, k_eff, dof))
    used = _used(ho_problem)
    r_ho = np.asarray(r_ho[0])
    rms_ch = _rms_per_channel(ho_problem, r_ho, np.asarray(sigma))
    rms_c = float(np.sqrt(np.mean(r_ho[used] ** 2)))
    gain = rms_cur / rms_c if rms_c > 0 else np.inf
    vals = {n: float(v) for n, v in res.value.items() if n in new}
    # the new parameters' intervals from the structural model's own fit (exact Jacobian)
    intervals = {
        n: {"std_error": float(res.std_errors[i]), "ci95": [float(res.ci_low[i]), float(res.ci_high[i])]}
        for i, n in enumerate(res.names)
        if n in new
    }
    score = Score(
        c.name,
        c.where,
        vals,
        float(res.cost),
        float(dbic),
        p_value,
        rms_ch,
        float(gain),
        bool(dbic < -bic_threshold and gain >= min_gain),
        k,
        intervals=intervals,
        held_out_gain_se=gain_standard_error(np.asarray(current["ho"]), r_ho[used]),
    )
    fitted_params = [dataclasses.replace(p, guess=_value_of(res, p.name)) for p in params]
    model = {
        "chain": fitted,
        "measurement": m,
        "parameters": fitted_params,
        "fit": res,
        "held_out_cost": float(np.sum(r_ho[used] ** 2)),
        "held_out_problem": ho_problem,
        "held_out_residual": r_ho[used],
    }
    return score, model


def _value_of(result: FitResult, name: str) -> float:
    """A free parameter's fitted value; for a per-log one (`Parameter.per_log`), the median
    of the logs' values (a start for a refit)."""
    if name in result.per_log:
        return float(np.median(list(result.per_log[name].values())))
    return float(result.value[name])


def _own_starts(result: FitResult) -> tuple:
    """`fit`'s `extra_starts` that start each log's own value of a per-log parameter at its
    value in `result` (none without per-log parameters): a `Parameter`'s guess is one value
    for all logs, their median in a refit (`_value_of`), which may be far from a log's own.
    A structural candidate's multi-start gets this warm start beside its design (one start
    more). (The search from a structural winner refits its baseline from one start, the
    median, warm in the other parameters: on the arm with payloads 30 and 50 g it reached
    the noise floor from there.)"""
    own = {f"{name}[{log}]": v for name, by_log in result.per_log.items() for log, v in by_log.items()}
    return (own,) if own else ()


def _with_extra_state(logs, chain):
    """Logs whose initial-state names exist in `chain` (a structural change may add
    coordinates; their initial values default to 0)."""
    from .channels import state_names

    names = set(state_names(chain))
    out = []
    for log in logs:
        out.append(
            dataclasses.replace(
                log,
                initial={k: v for k, v in log.initial.items() if k in names},
                fit_initial=tuple(k for k in log.fit_initial if k in names),
            )
        )
    return out


def diagnose(experiment, *, progress=None, **options) -> Diagnosis:
    """Diagnose an `Experiment` (see the module docstring); `options` go to `diagnose_logs`.
    The baseline fit starts from the experiment's `[[starts]]` too (`fit_options`'
    `extra_starts`, unless the caller gives them)."""
    from .experiment import Experiment
    from .run import log_data, parameters

    if not isinstance(experiment, Experiment):
        raise TypeError(
            f"diagnose: expected an Experiment (identify.load_experiment(path)), got {type(experiment).__name__} "
            f"{experiment!r}"
        )
    options["fit_options"] = {"extra_starts": experiment.starts, **(options.get("fit_options") or {})}

    n = experiment.chain.n_links
    fit_logs = [log_data(s, n) for s in experiment.fit_logs]
    val_logs = [log_data(s, n) for s in experiment.validation_logs]
    time_split = not val_logs and len(fit_logs) == 1
    fit_logs, held, desc = split_logs(fit_logs, val_logs)
    noise = {c: v for c, v in experiment.noise.items() if v is not None}
    return diagnose_logs(
        experiment.chain,
        # (a time split holds out a segment of the one log: a per-log parameter is its value)
        parameters(experiment, per_log=not time_split),
        fit_logs,
        held,
        noise,
        measurement=experiment.measurement,
        split=desc,
        progress=progress,
        **options,
    )


__all__ = ["Cause", "Diagnosis", "Score", "diagnose", "diagnose_logs", "split_logs"]

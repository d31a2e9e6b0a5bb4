"""One model holding every continuous catalogue candidate at its neutral value (`Superset`), and its
batched Levenberg-Marquardt fits (each candidate a row of one vmapped program).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import flexdyn as fd

from .._data import measurement as meas
from .._fit.steps import aligned_step
from .._model.parameters import Bounds, Parameter, exp_natural, x_from_z
from .._model.problem import Problem, make_problem
from .._model.residuals import (
    initial_states_of,
    log_blocked,
    log_jacobian,
    predict_jit,
    residuals as _residuals_from,
)
from .._model.variables import AbstractVariables
from . import catalogue as cat

SLOTS = 4  # extension parameters one fit can free at a time (accepted + candidate)


class JointShared(eqx.Module):
    """The shared part of `JointVariables`: `xe` the extension slots' natural values `(SLOTS,)`
    (a log-scale slot holds the logarithm), `zb` the baseline's transformed coordinates."""

    xe: jax.Array
    zb: jax.Array


class JointVariables(AbstractVariables):
    """The variables of a joint-model fit (`Superset`): the baseline's free parameters in
    transformed coordinates (`zb`, as `identify.fit`'s `Variables.phys`), the extension slots'
    natural values (`xe`, `SLOTS`; which parameters they hold is the fit's slot layout), and
    the per-log nuisances `y0`, `offset`. Batch-first in the vmapped fits."""

    offset: jax.Array
    xe: jax.Array
    y0: jax.Array
    zb: jax.Array

    @property
    def shared(self) -> JointShared:
        return JointShared(self.xe, self.zb)

    def with_parts(self, shared: JointShared, y0, offset) -> JointVariables:
        return JointVariables(offset=offset, xe=shared.xe, y0=y0, zb=shared.zb)


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


def _bounds(j: _Joint) -> Bounds:
    """The bounds of the joint model's baseline block (its first `nb` parameters)."""
    return Bounds(j.problem.lower[: j.nb], j.problem.upper[: j.nb])


def _unpack(args):
    j, idx, logf, sigma, step = args
    return j.problem, lambda s: _theta(j, x_from_z(_bounds(j), s.zb), s.xe, idx, logf), sigma, None, step


def _residual(v: JointVariables, args):
    problem, theta_of, sigma, horizon, step = _unpack(args)
    return _residuals_from(problem, theta_of(v.shared), v.y0, v.offset, sigma, horizon, step)[0]


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
    theta_of = lambda w: _theta(j, *w, idx, logf)  # noqa: E731  (w = (xb, xe))
    jac = log_jacobian(j.problem, theta_of, (xb, xe), y0, off, sigma, None, step)
    return jac.r.reshape(-1), jac.dense(len(j.problem.y0_free), len(j.problem.offset_free))


_predict = predict_jit  # shared with identify.fit.fitted_outputs: one compiled program


Z_SATURATION = 6.0


def _unsaturated(j: _Joint, zb):
    """`zb` with every bounded coordinate pulled back to at most `Z_SATURATION` inside its
    transform's linear range. A parameter the misspecified baseline pushed onto its bound sits
    where the sigmoid is flat (dx/dz ~ 1e-22 at z ~ -50), where Levenberg-Marquardt cannot move
    it back once an extension makes the bound no longer optimal; at |z| = 6 it moves by at most
    0.25 % of its (log-)range and regains a usable gradient."""
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
#: `STEP_DIVISORS` within it, and so does the search (`_finer_step`). On the shipped example
#: (`identify/examples/pendulum_friction`) this bar keeps a candidate's fitted values within
#: ~0.1 standard errors of those at a 10x finer step.
STEP_RECHECK = 0.05


#: `_finer_step`: the steps tried, as divisors of the round's step, coarsest first ...
STEP_DIVISORS = (2, 4, 8)


#: ... against the outputs at the step over this (Tsit5 is fifth order: 16x finer is ~1e6
#: times more accurate, a reference without an adaptive solve of its own to compile)
REFERENCE_DIVISOR = 16


#: `_refine` and `reconverge` continue one or a few fits of a round. Padded to the round's
#: batch size they reuse its compiled program, but every padded copy costs as much as a
#: fit (on CPU a vmapped member is a fit of its own). When the round's batch call took longer
#: than this (seconds: compiling plus running), they run at the smallest batch size that holds
#: them instead (`_few_size`), paying one compilation to save the copies; below it, a second
#: program would cost more than the copies.
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
    `_few_size`). Returns the variables and costs with the continued fits in. Candidates
    drifting to their neutral value (dBIC > 0 and no prediction below 0) and those far behind
    the best one (dBIC above half the lowest) are left alone: they cannot win.

    `predicted`: label -> the cost the screening's Gauss-Newton step predicted; a fit that
    ran out of steps short of it counts as a contender at the predicted dBIC.

    A winner's scores and 95 % intervals must be those of its optimum, and a fit stopped
    after `max_steps` can end far from it, even above the model it extends."""
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
        v0 = vs.take(sel)
        out, c2, s2 = _fit_batch(joint, _pad(v0, n), _pad(idx[sel], n), _pad(logf[sel], n), sigma, step, max_steps)
        c2, s2 = np.asarray(c2, dtype=float), np.asarray(s2)
        moved = False
        for i, b in enumerate(more):
            if np.isfinite(c2[i]) and c2[i] < costs[b]:
                improving = N * (costs[b] - c2[i]) / costs[b] >= 0.1
                moved |= improving
                vs = jax.tree_util.tree_map(lambda v, o: v.at[b].set(o[i]), vs, out)
                costs[b] = c2[i]
                # a start that stopped improving counts as converged
                steps[b] = s2[i] if improving else 0
            else:
                steps[b] = 0
        if not moved:
            break
    return vs, costs


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


def _best_starts(vs, costs, steps, owners) -> tuple:
    """A candidate batch's results trimmed to its `len(owners)` starts (host copies of the
    costs and step counts) and each candidate's best start, `{label: index}`."""
    B = len(owners)
    vs = vs.take(slice(None, B))
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
    y0s = initial_states_of(problem, y0_free)
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


def _pad_used(r_used, used):
    full = np.zeros(used.shape[0])
    full[used] = r_used
    return full


@dataclasses.dataclass(frozen=True)
class Superset:
    """The joint model of one search: the rig and sensors with every continuous candidate's
    parameters (`ext_names`, at their `neutral` values), fitted on the fit logs (`joint`,
    its problem's parameter vector the baseline's entries then the extensions), the residual
    entries that count (`used`, `N` of them) and the channels' noise `sigma` (SI; `sigma_j`
    the same as a JAX array, for the compiled programs)."""

    chain: fd.Chain
    measurement: meas.Measurement
    parameters: list  # the baseline's free `Parameter`s, then one per extension parameter
    ext_names: list[str]
    neutral: list[float]
    joint: _Joint
    used: np.ndarray
    N: int
    sigma: np.ndarray
    sigma_j: jax.Array
    controller: object = None  # the logs' `identify.Controller` (None: open loop)

    @property
    def problem(self) -> Problem:
        return self.joint.problem

    def layout(self, names_vals) -> tuple:
        """Slot index, log flags and starting natural values for [(name, value, is_log), ...]."""
        idx = np.full(SLOTS, len(self.ext_names), int)
        logf = np.zeros(SLOTS, bool)
        x = np.zeros(SLOTS)
        for s, (n, val, is_log) in enumerate(names_vals):
            idx[s] = self.ext_names.index(n)
            logf[s] = is_log
            x[s] = np.log(val) if is_log else val
        return idx, logf, x

    def theta_of(self, v, idx, logf):
        """The physical parameter vector (SI) of the joint model's variables `v` in slot layout `idx`, `logf`."""
        xb = x_from_z(_bounds(self.joint), v.zb)
        return _theta(self.joint, xb, v.xe, jnp.asarray(idx), jnp.asarray(logf))


def superset_of(
    chain, measurement, channels, driven, candidates, parameters, fit_logs, sigma, nb: int, *, controller=None
) -> Superset:
    """The joint model of the continuous `candidates` on the baseline's `chain` and
    `measurement` (`catalogue.superset`), its free `parameters` (`nb` entries in the
    baseline's parameter vector) and every candidate parameter, fitted on `fit_logs` with
    the channels' noise `sigma`; closed loop under `controller` (`identify.Controller`)."""
    sup_chain, sup_meas = cat.superset(chain, measurement, channels, driven)
    ext_names = []
    for c in candidates:
        if not c.structural:
            ext_names.extend(n for n in c.params if n not in ext_names)
    ext_params = [
        Parameter(
            n, 0.0 if (meas.is_signed(n) if meas.is_measurement_parameter(n) else fd.is_signed(sup_chain, n)) else 1.0
        )
        for n in ext_names
    ]
    sup_problem = make_problem(
        sup_chain,
        parameters + ext_params,
        fit_logs,
        dict(zip(channels, sigma)),
        measurement=sup_meas,
        controller=controller,
    )
    neutral = []
    for n in ext_names:
        neutral.append(
            float(meas.get_parameter(sup_meas, n))
            if meas.is_measurement_parameter(n)
            else float(fd.get_parameter(sup_chain, n))
        )
    joint = _Joint(sup_problem, jnp.asarray(neutral, dtype=float), nb)
    used = _used(sup_problem)
    return Superset(
        sup_chain,
        sup_meas,
        parameters + ext_params,
        ext_names,
        neutral,
        joint,
        used,
        int(used.sum()),
        sigma,
        jnp.asarray(sigma),
        controller,
    )

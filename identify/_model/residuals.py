"""Simulated outputs, weighted residuals and their Jacobian, for a fitting `Problem`.

A problem's residuals are

    r[l, k, c] = (y_c(t_lk; theta, x0_l) + o_lc - m_lkc) / sigma_c

(simulated minus measured output `c` of log `l` at sample `k`, plus a per-log sensor
offset `o_lc`; see `identify.fit`). The physical parameters `theta` are shared by every
log; the nuisances (free initial-state entries of `x0_l`, offsets `o_l`) belong to one log
each. So the Jacobian is block-arrow shaped: a dense column block for `theta`, then one
small block per log for its own nuisances, zero elsewhere.

**Why it matters.** Forward-mode differentiation of the whole residual vector (`jax.jacfwd`)
pushes every column's tangent through every log's ODE solve: with `L` logs of `k`
nuisances each, each solve carries `P + L k` tangents, and a Jacobian costs `L (P + L k)`
tangent solves, quadratic in the number of logs (measurements in docs/performance.md,
"Joint fits of many logs").
`log_jacobian` differentiates each log's residuals w.r.t. the shared parameters and that
log's own initial-state entries only (`P + k_y0` tangents per solve, `vmap` over logs),
and the offsets in closed form (`dr/do_lc = 1/sigma_c` where the sample is used): linear
in the number of logs. `log_blocked` wraps a residual function so that
Levenberg-Marquardt (optimistix) linearises it this way.
"""

from __future__ import annotations

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

import flexdyn as fd
from flexdyn.held_steps import clipped_constant_steps
from flexdyn.simulation import adaptive_controller as _adaptive_controller

from .._data import channels as ch, measurement as meas
from .closed_loop import closed_log_outputs
from .sensed import recorded_outputs


def _values(problem, theta, log_values=None, log_index=None) -> dict:
    """Parameter name -> value of one log's simulation: the shared free parameters
    `theta` (in `problem.names` order), the log's known values `log_values` (a row of
    `Problem.log_set`) and its own values of the per-log free parameters
    (`Problem.per_log`: their entries of `theta` at `log_index`, which may be traced)."""
    own = {i for _, index in problem.per_log for i in index}
    values = {n: theta[i] for i, n in enumerate(problem.names) if i not in own}
    if log_values is not None:
        values.update({n: log_values[k] for k, n in enumerate(problem.log_set_names)})
    if problem.per_log:
        if log_index is None:
            raise ValueError("identify.residuals: a problem with per-log parameters needs the log's index")
        theta = jnp.asarray(theta)
        for name, index in problem.per_log:
            values[name] = theta[np.asarray(index)][log_index]
    return values


def chain_at(problem, theta, log_values=None, log_index=None):
    """The problem's chain at parameters `theta`, with a log's known values `log_values`
    (a row of `Problem.log_set`) and per-log values (`_values`) if given."""
    values = _values(problem, theta, log_values, log_index)
    return fd.with_parameters(problem.chain, {n: v for n, v in values.items() if not meas.is_measurement_parameter(n)})


def _measurement(problem, theta, log_values=None, log_index=None):
    values = _values(problem, theta, log_values, log_index)
    sensors = {n: v for n, v in values.items() if meas.is_measurement_parameter(n)}
    return meas.with_parameters(problem.measurement, sensors)


def initial_states_of(problem, y0_free):
    """Initial states `(L, 2n)`: the known ones with the free entries `y0_free` (in
    `problem.y0_free` order) set."""
    y0 = problem.y0_known
    if problem.y0_free:
        rows = np.array([a for a, _ in problem.y0_free])
        cols = np.array([b for _, b in problem.y0_free])
        y0 = y0.at[rows, cols].set(y0_free)
    return y0


def sensor_offsets(problem, offset_free):
    """Sensor offsets `(L, C)`: zero but for the free ones (`problem.offset_free` order)."""
    off = jnp.zeros(problem.present.shape)
    if problem.offset_free:
        rows = np.array([a for a, _ in problem.offset_free])
        cols = np.array([b for _, b in problem.offset_free])
        off = off.at[rows, cols].set(offset_free)
    return off


def _strictly_increasing(t):
    # Padded logs repeat their last time; SampledTorque needs increasing knots.
    k = jnp.arange(t.shape[0], dtype=t.dtype)
    return jnp.where(jnp.concatenate([jnp.ones(1, bool), t[1:] > t[:-1]]), t, t[-1] + 1e-6 * k)


def _admissible(problem, theta, y0):
    """`(theta, y0, ok)`: the parameters and initial state with every non-finite entry
    (which the model refuses) replaced by a harmless value (1 for a parameter, 0 for a
    state entry), and whether none was. A Levenberg-Marquardt trial point far out (an unbounded
    log-scale stiffness whose exp overflowed to inf, a NaN from a singular step) must be a
    rejected step, as a failed solve is (`FAILED_RESIDUAL`), not stop the fit: the model's
    parameter checks (`eqx.error_if` at assembly) raise on it, and a diagnosis candidate
    with a new unbounded stiffness (joint elasticity) would fail with "joint1.stiffness
    must be finite and > 0" and drop out of the report."""
    theta = jnp.asarray(theta)
    # (finiteness only: a log-scale parameter at exactly 0 is legitimate where the model
    # allows >= 0, e.g. diagnose's candidates at their neutral values)
    good = jnp.isfinite(theta)
    y0_good = jnp.isfinite(y0)
    ok = jnp.all(good) & jnp.all(y0_good)
    return jnp.where(good, theta, 1.0), jnp.where(y0_good, y0, 0.0), ok


def _simulate_log(problem, theta, t, torque_v, y0, onset, horizon, step, stats: bool, log_values=None, log_index=None):
    """Outputs `(T, C)` of one log (times `t`, commanded torque samples `torque_v`,
    initial state `y0`, onset time `onset`: `Problem.onset`) and whether its solve
    succeeded.

    The solve stops at `onset + horizon`. It starts at `t[0]`, except when it stops before
    the log's end (an early stage of a growing horizon, `identify.fit`): then it starts at
    the onset, from `y0`, and the samples before it get `y0`'s outputs. Up to its onset a
    log shows the rig at rest (`identify.log_onset`), so a model at rest there is what
    the full solve would give with the right parameters; the early stages only have to
    land the fit in the right basin, and integrating seconds of rest at the motion's step
    in each of them makes a fit several times slower for the same optimum (see
    docs/performance.md). The last stage simulates the whole log. Parameters or an
    initial state the model would refuse (`_admissible`) count as a failed solve.
    `log_values`: the log's row of `Problem.log_set`; `log_index`: its index (for per-log
    parameters, `Problem.per_log`, and a closed-loop problem's references).

    A closed-loop problem (`Problem.loop`) runs each log under its controller instead
    (`closed_loop.closed_log_outputs`), `torque_v` the logged commands."""
    theta, y0, admissible = _admissible(problem, theta, y0)
    asm = fd.assemble(chain_at(problem, theta, log_values, log_index))
    sensors = _measurement(problem, theta, log_values, log_index)
    if horizon is None:
        t_begin, t_end = t[0], t[-1]
    else:
        t_end = jnp.minimum(t[-1], onset + horizon)
        t_begin = jnp.where(t_end < t[-1], onset, t[0])
    ts = jnp.clip(t, t_begin, t_end)
    if problem.loop is not None:  # a closed-loop log: the rig under its controller
        reference = problem.reference[0 if log_index is None else log_index]
        out, run = closed_log_outputs(problem, asm, sensors, ts, torque_v, reference, y0, step)
        ok = admissible & run.ok
        if stats == "limit":
            return out, ok, run.limited
        # (the step count as a float: summed over the periods it is a strong int, which
        # `identify.steps` divides a span by)
        return (out, ok, run.steps.astype(out.dtype)) if stats else (out, ok)
    torque = meas.actuated_torque(sensors, _strictly_increasing(t), torque_v, problem.hold)
    field = fd.ChainVectorField(asm, torque)
    # (fixed steps stop at a held torque's jumps, adaptive ones also at its constant
    # stretches' ends: `fd.held_steps`, `fd.SampledTorque.step_times`)
    if step is not None:
        solver, controller, dt0 = diffrax.Tsit5(), clipped_constant_steps(torque.jump_times()), step
    elif problem.dt is None:
        solver, controller, dt0 = diffrax.Tsit5(), _adaptive_controller(torque, problem.rtol, problem.atol), None
    else:
        solver, controller, dt0 = fd.RK4(), clipped_constant_steps(torque.jump_times()), problem.dt
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0=t_begin,
        t1=t_end,
        dt0=dt0,
        y0=y0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
        max_steps=problem.max_steps,
        adjoint=diffrax.ForwardMode(),
        throw=False,
    )
    ok = admissible & (sol.result == diffrax.RESULTS.successful) & jnp.all(jnp.isfinite(sol.ys))
    ys = jnp.where(ok, sol.ys, 0.0)
    out = open_loop_outputs(asm, problem.channels, sensors, field, ts, ys)
    if stats == "limit":  # (identify.fit._simulation_failure: why a solve failed)
        return out, ok, sol.result == diffrax.RESULTS.max_steps_reached
    return (out, ok, sol.stats["num_accepted_steps"]) if stats else (out, ok)


def open_loop_outputs(asm, channels, sensors, field: fd.ChainVectorField, ts, ys):
    """The recorded outputs `(T, C)` of an open-loop solve `ys` `(T, 2n)` at `ts` under
    `field` (its input a function of time)."""
    evaluate = lambda tk, yk: ch.evaluate(asm, channels, tk, yk, field.torque)  # noqa: E731
    return recorded_outputs(sensors, channels, ts, ys, evaluate, lambda tk, yk: field(tk, yk, None))


def predict(problem, theta, y0s, horizon=None, step=None, *, stats: bool = False):
    """Simulated outputs `(L, T, C)` and a success flag per log, for physical parameters
    `theta` (SI, in `problem.names` order) and initial states `y0s` `(L, 2n)`. Samples
    after `onset + horizon` (each log's `Problem.onset`) are not simulated (their value is
    that at the horizon).

    `step` (s, may be traced): integrate with Tsit5 at this constant step. Otherwise
    the problem's fixed `dt` (RK4) or its adaptive tolerances are used. With `stats`,
    also return the number of accepted steps per log (`stats="limit"`: whether the
    solve reached `problem.max_steps`, instead)."""

    def one(t, tv, y0, on, values, l):
        return _simulate_log(problem, theta, t, tv, y0, on, horizon, step, stats, values, l)

    L = problem.t.shape[0]
    return jax.vmap(one)(problem.t, problem.torque_v, y0s, problem.onset, problem.log_set, jnp.arange(L))


def used_mask(problem, horizon):
    """`(L, T, C)` mask of the residuals that count: valid samples of recorded channels,
    within the horizon (up to `onset + horizon`, each log's `Problem.onset`)."""
    mask = problem.valid[:, :, None] & problem.present[:, None, :]
    if horizon is not None:
        mask = mask & (problem.t <= problem.onset[:, None] + horizon)[:, :, None]
    return mask


# the weighted residual of every used sample of a log whose simulation failed
FAILED_RESIDUAL = 1e6


def residuals(problem, theta, y0_free, offset_free, sigma, horizon, step=None):
    """Weighted residuals (flat, log-major: `(L, T, C)` raveled; unused entries 0) and a
    success flag per log. A failed solve (wild parameters during the search) gives
    residuals of `FAILED_RESIDUAL` (1e6), so the optimiser rejects the step; the final solution is checked
    separately."""
    y0s = initial_states_of(problem, y0_free)
    pred, ok = predict(problem, theta, y0s, horizon, step)
    r = (pred + sensor_offsets(problem, offset_free)[:, None, :] - problem.measured) / sigma
    r = jnp.where(ok[:, None, None], r, FAILED_RESIDUAL)
    return jnp.where(used_mask(problem, horizon), r, 0.0).reshape(-1), ok


# ---------------------------------------------------------------------------
# The block-arrow Jacobian
# ---------------------------------------------------------------------------


def _slots(entries, L: int):
    """Per-log slots of the free nuisances `entries` ((log, index) pairs, in vector order):
    `(pos, index, used)`, each `(L, k)` with `k` the most any log has; `pos` is the
    entry's position in the vector, `index` the state (channel) index, `used` False on
    the padding of logs with fewer entries."""
    per = [[(p, i) for p, (l, i) in enumerate(entries) if l == k] for k in range(L)]
    k = max((len(e) for e in per), default=0)
    pos, index, used = np.zeros((L, k), int), np.zeros((L, k), int), np.zeros((L, k), bool)
    for l, e in enumerate(per):
        for j, (p, i) in enumerate(e):
            pos[l, j], index[l, j], used[l, j] = p, i, True
    return pos, index, used


def _spread(vector, pos, used):
    """`(L, k)` per-log slot values of a nuisance vector (0 on padding)."""
    if pos.shape[1] == 0:
        return jnp.zeros(pos.shape, vector.dtype)
    return jnp.where(used, vector[pos], 0.0)


class Layout(eqx.Module):
    """Where each log's nuisances sit in the variable vectors: per kind (0: `y0`, 1:
    `offset`) the `(L, k)` positions in the vector and whether each slot is used (logs with
    fewer entries are padded). Static; shared by `LogJacobian` and `identify.block_lm`."""

    n_logs: int = eqx.field(static=True)
    slots: tuple = eqx.field(static=True)  # ((pos rows, used rows), ...) for y0, then offset

    @staticmethod
    def of(problem) -> Layout:
        L = problem.t.shape[0]
        slots = []
        for entries in (problem.y0_free, problem.offset_free):
            pos, _, used = _slots(entries, L)
            slots.append((tuple(map(tuple, pos.tolist())), tuple(map(tuple, used.tolist())), pos.shape))
        return Layout(L, tuple(slots))

    def arrays(self, kind: int):
        pos, used, shape = self.slots[kind]
        return np.asarray(pos, int).reshape(shape), np.asarray(used, bool).reshape(shape)


class LogJacobian(eqx.Module):
    """Residuals and their block-arrow Jacobian (see the module docstring).

    - `r`: `(L, n)` weighted residuals per log (`n = T C`).
    - `shared`: `(L, n, P)` w.r.t. the flattened shared variables.
    - `y0`: `(L, n, k)` w.r.t. each log's free initial-state entries (its slots; padding
      slots have zero columns).
    - `offset`: `(L, n, m)` w.r.t. each log's free offsets (slots, likewise).
    - `ok`: `(L,)` whether each log's solve succeeded."""

    r: jax.Array
    shared: jax.Array
    y0: jax.Array
    offset: jax.Array
    ok: jax.Array
    layout: Layout

    def apply(self, t_shared, t_y0, t_offset):
        """`J @ (t_shared, t_y0, t_offset)`: flat `(L n,)` (tangents in vector order)."""
        dr = self.shared @ t_shared
        dr = dr + jnp.einsum("lnk,lk->ln", self.y0, _spread(t_y0, *self.layout.arrays(0)))
        dr = dr + jnp.einsum("lnk,lk->ln", self.offset, _spread(t_offset, *self.layout.arrays(1)))
        return dr.reshape(-1)

    def dense(self, n_y0: int, n_offset: int):
        """The whole Jacobian `(L n, P + n_y0 + n_offset)`, columns: shared, initial-state
        entries, offsets (each in vector order)."""
        L, n, _ = self.shared.shape

        def place(block, kind, width):
            pos, used = self.layout.arrays(kind)
            onehot = np.zeros((L, pos.shape[1], width))
            for l, j in zip(*np.nonzero(used)):
                onehot[l, j, pos[l, j]] = 1.0
            return jnp.einsum("lnk,lkm->lnm", block, onehot).reshape(L * n, width)

        return jnp.concatenate(
            [
                self.shared.reshape(L * n, -1),
                place(self.y0, 0, n_y0),
                place(self.offset, 1, n_offset),
            ],
            axis=1,
        )


def log_jacobian(problem, theta_of: Callable, shared, y0_free, offset_free, sigma, horizon, step=None) -> LogJacobian:
    """Residuals of `problem` at `theta_of(shared)` (physical parameters from any pytree
    of shared variables) with nuisances `y0_free`, `offset_free`, and their Jacobian:
    each log's solve carries `P + k` tangents (`P` shared variables, `k` initial-state
    entries of the log), `vmap`ped over logs; the offsets' columns are exact in closed
    form. Same values and derivatives as `jax.jacfwd` of `residuals`."""
    L = problem.t.shape[0]
    dtype = problem.y0_known.dtype
    flat, unravel = ravel_pytree(shared)
    flat = flat.astype(dtype)  # (an empty pytree ravels to float32)
    y0_pos, y0_index, y0_used = _slots(problem.y0_free, L)
    off_pos, off_index, off_used = _slots(problem.offset_free, L)
    u = _spread(jnp.asarray(y0_free, dtype), y0_pos, y0_used)
    offsets = sensor_offsets(problem, offset_free)
    mask = used_mask(problem, horizon)

    # Per-log parameters (`Problem.per_log`): a log's residuals depend on its own entries of
    # the shared vector only, so each solve carries the common entries' and its own
    # entries' tangents (not every log's), and the other logs' columns are zero. That holds
    # where the shared variables are one vector entry for entry with `problem.names` (`fit`'s
    # natural or transformed coordinates; `theta_of` maps entry i to parameter i); any other
    # pytree (diagnose's joint model: the baseline's entries and the candidates' slots)
    # carries all `P` tangents.
    P = flat.shape[0]
    own = np.array([index for _, index in problem.per_log], int).T.reshape(L, -1)  # (L, p)
    leaves = jax.tree_util.tree_leaves(shared)
    if not (len(leaves) == 1 and jnp.shape(leaves[0]) == (len(problem.names),)):
        own = np.zeros((L, 0), int)
    common = np.setdiff1d(np.arange(P), own.ravel())

    def one(t, tv, y0_known, onset, values, measured, off, used, idx, u_l, slot_used, l, own_l):
        def f(common_, own_, u_):
            flat_ = flat.at[common].set(common_).at[own_l].set(own_) if own.size else common_
            y0 = y0_known.at[idx].add(jnp.where(slot_used, u_ - y0_known[idx], 0.0))
            theta = theta_of(unravel(flat_))
            out, ok = _simulate_log(problem, theta, t, tv, y0, onset, horizon, step, False, values, l)
            r = jnp.where(ok, (out + off - measured) / sigma, FAILED_RESIDUAL)
            r = jnp.where(used, r, 0.0).reshape(-1)
            return r, (r, ok)

        args = (flat[common], flat[own_l], u_l)
        (J_common, J_own, J_y0), (r, ok) = jax.jacfwd(f, argnums=(0, 1, 2), has_aux=True)(*args)
        J_shared = J_common if not own.size else jnp.zeros((r.shape[0], P), dtype).at[:, common].set(J_common)
        J_shared = J_shared.at[:, own_l].set(J_own) if own.size else J_shared
        return r, J_shared, J_y0, ok

    r, J_shared, J_y0, ok = jax.vmap(one)(
        problem.t,
        problem.torque_v,
        problem.y0_known,
        problem.onset,
        problem.log_set,
        problem.measured,
        offsets,
        mask,
        y0_index,
        u,
        y0_used,
        jnp.arange(L),
        jnp.asarray(own),
    )
    # dr[l, k, c] / do_lc = 1 / sigma_c where the residual is used (and the solve succeeded)
    d_off = jnp.where(mask & ok[:, None, None], 1.0 / sigma, 0.0)  # (L, T, C)
    onehot = jnp.asarray(np.eye(mask.shape[2])[off_index] * off_used[..., None])  # (L, m, C)
    J_off = jnp.einsum("ltc,lmc->ltcm", d_off, onehot).reshape(L, r.shape[1], off_index.shape[1])
    return LogJacobian(r, J_shared, J_y0, J_off, ok, Layout.of(problem))


def log_blocked(unpack: Callable) -> Callable:
    """A residual function `fn(v, args)` for optimistix's least squares whose linearisation
    is the block-arrow Jacobian (`log_jacobian`), computed once per linearisation.

    `v` is a variables record (`variables.AbstractVariables`: its nuisances `v.y0`,
    `v.offset` in `problem.y0_free` / `problem.offset_free` order, the rest `v.shared`);
    `unpack(args)` returns `(problem, theta_of, sigma, horizon, step)`, `theta_of` mapping
    `v.shared` to the physical parameters. The value is `residuals(...)`.

    Levenberg-Marquardt (`optx.LevenbergMarquardt`) takes `jax.linearize` of the residuals
    at every trial point and keeps the linear map lazy: `jax.linearize` through a
    `while_loop` (diffrax's) re-runs the whole loop, primal included, each time the map is
    applied, and each step applies it twice (the predicted reduction of the trust region,
    then once per column when the damped system is factorised by QR). That is a primal
    solve, a one-tangent solve and an n-tangent solve per step. With this rule the
    linearisation computes the residuals and the Jacobian in one forward-mode solve per log
    and the linear map is a product with the stored blocks. Only `v` may be differentiated;
    `args` are constants of the fit."""

    @eqx.filter_custom_jvp
    def wrapped(v, args):
        problem, theta_of, sigma, horizon, step = unpack(args)
        return residuals(problem, theta_of(v.shared), v.y0, v.offset, sigma, horizon, step)[0]

    @wrapped.def_jvp
    def wrapped_jvp(primals, tangents):
        v, args = primals
        tv, targs = tangents
        if any(t is not None for t in jax.tree_util.tree_leaves(targs)):
            raise NotImplementedError("log_blocked: only the first argument (the variables) may be differentiated")
        problem, theta_of, sigma, horizon, step = unpack(args)
        jac = log_jacobian(problem, theta_of, v.shared, v.y0, v.offset, sigma, horizon, step)

        def flat(primal, tangent):
            # the tangent in `ravel_pytree`'s order; None (not differentiated) is zero
            leaves = jax.tree_util.tree_leaves(primal)
            parts = jax.tree_util.tree_structure(primal).flatten_up_to(tangent) if leaves else []
            parts = [jnp.zeros_like(p) if t is None else t for p, t in zip(leaves, parts)]
            return jnp.concatenate([jnp.reshape(t, (-1,)) for t in parts]) if parts else jnp.zeros((0,), jac.r.dtype)

        if tv is None:
            return jac.r.reshape(-1), jnp.zeros_like(jac.r.reshape(-1))
        return jac.r.reshape(-1), jac.apply(flat(v.shared, tv.shared), flat(v.y0, tv.y0), flat(v.offset, tv.offset))

    return wrapped


# compiled once per problem layout (an eager call re-traces and runs the assembly op by op)
predict_jit = eqx.filter_jit(predict)

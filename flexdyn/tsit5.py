"""Adaptive Tsit5 with a discrete-adjoint reverse-mode derivative: `tsit5_trajectory`.

`tsit5_trajectory(chain, y0, ts, torque, rtol=..., atol=...)` is `simulate(chain, y0, ts,
torque, rtol=..., atol=...)` (diffrax's `Tsit5` with a PID step-size controller, steps
clipped onto the input's jumps, the states at `ts` from Tsit5's dense output): the same
solve, the same numbers. What differs is its reverse-mode derivative (`jax.grad`,
`jax.vjp`): the discrete adjoint of the steps diffrax took, instead of diffrax's
checkpointed reverse pass through its general Runge-Kutta stage loop.

**The derivative.** The forward solve keeps the state at the end of every accepted step
(`SaveAt(steps=True)`: `max_steps x 2n` floats). With the step sizes held fixed, as
diffrax's own gradient holds them (its PID controller stops their gradient), each step is
a map `y_{k+1} = Phi_k(y_k, p)` of seven stages `Y_i = y_k + h sum_j a_ij f_j`, `f_i =
f(t_k + c_i h, Y_i)`, with `y_{k+1} = Y_7` (Tsit5's last stage is its solution), and each
output in the step is the dense output `y(t_k + theta h) = y_k + h sum_i b_i(theta) f_i`
(Tsitouras 2011, "Runge-Kutta pairs of order 5(4) satisfying only the first column
simplifying assumption"; the tableau and `b_i(theta)` are diffrax's own). Backwards over
the accepted steps, each step's stages are computed again from `y_k`, with each stage's
accelerations and Cholesky factor of `M`, and transposed in reverse order
(`lambda_k = (dPhi_k / dy)^T lambda_{k+1} + ` the outputs' cotangents), each stage by one
reverse pass over the scalar `w^T r` of the Lagrange residual at fixed accelerations
(`flexdyn.fixed_step.stage_vjp`: no mass matrix is formed or factorised in the
transpose). This is the exact derivative of the computed states at those step sizes
(Hager 2000; Sandu 2006). It equals diffrax's reverse-mode gradient through `simulate`
(tested to 1e-8 relative, across input jumps), except for the input's switching times.

**Switching times** (`BangBang.width`, `.start`; the sample times of a zero-order-hold
`SampledTorque`: whatever `jump_times()` is computed from). The steps are laid out on the
jumps, so moving a jump `J` moves no step here; its derivative is the solution's
(the classic jump condition of optimal control, e.g. Bryson & Ho 1975, sec. 3.7):

    dL/dJ = lambda(J)^T (f(J^-, y(J)) - f(J^+, y(J))),

with `lambda(J)` the adjoint at the step boundary on `J` (the discrete adjoint
`lambda_{k+1}`), `f(J^-)` the last stage of the step that ends there and `f(J^+)` the
first of the next (their velocity rows are equal, so only the accelerations differ). The
cotangents of the jump times are pulled back through `jump_times()` to the input's fields.
Tested against central differences of a Dopri8 solution: 1e-6 relative at rtol 1e-10,
1e-4 at rtol 1e-7. diffrax's reverse mode instead differentiates its step times, and is
not this derivative at usual tolerances (the same test: -3055 against 11.05 at rtol 1e-7).
Where the loss has a kink this is a one-sided derivative: a jump on an output time (the
derivative for moving the jump earlier), and a jump at `ts[0]` or `ts[-1]` (0: moving it
out of the interval changes nothing).

Cost: `value_and_grad` about 4x its forward solve (the same solve as `simulate`'s), less
than diffrax's reverse mode through `simulate` (`benchmarks/bench_gradient_cost.py`,
`docs/performance.md`). The backward pass is, per step, seven right-hand sides with their
factors and seven stage transposes. Memory: the step record, `max_steps x (2n + 1)`
floats. Forward mode (`jax.jvp`,
`jax.jacfwd`) is not defined for this function (it has its own `custom_vjp`): use
`simulate` with `adjoint=diffrax.ForwardMode()`.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .chain import AssembledChain, Chain, solve_forward_dynamics
from .fixed_step import stage_vjp
from .inputs import ZeroTorque
from .simulation import ChainVectorField, Trajectory, adaptive_controller, prepare

_TABLEAU = diffrax.Tsit5.tableau
_C = (0.0, *(float(c) for c in _TABLEAU.c))  # the stage times t_k + c_i h, 7 stages
_A = ((), *(tuple(float(a) for a in row) for row in _TABLEAU.a_lower))  # Y_i = y_k + h sum_j A[i][j] f_j
assert _TABLEAU.ssal and len(_A) == 7, "diffrax's Tsit5 tableau changed: y_{k+1} is no longer the last stage"
_A_MATRIX = np.array([list(row) + [0.0] * (7 - len(row)) for row in _A])  # strictly lower triangular
_C_VECTOR = np.array(_C)


def _dense_weights(theta):
    """`b_i(theta)`, i = 1..7, of Tsit5's dense output `y(t_k + theta h) = y_k + h sum_i
    b_i(theta) f_i`, evaluated by diffrax's own interpolation (unit stage increments)."""
    unit = diffrax.Tsit5.interpolation_cls(t0=0.0, t1=1.0, y0=jnp.zeros(7), y1=None, k=jnp.eye(7))
    return unit.evaluate(theta)


def _solve(dynamic, static, y0, ts, rtol, atol, max_steps, dtmax):
    """diffrax's Tsit5, as `simulate`: the states at `ts`, and at the end of every accepted
    step (`t_steps`, `y_steps`, padded with inf to `max_steps`)."""
    asm, torque = eqx.combine(dynamic, static)
    controller = adaptive_controller(torque, rtol, atol, dtmax, probe=(ts[0], ts[-1], y0))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(ChainVectorField(asm, torque)),
        diffrax.Tsit5(),
        t0=ts[0],
        t1=ts[-1],
        dt0=None,
        y0=y0,
        saveat=diffrax.SaveAt(subs=[diffrax.SubSaveAt(ts=ts), diffrax.SubSaveAt(steps=True)]),
        stepsize_controller=controller,
        max_steps=max_steps,
        throw=False,
    )
    (ys, y_steps), (_, t_steps) = sol.ys, sol.ts
    # The step count and the outcome travel as floats: boolean outputs of a `custom_vjp`
    # trip `eqx.error_if` under `jax.grad`.
    flags = (
        sol.stats["num_accepted_steps"],
        sol.result == diffrax.RESULTS.max_steps_reached,
        sol.result != diffrax.RESULTS.successful,
    )
    info = jnp.stack([jnp.asarray(f).astype(ys.dtype) for f in flags])
    return ys, t_steps, y_steps, sol.stats["num_accepted_steps"], info


@eqx.filter_custom_vjp
def _tsit5_adjoint(vjp_arg, static, ts, rtol, atol, max_steps, dtmax):
    dynamic, y0 = vjp_arg
    ys, _, _, _, info = _solve(dynamic, static, y0, ts, rtol, atol, max_steps, dtmax)
    return ys, info


@_tsit5_adjoint.def_fwd
def _tsit5_adjoint_fwd(perturbed, vjp_arg, static, ts, rtol, atol, max_steps, dtmax):
    del perturbed
    dynamic, y0 = vjp_arg
    ys, t_steps, y_steps, num_steps, info = _solve(dynamic, static, y0, ts, rtol, atol, max_steps, dtmax)
    return (ys, info), (t_steps, y_steps, num_steps)


def _stages(dynamic, static, t0, h, y):
    """The seven stages of the Tsit5 step from `(t0, y)` of size `h`, in a `lax.scan` (one
    right-hand side in the compiled program): their times, states, accelerations and upper
    Cholesky factors of `M` (the residuals of `stage_vjp`)."""
    asm, torque = eqx.combine(dynamic, static)
    n = y.shape[0] // 2

    def stage(fs, i):
        Y = y + h * (jnp.asarray(_A_MATRIX)[i] @ fs)
        t = t0 + jnp.asarray(_C_VECTOR)[i] * h
        Qdd, (factor, lower) = solve_forward_dynamics(asm, Y[:n], Y[n:], torque(t, Y))
        return fs.at[i].set(jnp.concatenate([Y[n:], Qdd])), (t, Y, Qdd, factor.T if lower else factor)

    _, recorded = jax.lax.scan(stage, jnp.zeros((7, y.shape[0]), y.dtype), jnp.arange(7))
    return recorded


def _step_ends(t_steps, jumps):
    """The end of each accepted step. `SaveAt(steps=True)` records the time the next step
    starts; across an input jump `J` they differ: diffrax's `ClipStepSizeController` ends
    the step at the float before `J` (its stages never read the far side) and starts the
    next one at the float after `J`."""
    if jumps is None:
        return t_steps
    jumps = jnp.sort(jnp.atleast_1d(jnp.asarray(jumps, dtype=t_steps.dtype)))
    if jumps.shape[0] == 0:
        return t_steps
    candidate = jnp.nextafter(t_steps, -jnp.inf)  # the jump, if this step was bumped past one
    nearest = jumps[jnp.clip(jnp.searchsorted(jumps, candidate), 0, jumps.shape[0] - 1)]
    return jnp.where(nearest == candidate, jnp.nextafter(candidate, -jnp.inf), t_steps)


def _jump_cotangent(jumps, t_end, t_steps, contribution):
    """The cotangent of `jumps` (the input's `jump_times()`, any shape) from the per-step
    `contribution`: step `k` that ends at the float before a jump `J` (`t_end[k] <
    t_steps[k]`, see `_step_ends`) gives its `contribution[k]` to the entries equal to `J`
    (shared equally among equal entries)."""
    flat = jnp.ravel(jnp.asarray(jumps, dtype=t_end.dtype))
    order = jnp.argsort(flat)
    ordered = flat[order]
    at = jnp.nextafter(t_end, jnp.inf)  # the jump a bumped step ends before
    index = jnp.clip(jnp.searchsorted(ordered, at), 0, flat.shape[0] - 1)
    hit = (t_end < t_steps) & (ordered[index] == at)
    summed = jnp.zeros_like(ordered).at[index].add(jnp.where(hit, contribution, 0.0))
    first = jnp.searchsorted(ordered, ordered, side="left")
    count = jnp.searchsorted(ordered, ordered, side="right") - first
    shared = summed[first] / count.astype(summed.dtype)
    return jnp.zeros_like(flat).at[order].set(shared).reshape(jnp.shape(jumps))


@_tsit5_adjoint.def_bwd
def _tsit5_adjoint_bwd(residuals, grads, perturbed, vjp_arg, static, ts, rtol, atol, max_steps, dtmax):
    r"""Backwards over the accepted steps `k = N-1, ..., 0` (see the module docstring):
    the cotangents of the stage derivatives `f_bar_i = h sum_j b_i(theta_j) g_j` from the
    outputs `j` in the step, then for `i = 7, ..., 1`: `Y_bar_i = f_Y(Y_i)^T f_bar_i` (plus
    `lambda_{k+1}` for `i = 7`, as `y_{k+1} = Y_7`), `f_bar_j += a_ij h Y_bar_i`,
    `y_bar += Y_bar_i`, and the parameters' cotangent `f_p(Y_i)^T f_bar_i`."""
    t_steps, y_steps, num_steps = residuals
    num_steps = jnp.asarray(num_steps).astype(int)
    dynamic, y0 = vjp_arg
    g = grads[0]
    g = jnp.zeros((ts.shape[0], y0.shape[0]), y0.dtype) if g is None else g
    t_start = jnp.concatenate([ts[:1], t_steps[:-1]])
    y_start = jnp.concatenate([y0[None], y_steps[:-1]])
    jumps_of = lambda d: eqx.combine(d, static)[1].jump_times()  # noqa: E731
    jumps = jumps_of(dynamic)
    has_jumps = jumps is not None and jnp.size(jumps) > 0
    t_end = _step_ends(t_steps, jumps)
    # The step whose dense output gave each output: diffrax saves ts[j] in the first step
    # whose end is >= ts[j].
    step_of = jnp.minimum(jnp.searchsorted(t_end, ts, side="left").astype(int), num_steps - 1)

    # The outputs of step k are step_of[lo[k]:hi[k]] (`ts` is increasing).
    steps = jnp.arange(t_steps.shape[0])
    lo, hi = (jnp.searchsorted(step_of, steps, side=side).astype(int) for side in ("left", "right"))

    n = y0.shape[0] // 2

    def body(carry):
        k, lam, p_bar, Qdd_next, switch = carry
        t0, y = t_start[k], y_start[k]
        h = t_end[k] - t0
        recorded = _stages(dynamic, static, t0, h, y)
        # A step that ends at an input jump J (the next one starts just after it): moving J
        # by dJ changes y_{k+1} by (f(J^-) - f(J^+)) dJ, both at y_{k+1}: the last stage of
        # this step (FSAL) and the first of the next. Their velocities are equal.
        Qdd = recorded[2]
        jump_term = lam[n:] @ (Qdd[6] - Qdd_next)
        switch = switch.at[k].set(jnp.where(k < num_steps - 1, jump_term, 0.0))

        def output(j, acc):
            y_bar, f_bar = acc
            weights = _dense_weights((ts[j] - t0) / h)
            return y_bar + g[j], f_bar + h * weights[:, None] * g[j][None, :]

        zeros = (jnp.zeros_like(y), jnp.zeros((7, y.shape[0]), y.dtype))
        y_bar, f_bar = jax.lax.fori_loop(lo[k], hi[k], output, zeros)

        def transpose(carry, inputs):
            y_bar, f_bar, p_bar = carry
            i, t, Y, Qdd, factor = inputs
            Y_bar, p_i = stage_vjp(dynamic, static, Y, t, Qdd, factor, f_bar[i])
            Y_bar = Y_bar + jnp.where(i == 6, 1.0, 0.0) * lam  # y_{k+1} = Y_7
            f_bar = f_bar + (h * jnp.asarray(_A_MATRIX)[i])[:, None] * Y_bar[None, :]
            return (y_bar + Y_bar, f_bar, jax.tree.map(jnp.add, p_bar, p_i)), None

        (y_bar, _, p_bar), _ = jax.lax.scan(transpose, (y_bar, f_bar, p_bar), (jnp.arange(7), *recorded), reverse=True)
        return k - 1, y_bar, p_bar, Qdd[0], switch

    zero = jax.tree.map(jnp.zeros_like, dynamic)
    init = (num_steps - 1, jnp.zeros_like(y0), zero, jnp.zeros(n, y0.dtype), jnp.zeros_like(t_steps))
    _, y0_bar, p_bar, _, switch = jax.lax.while_loop(lambda c: c[0] >= 0, body, init)
    if has_jumps:  # the switching times' cotangent, pulled back to the input's fields
        jumps_bar = _jump_cotangent(jumps, t_end, t_steps, switch)
        (from_jumps,) = jax.vjp(jumps_of, dynamic)[1](jumps_bar)
        p_bar = jax.tree.map(jnp.add, p_bar, from_jumps)
    perturbed_dynamic, perturbed_y0 = perturbed
    p_bar = jax.tree.map(lambda d, p: d if p else None, p_bar, perturbed_dynamic)
    return p_bar, (y0_bar if perturbed_y0 else None)


@eqx.filter_jit
def tsit5_trajectory(
    chain: Chain | AssembledChain,
    y0: Float[Array, " 2n"],
    ts,
    torque=None,
    *,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 100_000,
    dtmax: float | None = None,
) -> Trajectory:
    r"""Adaptive Tsit5 (`rtol`, `atol`): the state at every time of `ts` (s), as a
    `Trajectory`, exactly as `simulate(chain, y0, ts, torque, rtol=rtol, atol=atol,
    max_steps=max_steps)` computes it, with a reverse-mode derivative by the discrete
    adjoint of the steps taken (module docstring).

    **Arguments:** as `simulate`'s adaptive solve. `ts`: increasing output times, s (may
    be traced); `torque`: anything `simulate` accepts; `max_steps`: the step budget, and
    the length of the per-step record the derivative keeps (`max_steps x 2n` floats: 12.8
    MB for the default and 8 coordinates). Gradients flow to the chain's parameters, the
    input's array fields (its switching times included: module docstring) and `y0`; not
    to `ts`. `dtmax`: the largest step, s, as `simulate`'s: derivatives of a trajectory
    that starts at rest need it (`fd.stable_step(chain, y0)`; see `simulate`). Forward
    mode is not defined: use `simulate(..., adjoint=diffrax.ForwardMode())`.

    Raises (inside `jit` too) on reaching `max_steps`, on a solver failure and on a
    non-finite state, as `simulate` does.
    """
    if not (isinstance(max_steps, int) and max_steps > 0):
        raise ValueError(f"tsit5_trajectory: max_steps expected a positive int, got {max_steps!r}")
    if dtmax is not None and not (float(dtmax) > 0 and np.isfinite(float(dtmax))):
        raise ValueError(f"tsit5_trajectory: dtmax expected a step > 0 s, got {dtmax!r}")
    asm, y0, ts, torque = prepare(chain, y0, ts, torque, "tsit5_trajectory")
    n = asm.layout.n_dof
    dynamic, static = eqx.partition((asm, torque), eqx.is_inexact_array)
    ys, info = _tsit5_adjoint((dynamic, y0), static, ts, rtol, atol, max_steps, dtmax)
    info = jax.lax.stop_gradient(info)
    num_steps, max_reached, failed = info[0].astype(int), info[1] > 0.5, info[2] > 0.5
    ys = eqx.error_if(
        ys,
        max_reached,
        f"tsit5_trajectory: the solver reached max_steps={max_steps} before the last output time; "
        "raise max_steps or loosen rtol/atol",
    )
    ys = eqx.error_if(
        ys,
        failed & ~max_reached,
        "tsit5_trajectory: the ODE solver failed (step size collapsed or non-finite vector field); "
        "check the parameters (a NaN or negative mass/stiffness?) and the initial state",
    )
    ys = eqx.error_if(
        ys,
        ~jnp.all(jnp.isfinite(ys)),
        "tsit5_trajectory: the state became non-finite (NaN/inf); check the parameters and the initial state",
    )
    return Trajectory(ts, ys[:, :n], ys[:, n:], num_steps, asm.layout.names, not isinstance(torque, ZeroTorque))

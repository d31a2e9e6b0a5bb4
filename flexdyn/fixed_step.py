"""Lean fixed-step RK4 integrators: for large batched sweeps, and for cheap exact gradients.

`rk4_trajectory(chain, y0, ts, torque, dt=...)` returns the state at every `ts`, like
`simulate(..., dt=dt)`, and is differentiated in reverse mode by the discrete adjoint of
RK4 (its own `custom_vjp`, see its docstring), at a few times the cost of its forward
solve (measured: `docs/performance.md`).

`rk4_final(chain, y0, t0, t1, torque, dt=...)` integrates the chain's equations of motion
with the classical fourth-order Runge-Kutta method and returns the final state only. It
is `simulate(..., dt=dt)` without diffrax's general machinery (step-size controller,
dense output, event and error-state bookkeeping): one `lax.scan` over the steps, whose
body is the four stages and nothing else, so that under `vmap` on a GPU
each step is as few kernel launches as XLA can make it (`benchmarks/bench_gpu_sweep.py`
measures both). Use `simulate` for anything else: saved time series, adaptive steps,
reverse-mode gradients with checkpointing.

**Steps and input jumps.** The interval is cut at the input's `jump_times()` (which must
be concrete numbers, known when the function is traced). Each piece `[a, b]` takes
`n = ceil((b - a) / dt)` equal steps `h = (b - a) / n <= dt`, and every stage reads the
torque at `min(t, b^-)` (the last float before `b`), so no stage sees the far side of a
jump and the method stays fourth-order across a bang-bang switch, as `simulate` does by
clipping its steps onto the jumps.

The mass-matrix solve is `flexdyn.smallsolve.spd_solve` (`solve="unrolled"`, default),
its form without divisions or square roots `spd_solve_rsqrt` (`solve="rsqrt"`, what the GPU
kernel of `flexdyn.fused` uses), or `cho_factor`/`cho_solve` (`solve="cho"`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, Float

from .chain import (
    AssembledChain,
    Chain,
    accelerations,
    assemble,
    generalised_forces,
    lagrange_residual,
    mass_and_velocity_terms,
    solve_forward_dynamics,
)
from .inputs import AbstractInput, ZeroTorque
from .linear import check_rk4_step
from .simulation import Trajectory, as_initial_state, as_input, check_times, check_torque_shape
from .smallsolve import spd_solve, spd_solve_rsqrt

_SOLVES = {
    "unrolled": spd_solve,
    "rsqrt": spd_solve_rsqrt,
    "cho": lambda M, b: jsl.cho_solve(jsl.cho_factor(M), b),
}


def vector_field(asm: AssembledChain, torque: AbstractInput, solve: str = "unrolled"):
    """`f(t, y) = [Q_dot, Q_ddot]` of the assembled chain under `torque`, with the chosen
    mass-matrix solve (see the module docstring)."""
    if solve not in _SOLVES:
        raise ValueError(f"vector_field: solve expected one of {sorted(_SOLVES)}, got {solve!r}")
    linsolve = _SOLVES[solve]
    n = asm.layout.n_dof

    def f(t, y):
        Q, Qd = y[:n], y[n:]
        M, h = mass_and_velocity_terms(asm, Q, Qd)
        F = generalised_forces(asm, Q, Qd, torque(t, y))
        return jnp.concatenate([Qd, linsolve(M, F - h)])

    return f


def _jump_values(torque: AbstractInput, caller: str) -> list[float]:
    """The input's jump times as Python floats (none: `[]`)."""
    try:
        with jax.ensure_compile_time_eval():  # concrete inputs stay concrete inside jit
            jumps = torque.jump_times()
            if jumps is None:
                return []
            return [float(j) for j in np.ravel(np.asarray(jumps))]
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError) as e:
        raise ValueError(
            f"{caller}: the input's jump_times() must be concrete numbers (the steps are laid out "
            "when the function is traced); pass the input as a closed-over constant, not a traced "
            "argument, or use fd.simulate"
        ) from e


def input_breaks(torque: AbstractInput, t0: float, t1: float, caller: str = "rk4_final") -> list[float]:
    inner = sorted({j for j in _jump_values(torque, caller) if t0 < j < t1})
    return [t0, *inner, t1]


def input_pieces(breaks: list[float], dt: float, jumps=None) -> list[tuple[float, float, int, float]]:
    """`(a, h, n, last)` for each piece `[a, b]` between consecutive `breaks`: `n =
    ceil((b - a) / dt)` equal steps `h`, and the last admissible input time, `b^-` (the
    last float before `b`) where the input jumps at `b` (every break when `jumps` is None),
    else `b`."""
    out = []
    for a, b in zip(breaks[:-1], breaks[1:]):
        n = max(1, math.ceil((b - a) / dt - 1e-9))
        last = float(np.nextafter(b, a)) if jumps is None or b in jumps else b
        out.append((a, (b - a) / n, n, last))
    return out


def _step_table(breaks: list[float], dt: float):
    """Per-step start time, step and last admissible input time (numpy arrays): each piece
    `[a, b]` in `n = ceil((b - a) / dt)` equal steps, the input read at `min(t, b^-)`."""
    starts, steps, lasts = [], [], []
    for a, h, n, last in input_pieces(breaks, dt):
        starts.append(a + h * np.arange(n))
        steps.append(np.full(n, h))
        lasts.append(np.full(n, last))
    return tuple(jnp.asarray(np.concatenate(x)) for x in (starts, steps, lasts))


def rk4_final(
    chain: Chain | AssembledChain,
    y0: Float[Array, " 2n"],
    t0: float,
    t1: float,
    torque: AbstractInput,
    *,
    dt: float,
    solve: str = "unrolled",
    unroll: int = 1,
) -> Float[Array, " 2n"]:
    """The state `[Q, Q_dot]` at `t1` (s) from `y0` at `t0`, classical RK4 with steps of at
    most `dt` (s) laid out between the input's jumps (module docstring).

    **Arguments:** `t0`, `t1`, `dt`: Python floats (they fix the loop lengths); `torque`:
    an input (`flexdyn.inputs`) or anything `simulate` accepts; `solve`: `"unrolled"`,
    `"rsqrt"` or `"cho"`; `unroll`: RK4 steps per loop iteration (`lax.scan(unroll=...)`).

    Raises (inside `jit` and `vmap` too) if `dt` is above RK4's stability limit for the
    chain's linearisation about `y0` (`flexdyn.linear.check_rk4_step`, as `simulate` and
    `rk4_trajectory` check: above the limit a barely excited mode grows from round-off to
    a finite but wrong result), and if the state becomes non-finite.
    """
    t0, t1, dt = float(t0), float(t1), float(dt)
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"rk4_final: dt expected a step > 0 s, got {dt!r}")
    if not t1 > t0:
        raise ValueError(f"rk4_final: expected t1 > t0, got t0={t0!r}, t1={t1!r}")
    if int(unroll) < 1:
        raise ValueError(f"rk4_final: unroll expected an integer >= 1, got {unroll!r}")
    asm = assemble(chain)
    torque = as_input(torque, asm.chain.n_links)
    y0 = as_initial_state(asm, y0, "rk4_final")
    check_torque_shape(torque, t0, y0, asm.chain.n_links)
    y0 = check_rk4_step(asm, y0, torque(t0, y0), dt, "rk4_final")
    field = vector_field(asm, torque, solve)
    starts, steps, lasts = _step_table(input_breaks(torque, t0, t1), dt)

    def f(t, y, last):
        return field(jnp.minimum(t, last), y)

    def step(y, x):
        t, h, last = x
        k1 = f(t, y, last)
        k2 = f(t + 0.5 * h, y + (0.5 * h) * k1, last)
        k3 = f(t + 0.5 * h, y + (0.5 * h) * k2, last)
        k4 = f(t + h, y + h * k3, last)
        return y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4), None

    y, _ = jax.lax.scan(step, y0, (starts, steps, lasts), unroll=int(unroll))
    return eqx.error_if(
        y,
        ~jnp.all(jnp.isfinite(y)),
        "rk4_final: the state became non-finite (NaN/inf): dt is probably above the stability limit "
        "of the stiffest mode or joint (reduce dt), or a parameter is invalid (a NaN or negative mass/stiffness?)",
    )


def _output_table(ts: np.ndarray, jumps: list[float], dt: float):
    """Steps of `rk4_trajectory`: the interval `[ts[0], ts[-1]]` cut at every output time
    and input jump, each piece `[a, b]` in `ceil((b - a) / dt)` equal steps. Returns the
    per-step start time, step and last admissible input time (`b^-` if an input jumps at
    `b`, else `b`), and the index of each output time among the `N + 1` step boundaries."""
    jumps = {j for j in jumps if ts[0] < j <= ts[-1]}  # one at the end: read before it too
    breaks = sorted(set(ts.tolist()) | jumps)
    starts, steps, lasts, boundary = [], [], [], [0]
    for a, h, n, last in input_pieces(breaks, dt, jumps):
        starts.append(a + h * np.arange(n))
        steps.append(np.full(n, h))
        lasts.append(np.full(n, last))
        boundary.append(boundary[-1] + n)
    where = dict(zip(breaks, boundary))
    index = np.asarray([where[t] for t in ts.tolist()])
    return tuple(np.concatenate(x) for x in (starts, steps, lasts)), index


_RK4_A = (0.0, 0.5, 0.5, 1.0)  # stage i reads y + A[i] h k_{i-1} at t + A[i] h
_RK4_B = (1 / 6, 1 / 3, 1 / 3, 1 / 6)


def _rk4_step(dynamic, static, y, x, record=False):
    """One classical RK4 step of `y_dot = [Q_dot, Q_ddot(Q, Q_dot, tau(t, y))]`.

    Accelerations by `flexdyn.chain.accelerations` (its implicit-function derivative rule),
    the stages in a `lax.scan` (one right-hand side in the compiled loop, faster on the
    CPU than four inlined copies). With `record`, by the same solve, also returning each
    stage's `Q_ddot` and the upper Cholesky factor of its `M` (the residuals of the
    discrete adjoint), the stages inlined (faster there)."""
    asm, torque = eqx.combine(dynamic, static)
    t, h, last = x
    n = y.shape[0] // 2

    def stage(k, a):
        Y = y + (a * h) * k
        tau = torque(jnp.minimum(t + a * h, last), Y)
        if record:
            Qdd, (factor, lower) = solve_forward_dynamics(asm, Y[:n], Y[n:], tau)
            return jnp.concatenate([Y[n:], Qdd]), (Qdd, factor.T if lower else factor)
        return jnp.concatenate([Y[n:], accelerations(asm, Y[:n], Y[n:], tau)]), None

    zero = jnp.zeros_like(y)
    if not record:

        def scanned(carry, coefficients):
            k, total = carry
            k, _ = stage(k, coefficients[0])
            return (k, total + coefficients[1] * k), None

        (_, total), _ = jax.lax.scan(scanned, (zero, zero), (jnp.asarray(_RK4_A), jnp.asarray(_RK4_B)))
        return y + h * total
    k, total, Qdds, factors = zero, zero, [], []
    for a, b in zip(_RK4_A, _RK4_B):
        k, (Qdd, factor) = stage(k, a)
        total = total + b * k
        Qdds.append(Qdd)
        factors.append(factor)
    return y + h * total, (jnp.stack(Qdds), jnp.stack(factors))


def _rk4_states(dynamic, static, y0, table):
    """The states at all `N + 1` step boundaries, shape `(N + 1, 2n)`."""

    def body(y, x):
        y = _rk4_step(dynamic, static, y, x)
        return y, y

    _, ys = jax.lax.scan(body, y0, table)
    return jnp.concatenate([y0[None], ys])


@eqx.filter_custom_vjp
def _rk4_states_adjoint(vjp_arg, static, table):
    dynamic, y0 = vjp_arg
    return _rk4_states(dynamic, static, y0, table)


@_rk4_states_adjoint.def_fwd
def _rk4_states_adjoint_fwd(perturbed, vjp_arg, static, table):
    del perturbed
    dynamic, y0 = vjp_arg

    def body(y, x):
        y, (Qdds, factors) = _rk4_step(dynamic, static, y, x, record=True)
        return y, (y, Qdds, factors)

    _, (ys, Qdds, factors) = jax.lax.scan(body, y0, table)
    ys = jnp.concatenate([y0[None], ys])
    return ys, (ys, Qdds, factors)


def stage_vjp(dynamic, static, Y, t, Qdd, factor, v):
    """`(df/dY)^T v` and `(df/dp)^T v` for `f(t, Y) = [Q_dot, Q_ddot]` at a stage whose
    accelerations `Q_ddot` and mass-matrix factor were recorded: with `w = M^-1 v_a`,
    `v_a^T dQ_ddot = -d(w^T r)` for the Lagrange residual `r = M Q_ddot + h - F` at fixed
    `Q_ddot` (`flexdyn.chain.lagrange_residual`), so one reverse pass over the scalar
    `w^T r` gives the derivatives w.r.t. `Q`, `Q_dot`, the torque and the chain's arrays,
    and no mass matrix is formed again."""
    asm_dyn, torque_dyn = dynamic
    asm_static, torque_static = static
    n = Y.shape[0] // 2
    w = jsl.cho_solve((factor, False), v[n:])  # the upper Cholesky factor of M

    def contracted(asm_dyn_, Q, Qd, tau):
        return w @ lagrange_residual(eqx.combine(asm_dyn_, asm_static), Q, Qd, Qdd, tau)

    tau, torque_vjp = jax.vjp(lambda d, Y_: eqx.combine(d, torque_static)(t, Y_), torque_dyn, Y)
    asm_bar, Q_bar, Qd_bar, tau_bar = jax.grad(contracted, argnums=(0, 1, 2, 3))(asm_dyn, Y[:n], Y[n:], tau)
    torque_bar, Y_bar = torque_vjp(-tau_bar)
    Y_bar = Y_bar - jnp.concatenate([Q_bar, Qd_bar - v[:n]])
    return Y_bar, (jax.tree.map(jnp.negative, asm_bar), torque_bar)


def _step_vjp(dynamic, static, y, x, Qdds, factors, lam):
    """The transpose of one RK4 step's linearisation at `y`, from the recorded stages
    (`Y_i = y + a_i h k_{i-1}`): `k_bar_i = b_i h lam`, then for `i = 4, 3, 2, 1`:
    `Y_bar_i = f_Y(Y_i)^T k_bar_i` and, for `i > 1`, `k_bar_{i-1} += a_i h Y_bar_i`;
    `y_bar = lam + sum_i Y_bar_i`, and the parameters' cotangent `sum_i f_p(Y_i)^T k_bar_i`."""
    t, h, last = x
    n = y.shape[0] // 2
    Ys, k = [], None
    for i, a in enumerate(_RK4_A):  # the stage states, from the recorded accelerations
        Y = y if k is None else y + (a * h) * k
        Ys.append(Y)
        k = jnp.concatenate([Y[n:], Qdds[i]])
    k_bar = [(b * h) * lam for b in _RK4_B]
    y_bar, p_bar = lam, None
    for i in reversed(range(4)):
        t_i = jnp.minimum(t + _RK4_A[i] * h, last)
        Y_bar, p_i = stage_vjp(dynamic, static, Ys[i], t_i, Qdds[i], factors[i], k_bar[i])
        y_bar = y_bar + Y_bar
        p_bar = p_i if p_bar is None else jax.tree.map(jnp.add, p_bar, p_i)
        if i > 0:
            k_bar[i - 1] = k_bar[i - 1] + (_RK4_A[i] * h) * Y_bar
    return y_bar, p_bar


@_rk4_states_adjoint.def_bwd
def _rk4_states_adjoint_bwd(residuals, ys_bar, perturbed, vjp_arg, static, table):
    r"""The discrete adjoint of RK4: with `y_{k+1} = Phi_k(y_k, p)` and the cotangents `g_k`
    of the outputs, `lambda_N = g_N`, `lambda_k = g_k + (dPhi_k/dy)^T lambda_{k+1}` and
    `p_bar = sum_k (dPhi_k/dp)^T lambda_{k+1}`, backwards over the steps (`_step_vjp`)."""
    ys, Qdds, factors = residuals
    dynamic, y0 = vjp_arg
    ys_bar = jnp.zeros_like(ys) if ys_bar is None else ys_bar
    zero = jax.tree.map(jnp.zeros_like, dynamic)

    def body(carry, inputs):
        lam, p_bar = carry
        y, x, Qdd, factor, g = inputs
        y_bar, p_k = _step_vjp(dynamic, static, y, x, Qdd, factor, lam)
        return (y_bar + g, jax.tree.map(jnp.add, p_bar, p_k)), None

    inputs = (ys[:-1], table, Qdds, factors, ys_bar[:-1])
    (y0_bar, p_bar), _ = jax.lax.scan(body, (ys_bar[-1], zero), inputs, reverse=True)
    perturbed_dynamic, perturbed_y0 = perturbed
    p_bar = jax.tree.map(lambda g, p: g if p else None, p_bar, perturbed_dynamic)
    return p_bar, (y0_bar if perturbed_y0 else None)


def rk4_trajectory(
    chain: Chain | AssembledChain,
    y0: Float[Array, " 2n"],
    ts,
    torque: AbstractInput | None = None,
    *,
    dt: float,
    adjoint: str = "discrete",
) -> Trajectory:
    r"""Classical RK4 with steps of at most `dt` (s): the state at every time of `ts` (s),
    as a `Trajectory` (like `simulate(chain, y0, ts, torque, dt=dt)`), with a reverse-mode
    derivative that costs under four forward solves.

    **Steps.** `[ts[0], ts[-1]]` is cut at every output time and every input jump
    (`torque.jump_times()`); each piece `[a, b]` takes `ceil((b - a) / dt)` equal steps of at
    most `dt`, and a stage never reads the input from the far side of a jump (as
    `rk4_final`). With `ts` on a grid of `dt` and jumps on it (a 1 kHz log at `dt = 1e-3`)
    the steps are `simulate(..., dt=dt)`'s, and so are the states, to round-off.

    **Derivatives** (`adjoint`):
    - `"discrete"` (default): reverse mode (`jax.grad`, `jax.vjp`) by the discrete adjoint
      of RK4, the exact gradient of the computed states, not of the ODE's solution:
      `lambda_k = g_k + (dPhi_k / dy)^T lambda_{k+1}`, `p_bar = sum_k (dPhi_k / dp)^T
      lambda_{k+1}` for the step map `y_{k+1} = Phi_k(y_k, p)` and output cotangents `g_k`
      (Hager 2000, "Runge-Kutta methods in optimal control and the transformed adjoint
      system"; Sandu 2006, "On the properties of Runge-Kutta discrete adjoints"). The
      forward pass records, at every step, the state and each stage's accelerations and
      Cholesky factor of `M`; the backward pass transposes each stage from them without
      forming `M` again: with `w = M^-1 v`, `v^T dQ_ddot = -d(w^T r)` for the Lagrange
      residual `r = M Q_ddot + h - F` at fixed `Q_ddot`, one reverse pass over a scalar.
      Memory: `N (4 n (n + 1) + 2n) + 2n` floats for `N` steps and `n` coordinates: 24 MB
      for 10,000 steps of 8 (XLA reports 27 MiB for the whole gradient program).
      Cost: `value_and_grad` ~4x this function's forward solve (paper 004's arm, 10
      parameters; `benchmarks/bench_gradient_cost.py`, `docs/performance.md`). Gradients flow to the
      chain's parameters, the input's array fields and `y0`. The input's switching times
      (`BangBang.width`, `.start`) lay out the steps when the function is traced, so they
      must be concrete: differentiating them raises (use `tsit5_trajectory`, which gives
      their derivative). Forward mode (`jax.jvp`,
      `jax.jacfwd`) is not defined for it: use `adjoint="autodiff"`, or `simulate` with
      `diffrax.ForwardMode()`.
    - `"autodiff"`: no rule; JAX differentiates the `lax.scan` itself. Forward mode works;
      reverse mode stores every stage's linearisation (more memory, and slower than
      diffrax's checkpointed gradient).

    **Arguments:** `ts`: increasing output times, s, as concrete numbers (the steps are laid
    out when the function is traced: close over them rather than pass them to `jax.jit`
    as traced arguments); `torque`: anything `simulate` accepts, with concrete jump times;
    `dt`: the largest step, s. `Trajectory.num_steps` is the number of RK4 steps.

    Raises (inside `jit` too) if the state becomes non-finite: with a fixed step, `dt` is
    above the stability limit of the stiffest mode or joint.
    """
    dt = float(dt)
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"rk4_trajectory: dt expected a step > 0 s, got {dt!r}")
    if adjoint not in ("discrete", "autodiff"):
        raise ValueError(f"rk4_trajectory: adjoint expected 'discrete' or 'autodiff', got {adjoint!r}")
    try:
        with jax.ensure_compile_time_eval():
            ts_np = np.asarray(ts, dtype=float)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError) as e:
        raise ValueError(
            "rk4_trajectory: ts must be concrete numbers (the steps are laid out when the function is "
            "traced); close over them instead of passing them as traced arguments, or use fd.simulate"
        ) from e
    check_times(ts_np, "rk4_trajectory")
    asm = assemble(chain)
    torque = as_input(torque, asm.chain.n_links)
    n = asm.layout.n_dof
    y0 = as_initial_state(asm, y0, "rk4_trajectory")
    check_torque_shape(torque, ts_np[0], y0, asm.chain.n_links)
    y0 = check_rk4_step(asm, y0, torque(ts_np[0], y0), dt, "rk4_trajectory")
    jumps = [j for j in _jump_values(torque, "rk4_trajectory") if ts_np[0] < j <= ts_np[-1]]
    table, index = _output_table(ts_np, jumps, dt)
    table = tuple(jnp.asarray(x) for x in table)
    dynamic, static = eqx.partition((asm, torque), eqx.is_inexact_array)
    if adjoint == "discrete":
        ys = _rk4_states_adjoint((dynamic, y0), static, table)
    else:
        ys = _rk4_states(dynamic, static, y0, table)
    ys = ys[index]
    ys = eqx.error_if(
        ys,
        ~jnp.all(jnp.isfinite(ys)),
        "rk4_trajectory: the state became non-finite (NaN/inf): dt is probably above the stability limit "
        "of the stiffest mode or joint (reduce dt), or a parameter is invalid (a NaN or negative mass/stiffness?)",
    )
    steps, driven = jnp.asarray(table[0].shape[0]), not isinstance(torque, ZeroTorque)
    return Trajectory(jnp.asarray(ts_np), ys[:, :n], ys[:, n:], steps, asm.layout.names, driven)

"""A lean fixed-step RK4 integrator for large batched sweeps (payloads, designs).

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

The mass-matrix solve is `flexdyn.smallsolve.spd_solve` (`solve="unrolled"`, default) or
`cho_factor`/`cho_solve` (`solve="cho"`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, Float

from .chain import AssembledChain, Chain, assemble, generalised_forces, mass_and_velocity_terms
from .inputs import AbstractInput
from .simulate import _check_torque_shape, as_input
from .smallsolve import spd_solve

_SOLVES = {
    "unrolled": spd_solve,
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


def _breaks(torque: AbstractInput, t0: float, t1: float) -> list[float]:
    try:
        with jax.ensure_compile_time_eval():  # concrete inputs stay concrete inside jit
            jumps = torque.jump_times()
            if jumps is None:
                return [t0, t1]
            values = [float(j) for j in np.ravel(np.asarray(jumps))]
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError) as e:
        raise ValueError(
            "rk4_final: the input's jump_times() must be concrete numbers (the steps are laid out "
            "when the function is traced); pass the input as a closed-over constant, not a traced "
            "argument, or use fd.simulate"
        ) from e
    inner = sorted({j for j in values if t0 < j < t1})
    return [t0, *inner, t1]


def _step_table(breaks: list[float], dt: float):
    """Per-step start time, step and last admissible input time (numpy arrays): each piece
    `[a, b]` in `n = ceil((b - a) / dt)` equal steps, the input read at `min(t, b^-)`."""
    starts, steps, lasts = [], [], []
    for a, b in zip(breaks[:-1], breaks[1:]):
        n = max(1, math.ceil((b - a) / dt - 1e-9))
        h = (b - a) / n
        starts.append(a + h * np.arange(n))
        steps.append(np.full(n, h))
        lasts.append(np.full(n, np.nextafter(b, a)))
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
    an input (`flexdyn.inputs`) or anything `simulate` accepts; `solve`: `"unrolled"` or
    `"cho"`; `unroll`: RK4 steps per loop iteration (`lax.scan(unroll=...)`).

    Raises (inside `jit` too) if the state becomes non-finite: with a fixed step that means
    `dt` is above the stability limit of the stiffest mode or joint.
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
    y0 = jnp.asarray(y0, dtype=float)
    if y0.shape != (2 * asm.layout.n_dof,):
        raise ValueError(
            f"rk4_final: y0 expected shape ({2 * asm.layout.n_dof},) = [Q, Q_dot] of this chain, got {y0.shape}"
        )
    _check_torque_shape(torque, t0, y0, asm.chain.n_links)
    field = vector_field(asm, torque, solve)
    starts, steps, lasts = _step_table(_breaks(torque, t0, t1), dt)

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

"""Constant steps that stop at an input's jumps: fixed-step solves of held commands.

A fixed-step solve (`diffrax.ConstantStepSize`) steps over the jumps of a held
(zero-order-hold) command: a step that straddles one reads the command on both sides of
it inside its stages, an error of order `h |du|` in that step that no step size removes
at the rate of the method. A fit then absorbs it into whatever shifts the input in time
(a fitted actuator lag or sensor delay of a fraction of a step).

`clipped_constant_steps(jumps)` keeps the constant step `dt0` of `diffeqsolve` but ends a
step on the floating-point number just before the next jump and starts the next just
after it (diffrax's `ClipStepSizeController`, which wraps only adaptive controllers: so
the constant step is written here as an adaptive controller that accepts every step).
After a jump the steps restart at `dt0` from the jump, so a solve takes at most one extra
step per jump. `jumps` may be traced (fixed length, `inf` for none:
`flexdyn.inputs.held_changes`).
"""

from __future__ import annotations

import diffrax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float


class _EveryStepAccepted(diffrax.AbstractAdaptiveStepSizeController):
    """Steps of `dt0` s, each accepted (no error estimate is read: a fixed-step
    solver such as `flexdyn.RK4` has none)."""

    rtol: float = float("inf")
    atol: float = float("inf")
    norm: object = optx.rms_norm

    def wrap(self, direction):
        return self

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        del terms, t1, y0, args, func, error_order
        if dt0 is None:
            raise ValueError("clipped_constant_steps: a constant step needs dt0 (s) in diffeqsolve")
        return t0 + dt0, jnp.asarray(dt0)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        del t0, y0, y1_candidate, args, y_error, error_order
        return True, t1, t1 + controller_state, False, controller_state, diffrax.RESULTS.successful


def clipped_constant_steps(jumps: Float[Array, " J"] | None):
    """A step-size controller for `diffrax.diffeqsolve(..., dt0=h)`: steps of `h` s that
    stop on each of `jumps` (s; `inf` entries ignored), or plain constant steps when
    `jumps` is None. See the module docstring."""
    if jumps is None:
        return diffrax.ConstantStepSize()
    return diffrax.ClipStepSizeController(_EveryStepAccepted(), jump_ts=jumps)

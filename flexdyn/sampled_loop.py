"""A chain under a digital controller: feedback computed at sample ticks and held between.

A lab rig's controller reads its sensors every `period` s, computes a command, and its
output stage (a DAC, a PWM amplifier) holds the command until the next tick (zero-order
hold), clipped to the actuator's limit. Between ticks the chain is an ODE under a
constant torque; at each tick the command changes discontinuously. So the loop is
simulated tick by tick, exactly as the hardware runs it:

    u_k = clip(law(t_k, y(t_k)), -limit, limit)           (or from y(t_{k-1}): `delay`)
    y(t_{k+1}) = flow of the chain under the constant u_k from y(t_k) over [t_k, t_{k+1}]

the flow by adaptive Tsit5 (diffrax) inside a `lax.scan` over the ticks: one compiled
program for any number of ticks, differentiable in the chain's and the law's parameters.
Simulating the loop, rather than replaying its logged command open loop, keeps model errors
from integrating into drift: the feedback corrects the model as it corrected the rig.

`LinearFeedback` is the usual law: state feedback `u = K (y_ref(t) - y) + u_ff`, which
covers PD on a joint angle and feedback of modal coordinates (a strain gauge's tip
deflection is linear in them).
"""

from __future__ import annotations

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._checks import as_float_array
from .inputs import AbstractInput
from .simulation import ChainVectorField, Trajectory, floats_as_arrays, prepare


class HeldCommand(AbstractInput):
    """A constant torque (N m per joint) over one controller period. It declares no jump
    inside the period (`step_times` is a lone `inf`), so the solver does not probe it."""

    value: Float[Array, " n_joints"]

    def __call__(self, t, y=None):
        return self.value

    def step_times(self):
        return jnp.full(1, jnp.inf, self.value.dtype)


class LinearFeedback(eqx.Module):
    """`u = K (y_ref(t) - y) + u_ff`: state feedback on the chain's state `y = [Q, Q_dot]`.

    - `gain`: `K`, shape (n_joints, 2 n) (N m per rad, per m of a modal coordinate, per
      rad/s, ...), in the order of `chain.coordinate_names()` then their rates.
    - `target`: `y_ref(t)`, a callable `t -> (2 n,)` (e.g. a step of the joint angle), or
      None for the origin.
    - `feedforward`: `u_ff` (N m per joint), default 0.
    """

    gain: Float[Array, "n_joints n2"]
    target: Callable | None = None
    feedforward: Float[Array, " n_joints"] | None = None

    def __init__(self, gain, target=None, feedforward=None):
        self.gain = jnp.atleast_2d(as_float_array(gain))
        self.target = target
        self.feedforward = None if feedforward is None else jnp.atleast_1d(as_float_array(feedforward))

    def __call__(self, t, y):
        error = -y if self.target is None else self.target(t) - y
        u = self.gain @ error
        return u if self.feedforward is None else u + self.feedforward


class DigitalController(eqx.Module):
    """A feedback `law(t, y) -> (n_joints,)` (N m) sampled every `period` s and held.

    - `limit`: the actuator's saturation, N m per joint (or one for all), or None.
    - `delay`: `True` when the command computed from the state at tick `k` is applied
      from tick `k + 1` (a controller that computes during the period: one sample of
      computation delay), `False` when it is applied at once.
    """

    law: Callable
    limit: Float[Array, " n_joints"] | None = None
    delay: bool = eqx.field(static=True, default=False)

    def __init__(self, law, limit=None, delay: bool = False):
        self.law = law
        self.limit = None if limit is None else jnp.atleast_1d(as_float_array(limit))
        if self.limit is not None and not isinstance(self.limit, jax.core.Tracer):
            if not bool(jnp.all(self.limit > 0)):
                raise ValueError(f"DigitalController.limit: expected a saturation > 0 N m, got {limit!r}")
        self.delay = bool(delay)

    def command(self, t, y):
        u = jnp.atleast_1d(self.law(t, y))
        return u if self.limit is None else jnp.clip(u, -self.limit, self.limit)


class ClosedLoopRun(eqx.Module):
    """`trajectory` at the ticks and `commands` (N m, shape (T, n_joints)): the command
    applied from each tick (the last: what the controller commands at the final tick),
    what a log's command column records."""

    trajectory: Trajectory
    commands: Float[Array, "T n_joints"]


def simulate_closed_loop(chain, y0, ticks, controller: DigitalController, **options) -> ClosedLoopRun:
    return _simulate_closed_loop(floats_as_arrays(chain), y0, ticks, floats_as_arrays(controller), **options)


@eqx.filter_jit
def _simulate_closed_loop(
    chain,
    y0,
    ticks,
    controller: DigitalController,
    *,
    initial_command=None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps_per_tick: int = 4096,
) -> ClosedLoopRun:
    """Simulate `chain` from `y0` at `ticks[0]` under `controller`, ticking at `ticks` (s,
    increasing; a log's sample times at the controller's rate).

    - `initial_command`: with `controller.delay`, the command held over the first period
      (N m per joint, default 0).
    - `rtol`, `atol`: the adaptive tolerances within each period; `max_steps_per_tick`:
      its step budget (exceeding it is an error).
    """
    asm, y0, ticks, _ = prepare(chain, y0, ticks, None, "simulate_closed_loop")
    n = asm.layout.n_dof
    first = controller.command(ticks[0], y0)
    if controller.delay:
        first = jnp.zeros_like(first) if initial_command is None else jnp.broadcast_to(initial_command, first.shape)

    def period(carry, k):
        y, u = carry
        t0, t1 = ticks[k], ticks[k + 1]
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(ChainVectorField(asm, HeldCommand(u))),
            diffrax.Tsit5(),
            t0=t0,
            t1=t1,
            dt0=None,
            y0=y,
            saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
            max_steps=max_steps_per_tick,
            throw=False,
        )
        y1 = sol.ys[-1]
        failed = (sol.result != diffrax.RESULTS.successful) | ~jnp.all(jnp.isfinite(y1))
        # the command held over the next period: from the state at its start, or (one
        # sample of computation delay) from the state at this period's start
        u_next = controller.command(t0, y) if controller.delay else controller.command(t1, y1)
        return (y1, u_next), (y1, u_next, failed, sol.stats["num_accepted_steps"])

    _, (ys, us, failed, steps) = jax.lax.scan(period, (y0, first), jnp.arange(ticks.shape[0] - 1))
    ys = eqx.error_if(
        ys,
        jnp.any(failed),
        f"simulate_closed_loop: a controller period's solve failed (more than max_steps_per_tick="
        f"{max_steps_per_tick} steps, or a non-finite state): check the parameters and the gains",
    )
    ys = jnp.concatenate([y0[None], ys], axis=0)
    commands = jnp.concatenate([first[None], us], axis=0)
    traj = Trajectory(ticks, ys[:, :n], ys[:, n:], jnp.sum(steps), asm.layout.names, True)
    return ClosedLoopRun(traj, commands)


simulate_closed_loop.__doc__ = _simulate_closed_loop.__doc__

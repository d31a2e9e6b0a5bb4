"""A sampled torque command applied through a first-order actuator lag, exact between samples.

An actuator (a motor's current loop, an amplifier, a valve) applies the commanded torque
`u` through the lag

    T u_a' = u - u_a,        u_a(t_0) = u(t_0),        T >= 0 (s),

one time constant per joint. Between two samples `t_k <= t < t_{k+1}` (`s = t - t_k`) the
command is `u(t) = u_k + m_k s`, with `m_k = 0` for a held command (`hold="zoh"`, a digital
controller's) and `m_k = (u_{k+1} - u_k) / h_k` for a linear one, and the lag's solution is
the closed form

    u_a(t) = u(t) - T m_k + (a_k - u_k + T m_k) e^{-s/T},

`a_k = u_a(t_k)` carried from sample to sample by the same formula at `s = h_k` (the
knots, a `lax.scan`). `T = 0` is the identity: `u_a = u`. After the last sample the
command is held and the lag goes on relaxing; before the first, `u_a = u_0`.

Why not lag the samples and read them with the command's hold: a held command's lagged
torque is not held (it relaxes within each sample), so reading lagged knots as held is off
by up to a sample; reading them linearly is off by the exponential's curvature. This
input is exact, so a fitted actuator lag of a controller's held commands is not biased by
the reading.

Derivative in `T` at `T = 0`: for a linear command it is exact (`-m_k`, the first-order
lag `u_a ~ u - T u'`). For a held command it is zero almost everywhere (the lag's effect
at small `T` sits in boundary layers of width `T` after each change, a delay of each step
by `T`), so a fit of `T` must start from `T > 0` on held commands.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._checks import as_float_array
from .inputs import AbstractInput, SampledTorque


class LaggedTorque(AbstractInput):
    """`command` (a `SampledTorque`, linear or held per joint) applied through first-order
    lags of time constants `time_constant` (s, one per joint, or one for all; 0: no lag).
    See the module docstring for the closed form."""

    command: SampledTorque
    time_constant: Float[Array, " n_joints"]
    knots: Float[Array, "T n_joints"]  # u_a at each sample time (N m)
    slopes: Float[Array, "T n_joints"]  # the command's slope after each sample (N m/s)

    def __init__(self, command: SampledTorque, time_constant):
        n = command.values.shape[1]
        tc = as_float_array(time_constant)
        if tc.ndim > 1 or (tc.ndim == 1 and tc.shape[0] != n):
            raise ValueError(f"LaggedTorque.time_constant: expected one time constant (s) or {n}, got shape {tc.shape}")
        if not isinstance(tc, jax.core.Tracer) and not bool(jnp.all(tc >= 0)):
            raise ValueError(f"LaggedTorque.time_constant: expected time constants >= 0 s, got {tc}")
        self.command = command
        self.time_constant = jnp.broadcast_to(tc, (n,))
        # (computed once here, not in every right-hand side's evaluation)
        self.slopes = _slopes(command)
        self.knots = _knots(command, self.slopes, self.time_constant)

    def __call__(self, t, y=None):
        times, values = self.command.times, self.command.values
        k = jnp.clip(jnp.searchsorted(times, t, side="right") - 1, 0, times.shape[0] - 1)
        s = jnp.maximum(t - times[k], 0.0)
        m = self.slopes[k]
        u = values[k] + m * s
        T = self.time_constant
        return u - T * m + (self.knots[k] - values[k] + T * m) * _decay(s, T)

    def jump_times(self):
        return self.command.jump_times()

    def step_times(self):
        return self.command.step_times()


def _decay(s, T):
    """`e^{-s/T}`, and 0 where `T = 0` (the lag is the identity, right limits at jumps)."""
    positive = T > 0
    return jnp.where(positive, jnp.exp(-s / jnp.where(positive, T, 1.0)), 0.0)


def _slopes(command: SampledTorque):
    """Per-sample slopes `m_k` (N m/s, shape (T, n)) of the command: zero on held joints
    and after the last sample."""
    times, values = command.times, command.values
    m = jnp.diff(values, axis=0) / jnp.diff(times)[:, None]
    m = jnp.concatenate([m, jnp.zeros_like(values[:1])], axis=0)
    linear = jnp.array([h == "linear" for h in command._per_joint()])
    return jnp.where(linear, m, 0.0)


def _knots(command: SampledTorque, m, T):
    """`a_k = u_a(t_k)` for every sample, from `a_0 = u_0` (the closed form at `s = h_k`;
    `m`: `_slopes`)."""
    times, values = command.times, command.values
    h = jnp.diff(times)

    def step(a, k):
        u_end = values[k] + m[k] * h[k]
        a_next = u_end - T * m[k] + (a - values[k] + T * m[k]) * _decay(h[k], T)
        return a_next, a_next

    _, rest = jax.lax.scan(step, values[0], jnp.arange(times.shape[0] - 1))
    return jnp.concatenate([values[:1], rest], axis=0)


class RelaxingHold(AbstractInput):
    """One controller period of a held command `target` (per joint) applied through the
    same first-order lags: from `start` (the applied torque at the period's start `t0`,
    s) it relaxes as `u_a(t) = target + (start - target) e^{-(t - t0)/T}` (`T = 0`: the
    command itself). `LaggedTorque`'s closed form for one held stretch, for a loop that
    computes each command from the state (`identify`'s closed-loop logs). It declares no
    jump inside the period (`step_times` is a lone `inf`)."""

    target: Float[Array, " n_joints"]
    start: Float[Array, " n_joints"]
    t0: Float[Array, ""]
    time_constant: Float[Array, " n_joints"]

    def __call__(self, t, y=None):
        return self.target + (self.start - self.target) * _decay(jnp.maximum(t - self.t0, 0.0), self.time_constant)

    def step_times(self):
        return jnp.full(1, jnp.inf, self.target.dtype)

"""Joint-torque inputs: open-loop signals and simple state feedback.

An input is an `eqx.Module` called as `input(t, y) -> torque` with `t` in s, `y`
the state `[Q, Q_dot]` and `torque` in N m, one entry per joint (the torque
acts on the rotor coordinate of an elastic joint, on the link angle of a rigid
one). Open-loop inputs ignore `y`. Inputs with discontinuities list them in
`jump_times()` so adaptive solvers step onto them exactly.
"""

from __future__ import annotations

import abc
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._checks import as_float_array, warn_if_degrees


class AbstractInput(eqx.Module):
    """Base class of joint-torque inputs."""

    @abc.abstractmethod
    def __call__(self, t, y) -> Float[Array, " n_joints"]:
        raise NotImplementedError

    def jump_times(self):
        """Times (s) where the input is discontinuous, or None."""
        return None

    def step_times(self):
        """Times (s) an adaptive step must land on (not a discontinuity), or None."""
        return None


class ZeroTorque(AbstractInput):
    """No applied torque (free motion)."""

    n_joints: int = eqx.field(static=True)

    def __call__(self, t, y):
        return jnp.zeros(self.n_joints, dtype=jnp.result_type(float))


class BangBang(AbstractInput):
    """Bang-bang torque of papers 002 and 004: `+amplitude` on `[start, start + width)`,
    `-amplitude` on `[start + width, start + 2 width)`, zero otherwise.

    **Arguments:** `amplitude` (N m, per joint), `width` (s, duration of each
    pulse: 0.5 s in paper 004; paper 002's "1 s width" is the whole +/- pair, i.e. 0.5 s per
    pulse, as `notebooks/paper002_two_link.ipynb` explains), `start` (s).
    """

    amplitude: Float[Array, " n_joints"]
    width: Float[Array, ""]
    start: Float[Array, ""]

    def __init__(self, amplitude, width, start=0.0):
        self.amplitude = jnp.atleast_1d(as_float_array(amplitude))
        self.width = as_float_array(width)
        self.start = as_float_array(start)
        if np.ndim(self.width) != 0 or (not isinstance(self.width, jax.core.Tracer) and float(self.width) <= 0):
            raise ValueError(f"BangBang.width: expected a duration > 0 s, got {width!r}")

    def __call__(self, t, y=None):
        s = t - self.start
        first = (s >= 0) & (s < self.width)
        second = (s >= self.width) & (s < 2 * self.width)
        sign = jnp.where(first, 1.0, jnp.where(second, -1.0, 0.0))
        return sign * self.amplitude

    def jump_times(self):
        return jnp.stack([self.start, self.start + self.width, self.start + 2 * self.width])


class SampledTorque(AbstractInput):
    """Torque interpolated from samples, e.g. the torque column of a measured log.

    **Arguments:**
    - `times`: sample times, s, strictly increasing, shape (T,). Non-uniform
      spacing is fine.
    - `values`: torques, N m, shape (T,) or (T, n_joints).
    - `hold`: `"linear"` (piecewise linear) or `"zoh"` (zero-order hold: each
      sample held until the next, as a digital controller applies it); or one of
      them per joint, a tuple of length `n_joints`.

    Outside `[times[0], times[-1]]` the end values are held.

    Read with the wrong hold, a sampled torque is displaced in time: a controller's
    command (held) read as linear leads the true input by half a sample (0.5 ms at
    1 kHz), which a fitted actuator lag or sensor delay then absorbs; a continuous
    signal's samples (a measured current) read as held lag it by half a sample.
    """

    times: Float[Array, " T"]
    values: Float[Array, "T n_joints"]
    hold: str | tuple[str, ...] = eqx.field(static=True)

    def __init__(self, times, values, hold: str | tuple[str, ...] = "linear"):
        times = as_float_array(times)
        values = as_float_array(values)
        if values.ndim == 1:
            values = values[:, None]
        if times.ndim != 1 or times.shape[0] < 2 or values.ndim != 2 or values.shape[0] != times.shape[0]:
            raise ValueError(
                f"SampledTorque: expected times (T,) with T >= 2 and values (T,) or (T, n_joints), "
                f"got {times.shape} and {values.shape}"
            )
        hold = check_hold(hold, values.shape[1])
        if not isinstance(times, jax.core.Tracer):
            t = np.asarray(times)
            if np.any(np.diff(t) <= 0) or not np.all(np.isfinite(t)):
                k = int(np.argmax(~(np.diff(t) > 0)))
                raise ValueError(
                    f"SampledTorque.times: expected finite, strictly increasing times; "
                    f"sample {k + 1} (t = {t[k + 1]!r} s) does not follow t = {t[k]!r} s"
                )
        if not isinstance(values, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(values))):
            raise ValueError("SampledTorque.values: expected finite torques, found NaN or inf")
        self.times, self.values, self.hold = times, values, hold

    def _per_joint(self) -> tuple[str, ...]:
        return self.hold if isinstance(self.hold, tuple) else (self.hold,) * self.values.shape[1]

    def __call__(self, t, y=None):
        if self.hold == "linear":
            return jnp.stack([jnp.interp(t, self.times, v) for v in self.values.T])
        k = jnp.clip(jnp.searchsorted(self.times, t, side="right") - 1, 0, self.times.shape[0] - 1)
        if self.hold == "zoh":
            return self.values[k]
        return jnp.stack(
            [jnp.interp(t, self.times, v) if h == "linear" else v[k] for h, v in zip(self._per_joint(), self.values.T)]
        )

    def jump_times(self):
        """With a held (`"zoh"`) joint: the sample times where a held torque changes
        (`held_changes`), `inf` elsewhere. An adaptive solver lands a step on each and
        restarts there, and only there: a bang-bang command held over thousands of
        samples costs two restarts, not one per sample."""
        held = tuple(j for j, h in enumerate(self._per_joint()) if h == "zoh")
        if not held:
            return None
        return held_changes(self.times, self.values[:, held])

    def step_times(self):
        """With `hold="linear"`: the first and last sample of every run of equal samples (a
        stretch where the torque is constant), except the log's own ends; `inf` in the
        other entries (no step lands there), so the array's length is the number of
        samples and it may be traced. A chain at rest under a constant torque gives an
        adaptive solver an error estimate of exactly zero, so its steps grow tenfold each
        and step over an input that starts later (the solve can return no motion at
        all). Landing on the ends of the constant stretch puts the change inside the
        next step, whose error estimate sees it. A torque that changes at every sample
        has no stretch: every entry is `inf` and no step is clipped."""
        if "linear" not in self._per_joint():
            return None
        return constant_stretch_ends(self.times, self.values)


HOLDS = ("linear", "zoh")


def check_hold(hold, n_joints: int) -> str | tuple[str, ...]:
    """`SampledTorque.hold` checked: one of `HOLDS`, or a tuple of them, one per joint (a
    tuple of one kind collapses to it)."""
    if isinstance(hold, str) and hold in HOLDS:
        return hold
    if isinstance(hold, (tuple, list)) and len(hold) == n_joints and all(h in HOLDS for h in hold):
        return hold[0] if len(set(hold)) == 1 else tuple(hold)
    raise ValueError(
        f"SampledTorque.hold: expected 'linear' or 'zoh', or one of them per joint ({n_joints}), got {hold!r}"
    )


def held_changes(times, values):
    """`times` (shape (T,)) where held `values` (shape (T, n)) differ from the sample
    before, `inf` elsewhere and at the first sample (a fixed-length array, so it may be
    traced). Between two such times a zero-order-hold input is constant, so these are
    its only discontinuities."""
    changed = jnp.any(values[1:] != values[:-1], axis=1)
    return jnp.concatenate([jnp.full(1, jnp.inf, times.dtype), jnp.where(changed, times[1:], jnp.inf)])


def constant_stretch_ends(times, values):
    """`times` (shape (T,)) where a run of equal `values` (shape (T, n)) starts or ends,
    except the first and last time; `inf` elsewhere (a fixed-length array, so it may be
    traced). See `SampledTorque.step_times`."""
    v, t = values, times
    same = jnp.all(v[1:] == v[:-1], axis=1)  # the torque is constant on [t_k, t_k+1]
    no = jnp.zeros(1, bool)
    first = jnp.concatenate([same & ~jnp.concatenate([no, same[:-1]]), no])  # a run's first sample
    last = jnp.concatenate([no, same & ~jnp.concatenate([same[1:], no])])  # its last sample
    mark = (first | last).at[0].set(False).at[-1].set(False)
    return jnp.where(mark, t, jnp.inf)


#: Probe points of `probed_step_times` over the span of a solve.
PROBE_POINTS = 1024


def probed_step_times(torque, t0, t1, y0, n: int = PROBE_POINTS):
    """Step times for an input that declares none (`jump_times()` and `step_times()`
    both None: a plain callable, a feedback law): the ends of its constant stretches
    (`constant_stretch_ends`) on `n` equally spaced probe times of `[t0, t1]`, the state
    held at `y0`. Without them a chain at rest under a torque that is zero until later
    gives the adaptive solver an error estimate of exactly zero, its steps grow tenfold
    each, and it steps over the input (a 0.1 s pulse at 1 s written as
    `lambda t: jnp.where((t >= 1) & (t < 1.1), 0.05, 0)` would leave the link at rest).
    A change shorter than the probe spacing `(t1 - t0) / (n - 1)` can still be
    missed: declare it (`FunctionInput(fn, jumps=...)`) or bound the steps (`dtmax`)."""
    tp = jnp.linspace(t0, t1, n)
    values = jax.vmap(lambda t: jnp.atleast_1d(torque(t, y0)))(tp)
    return constant_stretch_ends(tp, values.reshape(n, -1))


class QuinticReference(eqx.Module):
    """Rest-to-rest quintic reference of paper 004 eq. (71):

        theta_d(t) = theta_0 + (6 s^5 - 15 s^4 + 10 s^3) (theta_f - theta_0),  s = t / t_d,

    held at `theta_f` for `t > t_d`. Paper 004: `theta_0 = (0, 0)`, `theta_f = (pi/2,
    pi/6)`, `t_d = 2 s`. Gives position, velocity and acceleration (rad, rad/s, rad/s^2).
    """

    start: Float[Array, " n"]
    end: Float[Array, " n"]
    duration: Float[Array, ""]

    def __init__(self, start, end, duration):
        self.start = jnp.atleast_1d(as_float_array(start))
        self.end = jnp.atleast_1d(as_float_array(end))
        self.duration = as_float_array(duration)
        warn_if_degrees("QuinticReference", "start", self.start)
        warn_if_degrees("QuinticReference", "end", self.end)

    def _s(self, t):
        return jnp.clip(t / self.duration, 0.0, 1.0)

    def position(self, t):
        s = self._s(t)
        return self.start + (6 * s**5 - 15 * s**4 + 10 * s**3) * (self.end - self.start)

    def velocity(self, t):
        s = self._s(t)
        return (30 * s**4 - 60 * s**3 + 30 * s**2) * (self.end - self.start) / self.duration

    def acceleration(self, t):
        s = self._s(t)
        return (120 * s**3 - 180 * s**2 + 60 * s) * (self.end - self.start) / self.duration**2


class PDTracking(AbstractInput):
    """Joint PD tracking of a reference: `tau = Kp (r - s) + Kd (r_dot - s_dot)`, with `s`
    the actuated coordinate of each joint (rotor angle of an elastic joint).

    **Arguments:** `reference` (has `position(t)`, `velocity(t)`), `kp` (N m/rad),
    `kd` (N m s/rad), `actuated` (indices of the actuated coordinates in Q, static:
    `chain.layout.actuated`), `n_dof` (static). `PDTracking.for_chain(chain, reference,
    kp, kd)` fills the last two from the chain.
    """

    reference: QuinticReference
    kp: Float[Array, " n"]
    kd: Float[Array, " n"]
    actuated: tuple[int, ...] = eqx.field(static=True)
    n_dof: int = eqx.field(static=True)

    @classmethod
    def for_chain(cls, chain, reference, kp, kd) -> PDTracking:
        """The tracking law on `chain`'s actuated coordinates."""
        return cls(reference, as_float_array(kp), as_float_array(kd), tuple(chain.layout.actuated), chain.n_dof)

    def __call__(self, t, y):
        idx = jnp.asarray(self.actuated)
        s, s_dot = y[idx], y[self.n_dof + idx]
        return self.kp * (self.reference.position(t) - s) + self.kd * (self.reference.velocity(t) - s_dot)


class FunctionInput(AbstractInput):
    """Wraps a plain callable `fn(t) -> torque` (or `fn(t, y)` with `state_feedback=True`).

    The callable must be traceable by JAX; arrays it closes over are constants, not
    parameters (use a Module subclass of `AbstractInput` for trainable inputs).
    `jumps`: the times (s) where `fn` is discontinuous, if known: adaptive and fixed
    steps land on them (as `BangBang`'s). Without them the adaptive solvers find where
    `fn` changes by probing it (`probed_step_times`).
    """

    fn: Callable
    state_feedback: bool = eqx.field(static=True, default=False)
    jumps: Float[Array, " J"] | None = None

    def __post_init__(self):
        if self.jumps is not None:
            self.jumps = jnp.atleast_1d(as_float_array(self.jumps))

    def __call__(self, t, y):
        return jnp.atleast_1d(self.fn(t, y) if self.state_feedback else self.fn(t))

    def jump_times(self):
        return self.jumps

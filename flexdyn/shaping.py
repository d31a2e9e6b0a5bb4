"""Classical input shaping: zero-vibration (ZV) and zero-vibration-and-derivative (ZVD)
shapers, and the convolution of a torque or reference signal with a shaper.

A shaper is a train of impulses `sum_i A_i delta(t - t_i)` with `sum_i A_i = 1`; a
command `f(t)` convolved with it, `f_s(t) = sum_i A_i f(t - t_i)`, moves the same
way as `f` in the rigid-body sense (unit gain) but leaves no residual vibration in a
mode of natural frequency `omega_n` (rad/s) and damping ratio `zeta` once the last
impulse has acted (Singer & Seering 1990, "Preshaping command inputs to reduce system
vibration", J. Dyn. Sys. Meas. Control 112:76-82). With
`omega_d = omega_n sqrt(1 - zeta^2)`, half damped period `T_d / 2 = pi / omega_d` and
`K = exp(-zeta pi / sqrt(1 - zeta^2))`:

- ZV:  `A = [1, K] / (1 + K)`, `t = [0, T_d / 2]`;
- ZVD: `A = [1, 2 K, K^2] / (1 + K)^2`, `t = [0, T_d / 2, T_d]`.

The residual vibration of a second-order mode after the last impulse, relative to
that of a single unit impulse applied at the last impulse's time `t_N`, is (Singer &
Seering 1990)

    V(omega_n, zeta) = exp(-zeta omega_n t_N) sqrt(C^2 + S^2),
    C = sum_i A_i exp(zeta omega_n t_i) cos(omega_d t_i),
    S = sum_i A_i exp(zeta omega_n t_i) sin(omega_d t_i).

ZV makes `V = 0` at the design frequency; ZVD also makes `dV/d omega_n = 0` there
(robust to modelling errors in the frequency), at the cost of one more half period.
Frequencies here are in Hz. `natural_frequency` is the **undamped** one, `omega_n / 2
pi`: `fd.modal_analysis`'s, or `f_d / sqrt(1 - zeta^2)` from `fd.damped_modes`' damped
frequency `f_d` and ratio `zeta` (passing `f_d` applies the damping correction twice:
at `zeta` = 0.085 the delay comes out 0.36 % long).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._checks import _is_concrete, as_float_array, check_parameter
from .inputs import AbstractInput, QuinticReference


class Shaper(eqx.Module):
    """An impulse train: `amplitudes` (dimensionless, sum 1) at `times` (s, ascending,
    first 0). Build with `zv_shaper` or `zvd_shaper`."""

    amplitudes: Float[Array, " N"]
    times: Float[Array, " N"]

    @property
    def duration(self) -> Float[Array, ""]:
        """Time of the last impulse (s): how much longer the shaped command lasts."""
        return self.times[-1]

    def residual_vibration(self, natural_frequency, damping_ratio) -> Float[Array, ""]:
        """Singer & Seering's `V(omega_n, zeta)` (module docstring) for a mode of
        `natural_frequency` (Hz) and `damping_ratio`: residual amplitude after the last
        impulse as a fraction of that left by a single unit impulse at `t_N`."""
        wn = 2 * jnp.pi * as_float_array(natural_frequency)
        zeta = as_float_array(damping_ratio)
        wd = wn * jnp.sqrt(1 - zeta**2)
        growth = self.amplitudes * jnp.exp(zeta * wn * self.times)
        C = jnp.sum(growth * jnp.cos(wd * self.times))
        S = jnp.sum(growth * jnp.sin(wd * self.times))
        return jnp.exp(-zeta * wn * self.times[-1]) * jnp.sqrt(C**2 + S**2)


def _k_and_half_period(natural_frequency, damping_ratio, caller: str):
    """`K` and the damped half period (s). Concrete arguments are checked (a NaN, zero or
    negative frequency, a damping ratio outside [0, 1)); traced ones (under
    jit/vmap/grad) are left as they are."""
    frequency, zeta = as_float_array(natural_frequency), as_float_array(damping_ratio)
    if _is_concrete(frequency):
        check_parameter(caller, "natural_frequency", frequency, positive=True)
    if _is_concrete(zeta):
        value = np.asarray(zeta, dtype=float)
        if not (np.all(np.isfinite(value)) and np.all(value >= 0) and np.all(value < 1)):
            raise ValueError(f"{caller}.damping_ratio: expected 0 <= zeta < 1 (an underdamped mode), got {value}")
    wn = 2 * jnp.pi * frequency
    root = jnp.sqrt(1 - zeta**2)
    return jnp.exp(-zeta * jnp.pi / root), jnp.pi / (wn * root)


def zv_shaper(natural_frequency, damping_ratio=0.0) -> Shaper:
    """Zero-vibration shaper (Singer & Seering 1990) for a mode of `natural_frequency`
    (Hz, undamped) and `damping_ratio` (0 <= zeta < 1): `A = [1, K] / (1 + K)` at
    `t = [0, pi / omega_d]`."""
    K, half = _k_and_half_period(natural_frequency, damping_ratio, "zv_shaper")
    return Shaper(jnp.stack([1.0, K]) / (1 + K), jnp.stack([jnp.zeros_like(half), half]))


def zvd_shaper(natural_frequency, damping_ratio=0.0) -> Shaper:
    """Zero-vibration-and-derivative shaper (Singer & Seering 1990) for a mode of
    `natural_frequency` (Hz, undamped) and `damping_ratio`: `A = [1, 2K, K^2] / (1 + K)^2`
    at `t = [0, pi / omega_d, 2 pi / omega_d]`."""
    K, half = _k_and_half_period(natural_frequency, damping_ratio, "zvd_shaper")
    return Shaper(jnp.stack([1.0, 2 * K, K**2]) / (1 + K) ** 2, jnp.stack([jnp.zeros_like(half), half, 2 * half]))


def convolve(signal, shaper: Shaper, t):
    """`sum_i A_i signal(t - t_i)`: the shaped value of a callable `signal(t)` at time(s) `t`.

    `signal` must give its pre-start value for negative arguments (zero for a torque
    that starts at 0, the initial position for a reference)."""
    t = as_float_array(t)
    terms = [a * signal(t - ti) for a, ti in zip(shaper.amplitudes, shaper.times)]
    return sum(terms[1:], terms[0])


class ShapedTorque(AbstractInput):
    """An open-loop torque input convolved with a shaper, one per joint or shared:
    `tau_j(t) = sum_i A_ji tau_base,j(t - t_ji)`.

    **Arguments:** `base` (an open-loop `AbstractInput`, zero before its start, e.g.
    `fd.BangBang`), `shapers` (a `Shaper`, or a tuple with one per joint).
    """

    base: AbstractInput
    shapers: tuple[Shaper, ...]

    def __init__(self, base: AbstractInput, shapers):
        self.base = base
        self.shapers = (shapers,) if isinstance(shapers, Shaper) else tuple(shapers)

    def __call__(self, t, y=None):
        if len(self.shapers) == 1:
            return convolve(lambda s: self.base(s, y), self.shapers[0], t)
        return jnp.stack([convolve(lambda s, j=j: self.base(s, y)[j], sh, t) for j, sh in enumerate(self.shapers)])

    def jump_times(self):
        jumps = self.base.jump_times()
        if jumps is None:
            return None
        return jnp.sort(jnp.concatenate([jumps + ti for sh in self.shapers for ti in sh.times]))

    def step_times(self):
        steps = self.base.step_times()
        if steps is None:
            return None
        return jnp.sort(jnp.concatenate([steps + ti for sh in self.shapers for ti in sh.times]))


class ShapedReference(eqx.Module):
    """A reference (`position`, `velocity`, `acceleration` of t, e.g. `fd.QuinticReference`)
    convolved with a shaper; usable wherever a `QuinticReference` is (PD tracking).
    Ends `shaper.duration` later than the base reference."""

    base: QuinticReference
    shaper: Shaper

    def position(self, t):
        return convolve(self.base.position, self.shaper, t)

    def velocity(self, t):
        return convolve(self.base.velocity, self.shaper, t)

    def acceleration(self, t):
        return convolve(self.base.acceleration, self.shaper, t)

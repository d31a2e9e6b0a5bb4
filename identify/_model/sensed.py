"""The recorded outputs of a solved trajectory: the model's channels read through the
log's sensors.

A delayed sensor reads its channel's value a moment back, which needs the channel's time
derivative as well (`measurement.apply_sensors` reads the past by cubic Hermite between
samples): `d out/dt = d out/dy . f(t, y)`, one forward-mode product per sample.
"""

from __future__ import annotations

from collections.abc import Callable

import jax

from .._data import measurement as meas


def recorded_outputs(sensors, channels, ts, ys, evaluate: Callable, rate: Callable, *inputs):
    """The recorded outputs `(T, C)` of `channels` at the sample times `ts` `(T,)` and
    states `ys` `(T, 2n)`.

    `evaluate(t, y, *u)` gives the channels' model values `(C,)`, `rate(t, y, *u)` the
    state's time derivative `(2n,)`; `inputs` are per-sample arrays `(T, ...)` passed to
    both as `u` (a closed loop's held command), or none (an input that is a function of
    time inside `evaluate`). The rates are computed only where a sensor needs them."""
    out = jax.vmap(evaluate)(ts, ys, *inputs)
    if meas.needs_rates(sensors, channels):

        def d_out(tk, yk, *uk):
            return jax.jvp(lambda y_: evaluate(tk, y_, *uk), (yk,), (rate(tk, yk, *uk),))[1]

        dout = jax.vmap(d_out)(ts, ys, *inputs)
    else:
        dout = out
    return meas.apply_sensors(sensors, channels, ts, out, dout)

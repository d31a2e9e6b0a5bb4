"""Synthetic logs: simulate a chain, record channels, add sensor noise.

Used by the tests (recovery, coverage, convergence), the benchmarks and the
shipped example. The simulation is independent of the fit's own (tight
adaptive tolerances, every channel evaluated from the state by flexdyn).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import flexdyn as fd

from .._data import channels as ch, measurement as meas
from .._data.channels import state_names
from .problem import LogData


def simulate_log(
    chain: fd.Chain,
    t,
    *,
    initial: dict | None = None,
    torque=None,
    channels=("theta1",),
    noise: dict | None = None,
    rng: np.random.Generator | None = None,
    fit_initial=(),
    offsets=(),
    true_offsets: dict | None = None,
    name: str = "synthetic",
    rtol: float = 1e-11,
    atol: float = 1e-13,
    measurement=None,
    hold: str | tuple[str, ...] = "linear",
) -> LogData:
    """A `LogData` of `chain` sampled at `t` (s).

    **Arguments:**
    - `initial`: initial-state entries by name (`theta1`, `q1_1`, `theta1_rate`, ...).
    - `torque`: samples `(T, n_joints)` in N m at `t`, or None; applied as `hold` reads
      them (`"linear"`, or `"zoh"`: held until the next sample, as a digital controller
      applies its commands; the returned `LogData.hold` says which).
    - `channels`: output channels to record (`identify.channels`).
    - `noise`: channel -> standard deviation of additive white Gaussian noise (SI).
    - `true_offsets`: channel -> constant sensor offset added to the record.
    - `fit_initial`, `offsets`: passed through to the `LogData` (what a fit estimates).
    - `measurement`: an `identify.measurement.Measurement` between the rig and the log
      (sensor gains, offsets, delays, high-pass filters, actuator lags): the torque in
      the returned log is the commanded one, the rig is driven by the lagged one, and
      the recorded channels pass through the sensors before the noise is added, and a
      sensor with a `resolution` then records whole steps of it (an encoder's counts).
    """
    t = np.asarray(t, float)
    initial = dict(initial or {})
    names = state_names(chain)
    y0 = np.zeros(len(names))
    for k, v in initial.items():
        y0[names.index(k)] = v
    for c in channels:
        ch.check_channel(chain, c)
    for c in sorted(set(noise or {}) - set(channels)):
        # a typo is refused rather than dropped; a channel of the chain that this log does
        # not record is fine (one noise dict for logs of different channels)
        try:
            ch.check_channel(chain, c)
        except ValueError as e:
            raise ValueError(f"simulate_log: noise: {e}; this log records {tuple(channels)}") from None
    inp = None
    if torque is not None:
        torque = np.asarray(torque, float).reshape(len(t), -1)
        inp = meas.actuated_torque(measurement or meas.Measurement(), t, torque, hold)
    traj = fd.simulate(chain, jnp.asarray(y0), jnp.asarray(t), inp, rtol=rtol, atol=atol)
    asm = fd.assemble(chain)
    inp_eval = inp if inp is not None else fd.ZeroTorque(chain.n_links)
    evaluate = lambda tk, yk: ch.evaluate(asm, tuple(channels), tk, yk, inp_eval)  # noqa: E731
    values = jax.vmap(evaluate)(traj.ts, traj.y)
    if measurement is not None:
        field = fd.ChainVectorField(asm, inp_eval)
        ydot = jax.vmap(lambda tk, yk: field(tk, yk, None))(traj.ts, traj.y)
        dvalues = jax.vmap(lambda tk, yk, vk: jax.jvp(lambda y_: evaluate(tk, y_), (yk,), (vk,))[1])(
            traj.ts, traj.y, ydot
        )
        values = meas.apply_sensors(measurement, tuple(channels), traj.ts, values, dvalues)
    values = np.asarray(values)
    rng = rng or np.random.default_rng(0)
    steps = meas.resolutions(measurement, tuple(channels)) if measurement is not None else np.zeros(len(channels))
    outputs = {}
    for j, c in enumerate(channels):
        v = values[:, j].copy()
        if true_offsets and c in true_offsets:
            v += true_offsets[c]
        if noise and noise.get(c):
            v += noise[c] * rng.standard_normal(v.shape)
        if steps[j] > 0:  # a quantised sensor (`Sensor.resolution`) records whole steps
            v = steps[j] * np.round(v / steps[j])
        outputs[c] = v
    return LogData(
        t=t,
        outputs=outputs,
        torque=torque,
        initial=initial,
        fit_initial=tuple(fit_initial),
        offsets=tuple(offsets),
        name=name,
        hold=hold,
    )

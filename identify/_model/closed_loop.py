r"""One closed-loop log simulated inside the residual: the rig under its digital controller.

The law is `identify.Controller`'s (its docstring has the equation); `FeedbackLaw` is its
numeric form inside a `Problem`, and `simulate_closed_log` runs it tick by tick at the
log's sample times `t_k`, as `flexdyn.simulate_closed_loop` does for a state-feedback law:

    u_k = law(readings at t_k, t_{k-1}; reference at t_k)   (or at t_{k-1}: `delay`)
    y(t_{k+1}) = flow of the chain under the constant u_k from y(t_k) over [t_k, t_{k+1}]

each period's flow by diffrax's Tsit5 inside a `lax.scan` (adaptive at the problem's
tolerances, or a constant step no longer than `step` that divides the period), in
forward mode, so a fit's Jacobian goes through the loop. The commands `u_k` are an output
of the model, compared with the log's command column.

**Quantised readings** (`Controller.quantise`). A reading rounded to its sensor's
resolution `q` is `m + stop_gradient(q round(m / q) - m)`: the rig's value exactly,
differentiated as if unrounded. The true derivative of the rounding is 0 almost everywhere, which would hide
the feedback from the fit's Jacobian; the rounding error itself is the reading's noise.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import flexdyn as fd
from flexdyn.sampled_loop import HeldCommand

from .._data import channels as ch, measurement as meas
from .._data.controller import Controller, check_period, reference_channel


class FeedbackLaw(eqx.Module):
    """`Controller`'s law in a `Problem`: the gains on `channels` (arrays, so a new value
    does not recompile), the commanded joint (0-based) and the static structure.

    - `gain`, `rate_gain`: `(F,)`, per channel of `channels` (0 where none).
    - `feedforward`: `()`; `limit`: `()` or None (command units).
    - `resolution`: `(F,)` static, each reading's quantisation step (0: none).
    - `referenced`: `(F,)` static, whether the channel's reference is a log column
      (`Problem.reference[..., f]`).
    - `period`: the rate's time step (s), or None for the sample intervals.
    """

    gain: jax.Array
    rate_gain: jax.Array
    feedforward: jax.Array
    limit: jax.Array | None
    channels: tuple[str, ...] = eqx.field(static=True)
    command: str = eqx.field(static=True)
    joint: int = eqx.field(static=True)
    resolution: tuple[float, ...] = eqx.field(static=True)
    referenced: tuple[bool, ...] = eqx.field(static=True)
    period: float | None = eqx.field(static=True)
    delay: bool = eqx.field(static=True)

    @staticmethod
    def of(controller: Controller, resolution) -> FeedbackLaw:
        """The law of `controller`; `resolution`: each of `controller.channels`'
        quantisation step (SI, 0 for none), used with `controller.quantise`."""
        chans = controller.channels
        resolution = resolution if controller.quantise else [0.0] * len(chans)
        return FeedbackLaw(
            gain=jnp.asarray([float(controller.gains.get(c, 0.0)) for c in chans]),
            rate_gain=jnp.asarray([float(controller.rate_gains.get(c, 0.0)) for c in chans]),
            feedforward=jnp.asarray(float(controller.feedforward)),
            limit=None if controller.limit is None else jnp.asarray(float(controller.limit)),
            channels=chans,
            command=controller.command,
            joint=controller.joint - 1,
            resolution=tuple(float(q) for q in resolution),
            referenced=tuple(c in controller.references for c in chans),
            period=controller.period,
            delay=controller.delay,
        )

    def command_of(self, reading, rate, reference):
        """The command (command units) from the readings, their rates and the references
        (each `(F,)`)."""
        u = self.feedforward + self.gain @ (reference - reading) - self.rate_gain @ rate
        return u if self.limit is None else jnp.clip(u, -self.limit, self.limit)


def _quantised(m, resolution: tuple[float, ...]):
    q = np.asarray(resolution, float)
    if not np.any(q > 0):
        return m
    qs = jnp.asarray(np.where(q > 0, q, 1.0))
    rounded = jnp.where(jnp.asarray(q > 0), qs * jnp.round(m / qs), m)
    return m + jax.lax.stop_gradient(rounded - m)


def _reading(asm, law: FeedbackLaw, sensors, t, y):
    """What the controller read at time `t` from state `y`: each channel's recorded value
    (`Sensor.gain`, `.offset`), quantised."""
    values = ch.evaluate(asm, law.channels, t, y, None)
    parts = []
    for k, c in enumerate(law.channels):
        v, s = values[k], sensors.sensors.get(c)
        if s is not None and s.gain is not None:
            v = s.gain * v
        if s is not None and s.offset is not None:
            v = v + s.offset
        parts.append(v)
    return _quantised(jnp.stack(parts), law.resolution)


class ClosedLog(eqx.Module):
    """`simulate_closed_log`'s result: the states at the samples `(T, 2n)`, the commands
    `(T,)` (command units; the commanded joint's input from each sample on), the inputs
    `(T, n_joints)` held from each sample, whether every period's solve succeeded, and
    their accepted steps, and whether a period's solve ran out of `max_steps`."""

    ys: jax.Array
    commands: jax.Array
    inputs: jax.Array
    ok: jax.Array
    steps: jax.Array
    limited: jax.Array


def simulate_closed_log(
    asm, law: FeedbackLaw, sensors, ts, logged, reference, y0, *, step=None, dt=None, rtol, atol, max_steps
) -> ClosedLog:
    """The loop over the sample times `ts` `(T,)` (non-decreasing: a zero-length interval,
    a padded sample or one outside the solve's span, leaves the state and the command as
    they are), from `y0` at `ts[0]`. `logged`: the log's inputs `(T, n_joints)` (the
    other joints', and with `delay` the first command); `reference`: `(T, F)`.

    `step` (s, may be traced): Tsit5 at the constant step `h / ceil(h / step)` in each
    period `h`; `dt`: RK4 likewise (`Problem.dt`); neither: adaptive Tsit5 at `rtol`,
    `atol`. `max_steps`: per period."""
    h = jnp.diff(ts)
    h_rate = h if law.period is None else jnp.where(h > 0, law.period, 0.0)
    zero_rate = jnp.zeros(len(law.channels), y0.dtype)

    def command(k, y, m_prev, rate_prev):
        """The law at sample `k >= 1` from the state `y` there and the previous reading
        `m_prev` (a zero-length interval keeps the rate `rate_prev`: no new reading)."""
        m = _reading(asm, law, sensors, ts[k], y)
        hk = h_rate[k - 1]
        rate = jnp.where(hk > 0, (m - m_prev) / jnp.where(hk > 0, hk, 1.0), rate_prev)
        return law.command_of(m, rate, reference[k]), m, rate

    def inputs(k, u):
        return logged[k].at[law.joint].set(u)

    m0 = _reading(asm, law, sensors, ts[0], y0)
    law0 = law.command_of(m0, zero_rate, reference[0])
    first = logged[0, law.joint] if law.delay else law0

    def period(carry, k):
        y, u, pending, m_prev, rate_prev = carry
        t0, t1 = ts[k], ts[k + 1]
        moves = t1 > t0
        # (a period of zero length, past the solve's span or padding, gets a dummy span of
        # one short step, its result discarded)
        t1s = jnp.where(moves, t1, t0 + 1e-9)
        if step is not None or dt is not None:
            solver = diffrax.Tsit5() if step is not None else fd.RK4()
            size = step if step is not None else dt
            controller, dt0 = diffrax.ConstantStepSize(), (t1s - t0) / jnp.ceil((t1s - t0) / size - 1e-9)
        else:
            solver, controller, dt0 = diffrax.Tsit5(), diffrax.PIDController(rtol=rtol, atol=atol), None
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(fd.ChainVectorField(asm, HeldCommand(inputs(k, u)))),
            solver,
            t0=t0,
            t1=t1s,
            dt0=dt0,
            y0=y,
            saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=controller,
            max_steps=max_steps,
            adjoint=diffrax.ForwardMode(),
            throw=False,
        )
        ok = (sol.result == diffrax.RESULTS.successful) & jnp.all(jnp.isfinite(sol.ys[-1]))
        y1 = jnp.where(moves & ok, sol.ys[-1], y)
        law_k1, m1, rate1 = command(k + 1, y1, m_prev, rate_prev)
        m1 = jnp.where(moves, m1, m_prev)
        rate1 = jnp.where(moves, rate1, rate_prev)
        # the command from t_{k+1}: the law there, or (delay) the one computed at t_k
        u_next = jnp.where(moves, pending if law.delay else law_k1, u)
        pending_next = jnp.where(moves, law_k1, pending)
        steps = jnp.where(moves, sol.stats["num_accepted_steps"], 0)
        limited = moves & (sol.result == diffrax.RESULTS.max_steps_reached)
        return (y1, u_next, pending_next, m1, rate1), (y1, u_next, ok | ~moves, steps, limited)

    carry0 = (y0, first, law0, m0, zero_rate)
    _, (ys, us, oks, steps, limited) = jax.lax.scan(period, carry0, jnp.arange(ts.shape[0] - 1))
    ys = jnp.concatenate([y0[None], ys], axis=0)
    commands = jnp.concatenate([first[None], us], axis=0)
    held = jax.vmap(inputs)(jnp.arange(ts.shape[0]), commands)
    return ClosedLog(ys, commands, held, jnp.all(oks), jnp.sum(steps), jnp.any(limited))


def closed_log_outputs(problem, asm, sensors, ts, logged, reference, y0, step):
    """The recorded outputs `(T, C)` of one closed-loop log, in `problem.channels` order
    (the command channel: the model's commands), and its `ClosedLog`. `ts`: the sample
    times clipped to the solve's span."""
    law = problem.loop
    _check_loop_measurement(sensors, law.channels)
    run = simulate_closed_log(
        asm,
        law,
        sensors,
        ts,
        logged,
        reference,
        y0,
        step=step,
        dt=problem.dt,
        rtol=problem.rtol,
        atol=problem.atol,
        max_steps=problem.max_steps,
    )
    ys = jnp.where(run.ok, run.ys, 0.0)
    physical = tuple(c for c in problem.channels if c != law.command)
    evaluate = lambda tk, yk, uk: ch.evaluate(asm, physical, tk, yk, HeldCommand(uk))  # noqa: E731
    out = jax.vmap(evaluate)(ts, ys, run.inputs)
    if meas.needs_rates(sensors, physical):
        # (delayed sensors: d out/dt = d out/dy . f(t, y), under the input held from each sample)
        def rate(tk, yk, uk):
            ydot = fd.ChainVectorField(asm, HeldCommand(uk))(tk, yk, None)
            return jax.jvp(lambda y_: evaluate(tk, y_, uk), (yk,), (ydot,))[1]

        dout = jax.vmap(rate)(ts, ys, run.inputs)
    else:
        dout = out
    out = meas.apply_sensors(sensors, physical, ts, out, dout)
    columns = {c: out[:, k] for k, c in enumerate(physical)}
    columns[law.command] = jnp.where(run.ok, run.commands, 0.0)
    return jnp.stack([columns[c] for c in problem.channels], axis=1), run


def _check_loop_measurement(measurement, channels) -> None:
    """The sensor and drive effects a closed loop does not simulate, refused while
    tracing (a measurement changed after `make_problem`, e.g. a diagnosis candidate)."""
    for c in channels:
        sensor = measurement.sensors.get(c)
        for effect in ("delay", "highpass"):
            if sensor is not None and getattr(sensor, effect) is not None:
                raise ValueError(
                    f"closed loop: the law reads {c}, whose sensor has a {effect}; a closed-loop simulation reads its "
                    f"channels at the samples, without sensor dynamics: drop sensor.{c}.{effect}"
                )
    if any(v is not None for v in measurement.actuator_lag):
        raise ValueError(
            "closed loop: an actuator lag is not simulated in a closed loop (the command is held at each sample); "
            "drop actuator<i>.lag"
        )


def check_closed_loop(chain, measurement, controller: Controller, logs) -> None:
    """Raise `ValueError` naming what a closed-loop problem cannot hold: a command of a
    joint the rig lacks or that drives it differently, a channel the rig lacks, a sensor
    with dynamics (a delay or a high-pass) on a channel the law reads (its reading would
    need the past between samples), an actuator lag (not simulated in the loop), and logs
    without the command column, a reference column, or a per-log offset on a channel the
    law reads (the controller read the sensor as it was)."""
    if not isinstance(controller, Controller):
        raise TypeError(f"make_problem: controller expected an identify.Controller, got {type(controller).__name__}")
    joint = controller.joint
    why = ch.channel_problem(chain, controller.command)
    if why is not None:
        raise ValueError(f"make_problem: controller.command {controller.command!r}: {why}")
    for c in controller.channels:
        try:
            ch.check_channel(chain, c)
        except ValueError as e:
            raise ValueError(f"make_problem: controller: {e}") from None
    try:
        _check_loop_measurement(measurement, controller.channels)
    except ValueError as e:
        raise ValueError(f"make_problem: controller: {e}") from None
    for log in logs:
        where = f"log {log.name!r}"
        if log.torque is None or np.asarray(log.torque).reshape(len(log.t), -1).shape[1] < joint:
            raise ValueError(
                f"{where}: no {controller.command} column; a closed-loop log records the command its controller "
                "computed (the law's output, compared with the model's)"
            )
        for c in controller.references:
            r = log.reference.get(c)
            if r is None:
                raise ValueError(
                    f"{where}: no reference for {c} ({reference_channel(c)}); the controller's law takes {c}'s "
                    "reference from the log (controller.references)"
                )
            r = np.asarray(r, float)
            if r.shape != (len(log.t),) or not np.all(np.isfinite(r)):
                raise ValueError(
                    f"{where}: reference[{c!r}] expected {len(log.t)} finite samples (SI), got shape {r.shape}"
                    + ("" if r.shape != (len(log.t),) else " with a non-finite value")
                )
        extra = sorted(set(log.reference) - set(controller.references))
        if extra:
            raise ValueError(
                f"{where}: reference for {extra}, which the controller does not take from the log (its "
                f"references: {list(controller.references)})"
            )
        read = sorted(set(log.offsets) & set(controller.channels))
        if read:
            raise ValueError(
                f"{where}: offsets for {read}, which the controller reads; a per-log offset would change what it "
                f"read: fit a calibration offset shared by all logs (sensor.{read[0]}.offset) instead"
            )
        check_period(controller, np.asarray(log.t, float), where)


def reference_array(controller: Controller, logs, T: int) -> np.ndarray:
    """`(L, T, F)`: each log's references of `controller.channels` (0 where none), the
    last sample repeated over the padding."""
    chans = controller.channels
    out = np.zeros((len(logs), T, len(chans)))
    for l, log in enumerate(logs):
        k = len(log.t)
        for f, c in enumerate(chans):
            if c in log.reference:
                r = np.asarray(log.reference[c], float)
                out[l, :k, f], out[l, k:, f] = r, r[-1]
    return out

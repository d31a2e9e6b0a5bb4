"""Time integration of a chain with diffrax, and the outputs users measure.

`simulate` integrates `y = [Q, Q_dot]` with an adaptive solver (default Tsit5,
`rtol`/`atol`) or with a fixed step (`dt`, default RK4: papers 002/004 use RK4 at
1 ms). It is pure and jit-compiled once per chain structure; `jax.grad`,
`jax.jacfwd` (with `adjoint=diffrax.ForwardMode()`: diffrax's default adjoint is reverse
mode only, and says "can't apply forward-mode autodiff (jvp) to a custom_vjp function")
and `jax.vmap` work through it (parameters are pytree leaves of the chain and the input).
Failures are raised, never returned as NaNs: reaching `max_steps`, or a non-finite state,
is an error that says what to change.
"""

from __future__ import annotations

import math
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._checks import as_float_array, check_parameter, warn_if_degrees, warn_if_single_precision
from .chain import (
    AssembledChain,
    Chain,
    accelerations,
    assemble,
    end_point,
    has_motors,
    motor_forces,
    root_curvatures,
    tip_deflections,
    total_energy,
)
from .inputs import AbstractInput, FunctionInput, ZeroTorque, probed_step_times
from .linear import check_rk4_step
from .solvers import RK4


def as_input(torque, n_joints: int) -> AbstractInput:
    """`None` -> no torque; an `AbstractInput` as is; any other callable `fn(t)` is wrapped
    in `FunctionInput`."""
    if torque is None:
        return ZeroTorque(n_joints)
    if isinstance(torque, AbstractInput):
        return torque
    if callable(torque):
        return FunctionInput(torque)
    raise ValueError(f"torque: expected None, an AbstractInput or a callable fn(t) -> (n_joints,) N m, got {torque!r}")


def as_initial_state(asm, y0, caller: str) -> Float[Array, " 2n"]:
    """`y0` as a float array, checked to be `[Q, Q_dot]` of the assembled chain (a
    `ValueError` naming `caller`, the expected shape and the coordinates otherwise)."""
    n = asm.layout.n_dof
    y0 = jnp.asarray(y0, dtype=float)
    if y0.shape != (2 * n,):
        raise ValueError(
            f"{caller}: y0 expected shape ({2 * n},) = [Q, Q_dot] for coordinates "
            f"{list(asm.layout.names)}, got {y0.shape}"
        )
    if isinstance(y0, jax.core.Tracer):
        return eqx.error_if(y0, ~jnp.all(jnp.isfinite(y0)), f"{caller}: y0 has a non-finite entry (NaN or inf)")
    bad = np.flatnonzero(~np.isfinite(np.asarray(y0)))
    if bad.size:
        i = int(bad[0])
        name = asm.layout.names[i] if i < n else f"{asm.layout.names[i - n]}_dot"
        raise ValueError(f"{caller}: y0 expected finite values, got {float(y0[i])} at index {i} ({name})")
    return y0


def check_torque_shape(torque: AbstractInput, t0, y0, n_joints: int) -> None:
    shape = jax.eval_shape(torque, t0, y0).shape
    if shape != (n_joints,):
        raise ValueError(
            f"torque: the input returns shape {shape}, expected ({n_joints},): one torque [N m] per joint "
            f"(e.g. BangBang(amplitude=[...] with {n_joints} value(s)))"
        )


def check_times(ts, caller: str):
    """`ts` as a float array, checked to be 1-D, of at least 2 finite, strictly increasing
    times: concrete values at once (a `ValueError` naming the first bad entry), traced ones
    at run time (`eqx.error_if`). diffrax would integrate a decreasing grid backwards from
    `y0` at `ts[0]` without a word."""
    if not isinstance(ts, jax.core.Tracer):
        ts = np.asarray(ts, dtype=float)  # concrete: checked on the host, even inside jit
    if np.ndim(ts) != 1 or np.shape(ts)[0] < 2:
        raise ValueError(f"{caller}: ts expected a 1-D array of at least 2 times, got shape {np.shape(ts)}")
    expected = f"{caller}: ts expected finite, strictly increasing times"
    if isinstance(ts, jax.core.Tracer):
        ts = jnp.asarray(ts, dtype=float)
        bad = ~jnp.all(jnp.isfinite(ts)) | ~jnp.all(jnp.diff(ts) > 0)
        return eqx.error_if(ts, bad, expected)
    t = ts
    if not np.all(np.isfinite(t)) or not np.all(np.diff(t) > 0):
        k = int(np.argmax(~np.isfinite(t[1:]) | ~(np.diff(t) > 0))) + 1
        k = 0 if not np.isfinite(t[0]) else k
        after = f" after ts[{k - 1}] = {float(t[k - 1])!r}" if k else ""
        raise ValueError(f"{expected}; ts[{k}] = {float(t[k])!r}{after}")
    return jnp.asarray(t)


def prepare(chain, y0, ts, torque, caller: str):
    """The assembled chain, `y0`, `ts` and the input of a solve, checked (a `ValueError`
    naming `caller` and what was expected otherwise)."""
    warn_if_single_precision(
        caller,
        "the results carry ~1e-7 relative error at best, and the adaptive solver's default tolerances "
        "(rtol 1e-8) are below float32's resolution, so it takes several times the steps",
    )
    asm = assemble(chain)
    y0 = as_initial_state(asm, y0, caller)
    ts = check_times(ts, caller)
    torque = as_input(torque, asm.chain.n_links)
    check_torque_shape(torque, ts[0], y0, asm.chain.n_links)
    # (a NaN torque makes the adaptive steps collapse until max_steps: said here instead)
    y0 = eqx.error_if(
        y0,
        ~jnp.all(jnp.isfinite(torque(ts[0], y0))),
        f"{caller}: the torque input is not finite (NaN or inf) at ts[0]: check its amplitudes, samples or function",
    )
    return asm, y0, ts, torque


def adaptive_controller(torque: AbstractInput, rtol: float, atol: float, dtmax: float | None = None, probe=None):
    """diffrax's PID step-size controller (steps of at most `dtmax` s, if given), with the
    steps clipped onto the input's jumps (`torque.jump_times()`) so that no stage reads the
    far side of a discontinuity, and onto its step times (`torque.step_times()`: e.g. where
    a sampled torque's constant stretch ends, so that a chain at rest does not step over
    the input that follows). An input that declares neither (a plain callable, a feedback
    law) is probed over the solve's span, `probe = (t0, t1, y0)`
    (`flexdyn.inputs.probed_step_times`)."""
    controller = diffrax.PIDController(rtol=rtol, atol=atol, dtmax=dtmax)
    jumps, steps = torque.jump_times(), torque.step_times()
    if jumps is None and steps is None and probe is not None and not isinstance(torque, ZeroTorque):
        steps = probed_step_times(torque, *probe)
    if jumps is not None or steps is not None:
        controller = diffrax.ClipStepSizeController(controller, step_ts=steps, jump_ts=jumps)
    return controller


class ChainVectorField(eqx.Module):
    """The first-order vector field `y_dot = [Q_dot, Q_ddot(Q, Q_dot, torque(t, y))]`.

    `t_last` (s, optional): the input is read at `min(t, t_last)`. The fixed-step solve of
    `simulate` passes `t1^-`, the last float before the span's end, so that a step ending on
    an input jump at `t1` reads the torque before it, as steps ending on interior jumps do
    (reading the far side would put the final rates off by `h dtau / (6 J)`)."""

    model: AssembledChain
    torque: AbstractInput
    t_last: Array | None = None

    def __call__(self, t, y, args):
        n = y.shape[0] // 2
        Q, Qd = y[:n], y[n:]
        t_input = t if self.t_last is None else jnp.minimum(t, self.t_last)
        return jnp.concatenate([Qd, accelerations(self.model, Q, Qd, self.torque(t_input, y))])


class Trajectory(eqx.Module):
    """A simulated trajectory: `ts` (s), `Q`, `Q_dot` (rad, m; rad/s, m/s) per time sample,
    the chain's coordinate names (static) and the number of accepted solver steps.
    `driven` (static): whether an input drove it (`observe` then needs the same input)."""

    ts: Float[Array, " T"]
    Q: Float[Array, "T n"]
    Qd: Float[Array, "T n"]
    num_steps: Array
    names: tuple[str, ...] = eqx.field(static=True)
    driven: bool = eqx.field(static=True, default=False)

    @property
    def y(self):
        return jnp.concatenate([self.Q, self.Qd], axis=-1)

    def coordinate(self, name: str):
        """Time series of one generalised coordinate by name (e.g. `'theta1'`, `'q2_1'`)."""
        if name not in self.names:
            raise KeyError(f"unknown coordinate {name!r}; this chain has {list(self.names)}")
        return self.Q[..., self.names.index(name)]


def initial_state(
    chain: Chain, joint_angles, joint_rates=None, modal=None, modal_rates=None, rotor_angles=None, rotor_rates=None
) -> Float[Array, " 2n"]:
    """Build `y0 = [Q, Q_dot]` from named parts (rad, rad/s, m, m/s).

    Rotor angles/rates of elastic joints default to the link angles/rates (unloaded
    springs). `modal` is the concatenation of all links' modal coordinates. Traceable
    (e.g. `jax.vmap` over release angles); concrete values are checked to be finite.
    """
    lay = chain.layout
    n_links = chain.n_links

    def vec(x, size, name):
        x = jnp.zeros(size) if x is None else jnp.atleast_1d(as_float_array(x))
        if x.shape != (size,):
            raise ValueError(f"initial_state: {name} expected shape ({size},), got {x.shape}")
        check_parameter("initial_state", name, x, signed=True)
        return x

    theta, theta_d = vec(joint_angles, n_links, "joint_angles"), vec(joint_rates, n_links, "joint_rates")
    warn_if_degrees("initial_state", "joint_angles", theta)
    if rotor_angles is not None:
        warn_if_degrees("initial_state", "rotor_angles", rotor_angles)
    n_modal = sum(len(m) for m in lay.modal)
    modal_idx = np.asarray([k for m in lay.modal for k in m], dtype=int)
    theta_idx = np.asarray(lay.theta, dtype=int)
    Q = jnp.zeros(lay.n_dof).at[theta_idx].set(theta).at[modal_idx].set(vec(modal, n_modal, "modal"))
    Qd = jnp.zeros(lay.n_dof).at[theta_idx].set(theta_d).at[modal_idx].set(vec(modal_rates, n_modal, "modal_rates"))
    alpha = theta if rotor_angles is None else vec(rotor_angles, n_links, "rotor_angles")
    alpha_d = theta_d if rotor_rates is None else vec(rotor_rates, n_links, "rotor_rates")
    for i, k in enumerate(lay.rotor):
        if k is not None:
            Q, Qd = Q.at[k].set(alpha[i]), Qd.at[k].set(alpha_d[i])
    return jnp.concatenate([Q, Qd])


def floats_as_arrays(tree):
    """Python floats among a pytree's leaves as float arrays. `eqx.filter_jit` holds a
    float leaf static, so each new value (put in by `eqx.tree_at(..., 2.0)`) would compile
    the program again."""
    return jax.tree.map(lambda x: jnp.asarray(x, dtype=float) if isinstance(x, float) else x, tree)


def simulate(chain, y0, ts, torque=None, **options) -> Trajectory:
    return _simulate(floats_as_arrays(chain), y0, ts, floats_as_arrays(torque), **options)


@eqx.filter_jit
def _simulate(
    chain: Chain | AssembledChain,
    y0,
    ts,
    torque: AbstractInput | None = None,
    *,
    solver: diffrax.AbstractSolver | None = None,
    dt: float | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 200_000,
    adjoint: diffrax.AbstractAdjoint | None = None,
    dtmax: float | None = None,
) -> Trajectory:
    """Integrate the chain from `y0` at `ts[0]` and return the state at every `ts`.

    **Arguments:**
    - `chain`: the model (a `Chain`; assembled inside, so its parameters are traced).
    - `y0`: initial state `[Q, Q_dot]` (see `initial_state`).
    - `ts`: output times, s, increasing; integration runs from `ts[0]` to `ts[-1]`.
    - `torque`: joint-torque input, N m (default: none): an `AbstractInput`
      (`BangBang`, `SampledTorque`, `PDTracking`, ...) or any callable `fn(t)`. The
      adaptive steps land where an input declares its changes (`jump_times()`,
      `step_times()`); one that declares none (a plain callable) is probed at 1024 times
      of `[ts[0], ts[-1]]` and the steps land on the ends of its constant stretches, so
      that a chain at rest does not step over a torque that starts later. A change
      shorter than the probe spacing can still be missed: declare it
      (`FunctionInput(fn, jumps=[...])`) or bound the steps (`dtmax`).
    - `solver`: a diffrax solver (default `Tsit5()` adaptive, `RK4()` with `dt`).
    - `dt`: fixed step, s (e.g. `1e-3` as papers 002/004); adaptive if None. Steps are
      aligned to the input's discontinuities (`torque.jump_times()`), so fixed-step RK4
      stays fourth-order accurate across a bang-bang switch. A `dt` above RK4's stability
      limit for the linearisation at `y0` (`fd.stable_step(chain, y0, solver="rk4", safety=1.0)`) by
      more than 2 % is refused before the run (`flexdyn.linear.check_rk4_step`; it costs
      ~1.5 s more compilation on paper 004's arm); the stiffness moves with the
      configuration, so stay clear of the limit.
    - `rtol`, `atol`: adaptive tolerances.
    - `dtmax`: the largest adaptive step, s (default: none). **Derivatives from rest need
      it.** While nothing moves (at rest, no input yet) the error estimate is 0 and the
      steps grow tenfold each, far beyond the stability limit of the stiffest mode. The
      states stay right (nothing moves), but their derivatives (`jax.grad`, `jax.jacfwd`)
      pass through those steps' linearisation and blow up: on paper 004's arm at rest, a
      bang-bang starting at 0.05 s gave a NaN gradient (a zero input, 1e27). A `dtmax` at
      the stability limit of the stiffest mode (`fd.stable_step(chain, y0)`) keeps them
      bounded; a quarter of it made them accurate (1e-7 relative, tested to 1e-6, on a
      flexible pendulum at rest: `tests/flexdyn/test_linear.py`; at the limit itself, 0.7 % off: nothing
      controls the error of the derivatives while nothing moves). Once the chain moves,
      the step control keeps them right by itself (paper 004's arm from rest under a
      bang-bang from t = 0: 4e-7 at rtol 1e-6). The cost: every step at most `dtmax`.
      Alternatives: start the log where the input starts, or use a fixed `dt`.
    - `max_steps`: step budget; exceeding it is an error.
    - `adjoint`: diffrax adjoint for reverse-mode gradients (default: recursive
      checkpointing; forward mode `jax.jacfwd` needs `diffrax.ForwardMode()`).

    **Cost of gradients** (measured: `docs/performance.md`): `jax.grad` with the defaults
    pays for a checkpoint schedule planned for `max_steps` steps; with `max_steps` near the
    number of steps taken and `adjoint=diffrax.RecursiveCheckpointAdjoint(checkpoints=
    max_steps)` (a checkpoint at every step: one solver state per step) it is cheaper.
    `jax.jacfwd` needs `diffrax.ForwardMode()`. For reverse mode with fixed-step RK4 on
    output times known when tracing, `flexdyn.rk4_trajectory` takes the same steps with a
    discrete adjoint (~4x its forward solve); for the adaptive solve,
    `flexdyn.tsit5_trajectory` is this function's solve with a discrete adjoint (~4x).
    """
    asm, y0, ts, torque = prepare(chain, y0, ts, torque, "simulate")
    n = asm.layout.n_dof
    field = ChainVectorField(asm, torque)
    if dtmax is not None and not (float(dtmax) > 0 and math.isfinite(float(dtmax))):
        raise ValueError(f"simulate: dtmax expected a step > 0 s, got {dtmax!r}")
    if dt is not None and not isinstance(dt, jax.core.Tracer) and not (float(dt) > 0 and math.isfinite(float(dt))):
        raise ValueError(f"simulate: dt expected a fixed step > 0 s (or None: adaptive), got {dt!r}")
    if dt is None:
        solver = diffrax.Tsit5() if solver is None else solver
        controller = adaptive_controller(torque, rtol, atol, dtmax, probe=(ts[0], ts[-1], y0))
        dt0 = None
    else:
        if dtmax is not None:
            raise ValueError("simulate: dtmax bounds the adaptive steps; with a fixed dt, leave it None")
        if solver is None or isinstance(solver, RK4):
            y0 = check_rk4_step(asm, y0, torque(ts[0], y0), dt, "simulate")
        solver = RK4() if solver is None else solver
        dt0 = dt
        field = ChainVectorField(asm, torque, t_last=jnp.nextafter(ts[-1], ts[0]))
        jumps = torque.jump_times()
        if jumps is None:
            controller = diffrax.ConstantStepSize()
        else:
            # Fixed steps of `dt`, except that a step ending on an input discontinuity is
            # clipped to end just before it and the next one starts on it: without this,
            # one stage would read the torque from the far side of the jump and RK4 would
            # be first-order accurate (measured: 3e-3 rad at 1 ms vs 2.5e-10 with clipping
            # on paper 002's bang-bang). RK4 has no error estimate, so the PID controller
            # below always proposes `dt`.
            controller = diffrax.ClipStepSizeController(
                diffrax.PIDController(rtol=1.0, atol=1.0, dtmin=dt, dtmax=dt), jump_ts=jumps
            )
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0=ts[0],
        t1=ts[-1],
        dt0=dt0,
        y0=y0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
        max_steps=max_steps,
        adjoint=diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint,
        throw=False,
    )
    ys = sol.ys
    ys = eqx.error_if(
        ys,
        sol.result == diffrax.RESULTS.max_steps_reached,
        f"simulate: the solver reached max_steps={max_steps} before the last output time; "
        + (
            "raise max_steps, loosen rtol/atol, or use a larger fixed dt (a torque input that turns NaN "
            "after ts[0] also ends this way: check the input)"
            if dt is None
            else "raise max_steps or use a larger dt; or the fixed step dt is above the "
            "stability limit of the stiffest mode or joint and the state blew up (the step control "
            "then rejects every step): reduce dt or use the adaptive solver (dt=None)"
        ),
    )
    ys = eqx.error_if(
        ys,
        (sol.result != diffrax.RESULTS.successful) & (sol.result != diffrax.RESULTS.max_steps_reached),
        "simulate: the ODE solver failed (step size collapsed or non-finite vector field); "
        "check the parameters (a NaN or negative mass/stiffness?) and the initial state",
    )
    ys = eqx.error_if(
        ys,
        ~jnp.all(jnp.isfinite(ys)),
        "simulate: the state became non-finite (NaN/inf); with a fixed step this usually means "
        "dt is above the stability limit of the stiffest mode or joint: reduce dt or use the adaptive solver "
        "(or the torque input turned NaN: check it)",
    )
    driven = not isinstance(torque, ZeroTorque)
    return Trajectory(ts, ys[:, :n], ys[:, n:], sol.stats["num_accepted_steps"], asm.layout.names, driven)


simulate.__doc__ = _simulate.__doc__


class Outputs(eqx.Module):
    """What a rig's sensors and a user want per time sample (SI units).

    - `joint_angle`, `joint_rate`: link angles theta_i (rad, rad/s), shape (T, n_links).
    - `rotor_angle`, `rotor_rate`: rotor angles alpha_i (equal to theta_i for rigid joints).
    - `joint_deflection`: alpha_i - theta_i (rad), zero for rigid joints.
    - `modal`, `modal_rate`: all modal coordinates (m, m/s), shape (T, n_modes_total).
    - `tip_deflection`: elastic tip deflection v_i(l_i) of every link (m).
    - `root_curvature`: v_i''(0) (1/m), proportional to root strain-gauge readings.
    - `end_point`, `end_point_acceleration`: tip of the last link in the base frame
      (m, m/s^2), shape (T, 2).
    - `energy`: total mechanical energy T + V (J) (and the inductive motors' magnetic
      energy `1/2 L i^2`: `flexdyn.motor`).
    - `torque`: applied joint torques (N m); a motor's torque on its joint
      (`flexdyn.motor.joint_torque`, its own friction included), not its command.
    """

    ts: Array
    joint_angle: Array
    joint_rate: Array
    rotor_angle: Array
    rotor_rate: Array
    joint_deflection: Array
    modal: Array
    modal_rate: Array
    tip_deflection: Array
    root_curvature: Array
    end_point: Array
    end_point_acceleration: Array
    energy: Array
    torque: Array


#: `observe` warns when a link's elastic tip deflection exceeds this fraction of its length
#: (what the small-deflection model neglects is of the order of its square: 4 %; paper
#: 004's own bang-bang bends its first link by 10 %)
LARGE_DEFLECTION = 0.2


def observe(chain: Chain | AssembledChain, traj: Trajectory, torque: AbstractInput | None = None) -> Outputs:
    """Evaluate all `Outputs` along a trajectory (the same `torque` as the simulation:
    the accelerations and the `torque` output depend on it). A trajectory that an input
    drove (`traj.driven`) observed without one is refused: its end-point accelerations
    would be those of free motion, wrong without a word.

    The links' elastic deformation is modelled for small deflections (Euler-Bernoulli
    beams, assumed modes: the strain is linear in the modal coordinates). Called outside
    `jit`, it warns when a link's tip deflection exceeds `LARGE_DEFLECTION` (20 %) of its
    length, where that no longer holds."""
    out = _observe(chain, traj, torque)
    _warn_if_large_deflection(chain, out.tip_deflection)
    return out


def _warn_if_large_deflection(chain, tip) -> None:
    links = chain.chain.links if isinstance(chain, AssembledChain) else chain.links
    if isinstance(tip, jax.core.Tracer) or any(isinstance(link.length, jax.core.Tracer) for link in links):
        return
    tip = np.asarray(tip)
    if tip.ndim != 2:  # (a vmapped batch of trajectories: not looked at)
        return
    peak = np.max(np.abs(tip), axis=0)
    for i, link in enumerate(links):
        length = float(np.asarray(link.length))
        if np.isfinite(peak[i]) and peak[i] > LARGE_DEFLECTION * length:
            warnings.warn(
                f"observe: link{i + 1}'s elastic tip deflection reaches {peak[i]:.3g} m, "
                f"{100 * peak[i] / length:.0f} % of its {length:g} m length; the model assumes small deflections "
                f"and neglects terms of the order of (deflection / length)^2 ({100 * (peak[i] / length) ** 2:.0f} % "
                "here): check the input's size and units",
                UserWarning,
                stacklevel=3,
            )


@eqx.filter_jit
def _observe(chain: Chain | AssembledChain, traj: Trajectory, torque: AbstractInput | None = None) -> Outputs:
    if torque is None and traj.driven:
        raise ValueError(
            "observe: this trajectory was simulated with an input; pass the same torque "
            "(observe(chain, traj, torque)): without it the accelerations and torques would be those of free motion"
        )
    asm = assemble(chain)
    lay = asm.layout
    torque = as_input(torque, asm.chain.n_links)

    def one(t, Q, Qd):
        tau = torque(t, jnp.concatenate([Q, Qd]))
        Qdd = accelerations(asm, Q, Qd, tau)
        applied = motor_forces(asm, Qd, tau)[jnp.asarray(lay.actuated)] if has_motors(asm.chain) else tau
        pos = lambda Q_: end_point(asm, Q_)  # noqa: E731
        vel = lambda Q_, Qd_: jax.jvp(pos, (Q_,), (Qd_,))[1]  # noqa: E731
        # a = J Qdd + (dJ/dt) Qd
        acc = jax.jvp(pos, (Q,), (Qdd,))[1] + jax.jvp(lambda Q_: vel(Q_, Qd), (Q,), (Qd,))[1]
        theta = Q[jnp.asarray(lay.theta)]
        theta_d = Qd[jnp.asarray(lay.theta)]
        act = jnp.asarray(lay.actuated)
        modal_idx = jnp.asarray([k for m in lay.modal for k in m], dtype=int)
        return dict(
            joint_angle=theta,
            joint_rate=theta_d,
            rotor_angle=Q[act],
            rotor_rate=Qd[act],
            joint_deflection=Q[act] - theta,
            modal=Q[modal_idx],
            modal_rate=Qd[modal_idx],
            tip_deflection=tip_deflections(asm, Q),
            root_curvature=root_curvatures(asm, Q),
            end_point=pos(Q),
            end_point_acceleration=acc,
            energy=total_energy(asm, Q, Qd),
            torque=applied,
        )

    out = jax.vmap(one)(traj.ts, traj.Q, traj.Qd)
    return Outputs(ts=traj.ts, **out)

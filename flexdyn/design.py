"""Gradient-based trajectory design: rest-to-rest moves with no residual vibration.

A move takes the arm from rest at `start_angles` to rest at `goal_angles` (rad) in a
move time `T` (s). The joint torque is a smooth parameterised signal
(`BSplineTorque`: a cubic B-spline per joint, saturated smoothly so that
`|tau_j(t)| < tau_max` at every instant); its control points are chosen by
Levenberg-Marquardt (optimistix) on a residual vector built from one simulation
(`fd.simulate`, fixed-step RK4) over `[0, T + settle]`, differentiated through the
solver in forward mode:

    r = [ (theta(t_k) - theta_goal) / sqrt(K),                  (rad)
          v_tip(t_k) / (L_ref sqrt(K)),                         (m / m)
          theta_dot(T) tau_ref,                                 (rad/s * s)
          (alpha(t_k) - theta(t_k)) / sqrt(K),                  (rad, elastic joints)
          alpha_dot(T) tau_ref ],                               (rad/s * s, elastic joints)

with `t_k` the `K` samples of the settle window `[T, T + settle]` and `v_tip` the
elastic tip deflections of every link. After `T` the torque is zero, so a state that
stays at the goal over the window is a rest-to-rest move. For an arm with elastic joints
(paper 004) the torque acts on the rotors (`alpha`) and the goal is on the link angles;
the last two blocks (only present when some joint is elastic, so the residuals of a
rigid-joint arm are unchanged) ask the joint springs to be unloaded over the window and
the rotors to be at rest at `T`. The robust variant
(`robust_residuals`) appends, for a vmapped batch of payload masses, the same residuals
without the window angles (at rest without vibration, wherever the payload made the arm
stop), weighted by `payload_weight` against the nominal ones.

Robust design (`notebooks/trajectory_design*.ipynb`, batch 0 / 50 / 100 g): the
worst-case residual vibration over 0-100 g is 5.0x below the nominal design's on paper
002's arm (default weight 1), 4.2x on paper 004's arm (weight 15; there the payload
halves or doubles the shoulder inertia, and the robust move gives up 6e-2 rad of goal
accuracy with the nominal payload).

Performance measures (`move_metrics`) are the same for every input, so the optimised
move can be compared with bang-bang, shaped bang-bang (`flexdyn.shaping`) or a tracking
controller on the same move and the same `T`.
"""

from __future__ import annotations

import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from ._checks import _is_concrete, as_float_array, check_parameter, warn_if_degrees
from .chain import Chain, assemble, generalised_forces
from .inputs import AbstractInput
from .simulation import observe, simulate


def cubic_bspline(x):
    """The centred cardinal cubic B-spline `b(x)` (support `[-2, 2]`, C^2, `b(0) = 2/3`):
    `(2 - |x|)^3 / 6` for `1 <= |x| < 2`, `2/3 - x^2 + |x|^3 / 2` for `|x| < 1`, else 0."""
    a = jnp.abs(x)
    inner = 2.0 / 3.0 - a**2 + 0.5 * a**3
    outer = (2.0 - a) ** 3 / 6.0
    return jnp.where(a < 1.0, inner, jnp.where(a < 2.0, outer, 0.0))


def bspline_basis(t, n_control: int, duration) -> Float[Array, "... n_control"]:
    """Basis `N_k(t) = b(t / h - k - 2)`, `k = 0 .. n_control - 1`, knot spacing
    `h = duration / (n_control + 3)`: every basis function's support lies inside
    `[0, duration]`, so the spline and its first two derivatives are zero at `t <= 0`
    and `t >= duration` (a torque that starts and ends smoothly at zero)."""
    h = duration / (n_control + 3)
    k = jnp.arange(n_control, dtype=float)
    return cubic_bspline(jnp.asarray(t, dtype=float)[..., None] / h - k - 2.0)


class BSplineTorque(AbstractInput):
    """Joint torque `tau_j(t) = tau_max_j tanh(s_j(t) / tau_max_j)`, N m, with
    `s_j(t) = sum_k c_kj N_k(t)` a cubic B-spline on `[0, duration]` (`bspline_basis`),
    zero outside it. The saturation keeps `|tau_j| < tau_max_j` at every time by
    construction and is smooth, so gradients flow for every control point.

    **Arguments:** `control_points` (N m, shape `(n_control, n_joints)`), `duration` (s),
    `tau_max` (N m, scalar or one per joint).
    """

    control_points: Float[Array, "n_control n_joints"]
    duration: Float[Array, ""]
    tau_max: Float[Array, " n_joints"]

    def __init__(self, control_points, duration, tau_max):
        self.control_points = as_float_array(control_points)
        if self.control_points.ndim != 2 or self.control_points.shape[0] < 1:
            raise ValueError(
                f"BSplineTorque.control_points: expected shape (n_control, n_joints), got {self.control_points.shape}"
            )
        check_parameter("BSplineTorque", "control_points", self.control_points, signed=True)
        self.duration = as_float_array(duration)
        check_parameter("BSplineTorque", "duration", self.duration, positive=True, shape=())
        tau = as_float_array(tau_max)
        check_parameter("BSplineTorque", "tau_max", tau, positive=True)
        if tau.ndim > 1 or (tau.ndim == 1 and tau.shape != self.control_points.shape[1:]):
            raise ValueError(
                f"BSplineTorque.tau_max: expected a scalar or one limit per joint (shape "
                f"{self.control_points.shape[1:]}, the control points' columns), got shape {tau.shape}"
            )
        self.tau_max = jnp.broadcast_to(tau, self.control_points.shape[1:])
        if not isinstance(self.tau_max, jax.core.Tracer) and np.any(np.asarray(self.tau_max) <= 0):
            raise ValueError(f"BSplineTorque.tau_max: expected torque limits > 0 N m, got {tau_max!r}")

    def spline(self, t):
        """The unsaturated spline `s(t)` (N m)."""
        return bspline_basis(t, self.control_points.shape[0], self.duration) @ self.control_points

    def __call__(self, t, y=None):
        return self.tau_max * jnp.tanh(self.spline(t) / self.tau_max)

    @staticmethod
    def fit(times, torques, n_control: int, duration, tau_max) -> BSplineTorque:
        """The `BSplineTorque` whose spline is the least-squares fit of sampled torques
        `(T, n_joints)` (clipped to 0.95 `tau_max` and passed through `artanh`, so that the
        saturated torque matches them): e.g. an initial guess from a bang-bang."""
        check_parameter("BSplineTorque.fit", "tau_max", np.asarray(tau_max, dtype=float), positive=True)
        check_parameter("BSplineTorque.fit", "duration", np.asarray(duration, dtype=float), positive=True, shape=())
        late = np.asarray(times, dtype=float) > float(duration)
        if np.any(late):
            warnings.warn(
                f"BSplineTorque.fit: {int(np.sum(late))} of the {late.size} samples lie after duration = "
                f"{float(duration):g} s, where the spline is zero; they are not fitted",
                UserWarning,
                stacklevel=2,
            )
        tau_max = np.broadcast_to(np.asarray(tau_max, dtype=float), np.shape(torques)[1:])
        target = tau_max * np.arctanh(np.clip(np.asarray(torques) / tau_max, -0.95, 0.95))
        basis = np.asarray(bspline_basis(jnp.asarray(times), n_control, jnp.asarray(float(duration))))
        cp, *_ = np.linalg.lstsq(basis, target, rcond=None)
        return BSplineTorque(cp, duration, tau_max)


class RestToRestMove(eqx.Module):
    """A rest-to-rest move and how it is scored.

    **Arguments:**
    - `chain`: the arm (its `payload.mass` is replaced per evaluation in the robust design).
    - `start_angles`, `goal_angles`: link angles (rad), at rest.
    - `duration`: move time `T` (s).
    - `tau_max`: torque limit (N m), scalar or per joint.
    - `settle`: length of the window after `T` over which residual vibration is scored (s).
    - `n_window`: samples in the window (including `T` and `T + settle`).
    - `dt`: fixed RK4 step (s); a compile-time setting.
    - `length_scale`: `L_ref` (m) that turns tip deflections into angles in the residuals.
    - `rate_time_scale`: `tau_ref` (s) weighting the terminal joint rates.
    """

    chain: Chain
    start_angles: Float[Array, " n_joints"]
    goal_angles: Float[Array, " n_joints"]
    duration: Float[Array, ""]
    tau_max: Float[Array, " n_joints"]
    settle: Float[Array, ""]
    length_scale: Float[Array, ""]
    rate_time_scale: Float[Array, ""]
    n_window: int = eqx.field(static=True)
    dt: float = eqx.field(static=True)

    def __init__(
        self,
        chain,
        start_angles,
        goal_angles,
        duration,
        tau_max,
        *,
        settle=1.0,
        n_window=101,
        dt=2e-3,
        length_scale=0.5,
        rate_time_scale=0.1,
    ):
        self.chain = chain
        self.start_angles = jnp.atleast_1d(as_float_array(start_angles))
        self.goal_angles = jnp.atleast_1d(as_float_array(goal_angles))
        n = chain.n_links
        if self.start_angles.shape != (n,) or self.goal_angles.shape != (n,):
            raise ValueError(
                f"RestToRestMove: expected {n} start and goal angles, got {self.start_angles.shape} "
                f"and {self.goal_angles.shape}"
            )
        check_parameter("RestToRestMove", "start_angles", self.start_angles, signed=True)
        check_parameter("RestToRestMove", "goal_angles", self.goal_angles, signed=True)
        warn_if_degrees("RestToRestMove", "start_angles", self.start_angles)
        warn_if_degrees("RestToRestMove", "goal_angles", self.goal_angles)
        self.duration = as_float_array(duration)
        tau = as_float_array(tau_max)
        if tau.ndim > 1 or (tau.ndim == 1 and tau.shape != (n,)):
            raise ValueError(
                f"RestToRestMove.tau_max: expected a scalar or one limit per joint (shape ({n},)), got shape "
                f"{tau.shape}"
            )
        self.tau_max = jnp.broadcast_to(tau, (n,))
        self.settle = as_float_array(settle)
        self.length_scale = as_float_array(length_scale)
        self.rate_time_scale = as_float_array(rate_time_scale)
        for name in ("duration", "tau_max", "settle", "length_scale", "rate_time_scale"):
            value = getattr(self, name)
            check_parameter("RestToRestMove", name, value, positive=True, shape=() if name != "tau_max" else (n,))
        if _is_concrete(self.duration) and float(self.duration) > 60.0:
            warnings.warn(
                f"RestToRestMove.duration = {float(self.duration):g} s is over a minute; flexdyn takes seconds "
                f"(if {float(self.duration):g} is in ms, pass {float(self.duration) / 1e3:g})",
                UserWarning,
                stacklevel=4,  # the user's RestToRestMove(...) line (through equinox's __call__)
            )
        if isinstance(n_window, bool) or int(n_window) != n_window or n_window < 2:
            raise ValueError(
                f"RestToRestMove.n_window: expected an integer >= 2 (samples from T to T + settle), got {n_window!r}"
            )
        self.n_window = int(n_window)
        check_parameter("RestToRestMove", "dt", dt, positive=True)
        self.dt = float(dt)
        if _is_concrete(self.duration) and self.dt >= float(self.duration):
            raise ValueError(
                f"RestToRestMove.dt: expected a step shorter than the move's duration {float(self.duration):g} s, "
                f"got {self.dt:g} s"
            )
        _warn_if_not_at_rest(chain, self.start_angles, self.goal_angles, self.tau_max)

    def output_times(self):
        """`[0, T, ..., T + settle]` (s): start, then the window samples."""
        window = self.duration + jnp.linspace(0.0, 1.0, self.n_window) * self.settle
        return jnp.concatenate([jnp.zeros(1), window])

    def initial_state(self):
        """Rest at `start_angles` with undeformed links and unloaded joint springs (traceable)."""
        return jnp.concatenate([_rest_configuration(self.chain, self.start_angles), jnp.zeros(self.chain.n_dof)])

    def with_payload(self, payload_mass) -> RestToRestMove:
        """The move with the chain's `payload.mass` (kg) replaced; the payload's rotary
        inertia `payload.inertia` is kept (so a mass of 0 still carries it)."""
        mass = as_float_array(payload_mass)
        check_parameter("RestToRestMove.with_payload", "payload_mass", mass, shape=())
        return eqx.tree_at(lambda m: m.chain.payload.mass, self, mass)

    def torque(self, control_points) -> BSplineTorque:
        return BSplineTorque(control_points, self.duration, self.tau_max)


def _rest_configuration(chain: Chain, angles):
    """`Q` with the link angles at `angles` (rad), undeformed links and unloaded joint
    springs (each rotor at its link's angle). Traceable."""
    lay = chain.layout
    Q = jnp.zeros(lay.n_dof).at[jnp.asarray(lay.theta)].set(angles)
    for i, k in enumerate(lay.rotor):
        if k is not None:
            Q = Q.at[k].set(angles[i])
    return Q


#: `RestToRestMove` warns when gravity's torque on a joint at the start or goal, at rest,
#: exceeds this fraction of the joint's torque limit
HOLDING_TORQUE_FRACTION = 1e-3


def _warn_if_not_at_rest(chain: Chain, start, goal, tau_max) -> None:
    """Warn when the start or goal angles are not an equilibrium of the unforced arm
    (gravity's torque on a joint, links undeformed, above `HOLDING_TORQUE_FRACTION` of its
    limit). The designed torque is zero from `T` on (`BSplineTorque`), so under gravity
    the arm can stay only where gravity exerts no torque (a vertical pendulum moved from
    hanging to 0.5 rad off would end far from its goal)."""
    values = (chain, start, goal, tau_max)
    if not all(_is_concrete(x) for x in jax.tree_util.tree_leaves(values)):
        return
    if not np.any(np.asarray(chain.gravity, dtype=float)):
        return
    asm = assemble(chain)
    lay = asm.layout
    for label, angles in (("start", start), ("goal", goal)):
        Q = _rest_configuration(chain, angles)
        F = generalised_forces(asm, Q, jnp.zeros(lay.n_dof), jnp.zeros(chain.n_links))
        hold = np.abs(np.asarray(F)[list(lay.theta)])
        limit = np.asarray(tau_max, dtype=float)
        if np.any(hold > HOLDING_TORQUE_FRACTION * limit):
            j = int(np.argmax(hold / limit))
            warnings.warn(
                f"RestToRestMove: the {label} angles are not an equilibrium of the unforced arm: at rest there, "
                f"gravity exerts {hold[j]:.3g} N m on joint {j + 1} (its limit {limit[j]:.3g} N m), and the "
                "designed torque is zero after T, so the arm cannot "
                + ("stay at its goal" if label == "goal" else "start at rest")
                + "; choose angles where the links hang or stand upright, or a chain in a horizontal plane "
                "(gravity=(0, 0))",
                UserWarning,
                stacklevel=5,  # the user's RestToRestMove(...) line (through equinox's __call__)
            )


def move_residuals(control_points, move: RestToRestMove, *, at_goal: bool = True, adjoint=None):
    """Residual vector of the move (module docstring) for one chain: dimensionless
    (rad-like), length `n_window (n_joints + n_links) + n_joints`, plus
    `n_window n_joints + n_joints` when some joint is elastic.

    With `at_goal=False` the block of window angles is left out (length `n_window n_links
    + n_joints`, plus the elastic-joint blocks): the residuals then ask only that the arm
    have no vibration over the window and no joint rates at `T` (so no drift), wherever it
    stopped. The window angles measured from `theta(T)` are not used instead: for a free
    arm (no torque, no joint damping after `T`) they equal a rate at `T` times the time
    since `T`, so they would repeat the rate residuals with a weight growing over the
    window, and in the robust design that rigid drift crowded out the tip vibration.

    `adjoint`: how the solve is differentiated (default `diffrax.ForwardMode()`: for
    `jax.jacfwd` / `jax.jvp`, what `design_move`'s Levenberg-Marquardt uses). For
    `jax.grad` of a cost built on the residuals (reverse mode: optax, your own
    optimiser) pass `adjoint=diffrax.RecursiveCheckpointAdjoint()`: forward mode
    cannot be reversed (JAX's "Reverse-mode differentiation does not work for
    lax.while_loop")."""
    torque = move.torque(control_points)
    traj = simulate(
        move.chain,
        move.initial_state(),
        move.output_times(),
        torque,
        dt=move.dt,
        adjoint=diffrax.ForwardMode() if adjoint is None else adjoint,
    )
    out = observe(move.chain, traj, torque)
    scale = 1.0 / jnp.sqrt(float(move.n_window))
    tip = out.tip_deflection[1:] / move.length_scale * scale
    rates = out.joint_rate[1] * move.rate_time_scale
    parts = [tip.ravel(), rates]
    if at_goal:
        parts.insert(0, ((out.joint_angle[1:] - move.goal_angles) * scale).ravel())
    if any(k is not None for k in move.chain.layout.rotor):
        # elastic joints: unloaded springs over the window, rotors at rest at T
        parts += [(out.joint_deflection[1:] * scale).ravel(), out.rotor_rate[1] * move.rate_time_scale]
    return jnp.concatenate(parts)


def robust_residuals(control_points, move: RestToRestMove, payload_masses, payload_weight=1.0, *, adjoint=None):
    """Residuals of a design robust to the payload: `move_residuals` of the nominal chain
    (`move.chain`, reaching the goal), followed by the at-rest residuals
    (`at_goal=False`) for every payload mass (kg) of a vmapped batch, scaled by
    `payload_weight / sqrt(n_payloads)` (with the default weight 1 their sum of squares
    is the mean over payloads, and the nominal residuals count as much as that mean).

    `payload_weight` sets the trade-off between reaching the goal exactly with the
    nominal payload and stopping without vibration with the others. When the payload
    changes the inertia a lot (paper 004's arm: 0-100 g at the tip halves or doubles the
    inertia about the shoulder) no open-loop torque does both in a short move, and a
    weight above 1 spreads the residual vibration evenly over the batch at the cost of
    the nominal goal error (`notebooks/trajectory_design_paper004.ipynb`).

    An open-loop torque cannot bring different inertias to the same angles, so the
    payloads other than the nominal one are asked to stop without vibration and with
    their joints at rest at `T`, not to stop at the goal; how far from the goal they stop
    is reported by `move_metrics`. `adjoint`: as for `move_residuals`."""
    payload_masses = as_float_array(payload_masses)
    per_payload = jax.vmap(
        lambda m: move_residuals(control_points, move.with_payload(m), at_goal=False, adjoint=adjoint)
    )(payload_masses)
    nominal = move_residuals(control_points, move, adjoint=adjoint)
    scale = payload_weight / jnp.sqrt(float(payload_masses.shape[0]))
    return jnp.concatenate([nominal, per_payload.ravel() * scale])


class MoveDesign(eqx.Module):
    """Result of `design_move`: the optimised `torque`, the final `cost`
    (`0.5 |r|^2`), the initial cost, the optimistix result code and its stats.

    `result` is optimistix's: `max_steps_reached` is usual even after the cost has
    fallen by many orders. Near the optimum the residual is not zero (finitely many
    control points do not cancel the vibration exactly) and Gauss-Newton converges
    linearly there, each step moving the residuals by more than optimistix's `atol`.
    Judge a design by `cost` against `initial_cost` and by `move_metrics` (residual
    vibration, goal error), not by `result` alone.

    `goal_error` (rad): the largest |theta - theta_goal| of the nominal chain over the
    window `[T, T + settle]`, from the residuals at the optimum; `reached_goal`: whether
    it is within `GOAL_TOLERANCE` of the move's largest joint travel. `summary()` says both
    in words, and what to try when the goal is not reached (an infeasible move returns
    the same `result` as a good design)."""

    torque: BSplineTorque
    cost: Array
    initial_cost: Array
    result: optx.RESULTS
    num_steps: Array
    goal_error: Array
    travel: Array  # rad: the largest |goal - start| over the joints

    @property
    def reached_goal(self) -> bool:
        return bool(float(self.goal_error) <= GOAL_TOLERANCE * max(float(self.travel), 1e-12))

    def summary(self) -> str:
        cost, cost0 = float(self.cost), float(self.initial_cost)
        lines = [
            f"cost {cost0:.4g} -> {cost:.4g} ({cost / cost0 if cost0 > 0 else float('nan'):.3g} of the initial) in "
            f"{int(self.num_steps)} Levenberg-Marquardt steps"
            + (
                " (all of max_steps: `result` then reads max_steps_reached, usual for a design whose residual "
                "cannot reach zero; judge it by the cost and the goal error below)"
                if self.result == optx.RESULTS.max_steps_reached
                else ""
            ),
            f"largest joint-angle error over [T, T + settle] (nominal payload): {float(self.goal_error):.3g} rad "
            f"({100 * float(self.goal_error) / max(float(self.travel), 1e-12):.3g} % of the move's "
            f"{float(self.travel):.3g} rad)",
        ]
        if not self.reached_goal:
            lines.append(
                f"warning: the arm does not stop at its goal (more than {100 * GOAL_TOLERANCE:g} % of the move off): "
                "the move may be infeasible with this duration and torque limit (try a longer duration or a larger "
                "tau_max), gravity may pull the arm off its goal (RestToRestMove warns of that), or the design needs "
                "more steps (max_steps); move_metrics gives the details"
            )
        return "\n".join(lines)


#: `MoveDesign.reached_goal`: the goal error allowed, as a fraction of the move's travel
GOAL_TOLERANCE = 0.01


def _residuals(control_points, args):
    # A module-level function, not a closure made per call, so that optimistix's compiled
    # solve is reused by later calls with the same shapes.
    move, masses, weight = args
    if masses is None:
        return move_residuals(control_points, move)
    return robust_residuals(control_points, move, masses, weight)


MARQUARDT_TRUST_REGION = optx.ClassicalTrustRegion(
    high_cutoff=0.75, low_cutoff=0.25, high_constant=3.0, low_constant=0.5
)
"""Marquardt's damping update (Fletcher 1971; Nocedal and Wright, "Numerical
Optimization", 2nd ed., Algorithm 4.1, with its constants 1/4 and 3/4): the trust region
grows after every step whose actual reduction is more than 3/4 of the Gauss-Newton
model's and shrinks (the step rejected) below 1/4. optimistix's default grows it only
above 0.99, so on a move's residuals, whose model agreement stays between those, the
damping froze and the cost crept down ~20 % a step (the gain on paper 002's arm:
`docs/performance.md`)."""


def _move_solver(rtol: float, atol: float):
    """`optx.LevenbergMarquardt` with `MARQUARDT_TRUST_REGION` as its search."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    return eqx.tree_at(lambda s: s.search, solver, MARQUARDT_TRUST_REGION)


def _check_design_inputs(move: RestToRestMove, initial) -> None:
    """`design_move`'s preconditions on the initial torque: a `BSplineTorque` over the
    move's joints, duration and torque limits (the move's are the ones used)."""
    if not isinstance(initial, BSplineTorque):
        raise TypeError(
            f"design_move: initial expected a BSplineTorque (e.g. BSplineTorque.fit of a bang-bang's samples), "
            f"got {type(initial).__name__}"
        )
    n = move.chain.n_links
    if initial.control_points.shape[1] != n:
        raise ValueError(
            f"design_move: initial has {initial.control_points.shape[1]} joint columns, the move's arm {n} joints"
        )
    for name in ("duration", "tau_max"):
        mine, theirs = getattr(initial, name), getattr(move, name)
        if _is_concrete(mine) and _is_concrete(theirs) and not np.allclose(np.asarray(mine), np.asarray(theirs)):
            raise ValueError(
                f"design_move: initial.{name} = {np.asarray(mine)} differs from the move's {np.asarray(theirs)}; the "
                f"design uses the move's (build the initial torque with move.torque(control_points) or "
                f"BSplineTorque.fit(..., duration=move.duration, tau_max=move.tau_max))"
            )


def design_move(
    move: RestToRestMove,
    initial: BSplineTorque,
    payload_masses=None,
    *,
    payload_weight=1.0,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 60,
    throw: bool = False,
) -> MoveDesign:
    """Choose the control points of `initial` (a `BSplineTorque` with the move's duration
    and limits) by Levenberg-Marquardt on `move_residuals` (nominal chain), or on
    `robust_residuals` over `payload_masses` (kg) when given, with `payload_weight` (see
    `robust_residuals`). Jacobians are forward-mode
    through the RK4 solve; the damping follows Marquardt's update
    (`MARQUARDT_TRUST_REGION`). `throw=False` returns the best point found when `max_steps` is
    reached (check `result`)."""

    _check_design_inputs(move, initial)
    if isinstance(max_steps, bool) or int(max_steps) != max_steps or max_steps < 1:
        raise ValueError(f"design_move.max_steps: expected an integer >= 1, got {max_steps!r}")
    masses = None if payload_masses is None else as_float_array(payload_masses)
    if masses is not None:
        if masses.ndim != 1 or masses.shape[0] < 1:
            raise ValueError(
                f"design_move.payload_masses: expected a 1-D array of payload masses (kg), e.g. [0.0, 0.05, 0.1], "
                f"got shape {masses.shape}"
            )
        check_parameter("design_move", "payload_masses", masses)
    weight = as_float_array(payload_weight)
    if weight.ndim != 0 or (not isinstance(weight, jax.core.Tracer) and not float(weight) > 0):
        raise ValueError(f"design_move.payload_weight: expected one number > 0, got {payload_weight!r}")
    args = (move, masses, weight)
    cp0 = initial.control_points
    cost0 = 0.5 * jnp.sum(_residuals(cp0, args) ** 2)
    sol = optx.least_squares(
        _residuals,
        _move_solver(rtol, atol),
        cp0,
        args=args,
        options={"jac": "fwd"},
        max_steps=max_steps,
        throw=throw,
    )
    r = _residuals(sol.value, args)
    cost = 0.5 * jnp.sum(r**2)
    # the first block of the nominal residuals: (theta - goal) / sqrt(n_window) over the window
    goal_error = jnp.max(jnp.abs(r[: move.n_window * move.chain.n_links])) * jnp.sqrt(float(move.n_window))
    travel = jnp.max(jnp.abs(move.goal_angles - move.start_angles))
    return MoveDesign(move.torque(sol.value), cost, cost0, sol.result, sol.stats["num_steps"], goal_error, travel)


def move_metrics(
    move: RestToRestMove,
    torque: AbstractInput,
    *,
    solver: diffrax.AbstractSolver | None = None,
    dt: float | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    n_torque_samples: int = 4001,
) -> dict[str, np.ndarray]:
    """Score any input on the move (host-side, NumPy results, SI units):

    - `residual_vibration` (m): RMS over the window `[T, T + settle]` of the Euclidean
      norm of the links' elastic tip deflections;
    - `peak_residual_deflection` (m): largest |tip deflection| in the window;
    - `angle_error_T`, `angle_error_end` (rad): max |theta - theta_goal| at `T` and at
      `T + settle`;
    - `rate_T` (rad/s): max |theta_dot| and |alpha_dot| (link and rotor rates) at `T`;
    - `joint_deflection_T`, `joint_deflection_window` (rad): max |alpha - theta| at `T`
      and over the window (zero for rigid joints);
    - `peak_torque` (N m): max |tau| per joint over `n_torque_samples` times on
      `[0, T + settle]` (for a feedback input, along the simulated trajectory);
    - `state_T`: the state `[Q, Q_dot]` at `T`.

    Simulated with `solver` (default RK4 at `dt`, the move's step, when `dt` is None and
    `solver` is None; pass e.g. `diffrax.Dopri8()` with `rtol`/`atol` for an adaptive
    reference run)."""
    if solver is None and dt is None:
        dt = move.dt
    # one run on the union of the window samples and a fine grid for the torque
    window = np.asarray(move.output_times())
    t_fine = np.linspace(0.0, window[-1], n_torque_samples)
    ts = np.unique(np.concatenate([window, t_fine]))
    k = np.searchsorted(ts, window)
    traj = simulate(
        move.chain, move.initial_state(), jnp.asarray(ts), torque, solver=solver, dt=dt, rtol=rtol, atol=atol
    )
    out = observe(move.chain, traj, torque)
    tip = np.asarray(out.tip_deflection)[k[1:]]
    theta = np.asarray(out.joint_angle)[k]
    rate_T = np.concatenate([np.asarray(out.joint_rate)[k[1]], np.asarray(out.rotor_rate)[k[1]]])
    deflection = np.asarray(out.joint_deflection)[k[1:]]
    goal = np.asarray(move.goal_angles)
    tau = np.asarray(out.torque)
    return {
        "residual_vibration": float(np.sqrt(np.mean(np.sum(tip**2, axis=1)))),
        "peak_residual_deflection": float(np.max(np.abs(tip))),
        "angle_error_T": float(np.max(np.abs(theta[1] - goal))),
        "angle_error_end": float(np.max(np.abs(theta[-1] - goal))),
        "rate_T": float(np.max(np.abs(rate_T))),
        "joint_deflection_T": float(np.max(np.abs(deflection[0]))),
        "joint_deflection_window": float(np.max(np.abs(deflection))),
        "peak_torque": np.max(np.abs(tau), axis=0),
        "state_T": np.asarray(traj.y)[k[1]],
    }

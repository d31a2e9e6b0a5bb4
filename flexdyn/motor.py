r"""A DC motor with a gearbox driving a joint: the electrical side of a real rig's drive.

A joint of a `Chain` may carry a `DCMotor` (`Chain(..., motors=[...])`, one entry per
joint, `None` for a joint driven by torque directly). The joint's input (the column of the
`AbstractInput`, e.g. a log's `SampledTorque`) is then the motor's *command*: a voltage
(V, `drive="voltage"`), a current (A, `drive="current"`, a current amplifier) or a torque
(N m at the joint, `drive="torque"`, a torque amplifier: a current amplifier whose command
is scaled by `N K_t`).

**The motor and its gear** (the permanent-magnet DC motor of Hughes & Drury, *Electric
Motors and Drives*; the Maxon catalogue's "key information" formulas). The gear ratio `N` and the rotor inertia
`J_m` are the joint's own (`joint.gear_ratio`, `joint.rotor_inertia`: the rotor's kinetic
energy `1/2 J_m (N s_dot)^2` is already in the chain's), so the motor shaft turns at
`w = N s_dot`, `s_dot` the rate of the joint's actuated coordinate (the link angle of a
rigid joint, the rotor angle of an elastic one). With armature resistance `R`, torque
constant `K_t` (N m/A, equal in SI to the back-EMF constant `K_b`, V s/rad, by the power
balance of an ideal converter: `K_t i w = e i`), current `i` and supply voltage `V`:

    L di/dt = V - R i - K_t w                              (armature circuit)
    tau_joint = N e(x) K_t i - N (b_m w + c_m tanh(w / v_s))   (joint torque, N m)

with the motor's own viscous friction `b_m` (N m s/rad) and smoothed Coulomb friction
`c_m` (N m), both on the motor side and referred through the gear by `N` (the viscous term
becomes `N^2 b_m` on the joint rate); `v_s` is the smoothing speed (rad/s, motor side,
as `flexdyn.nonlinear`'s dry friction).

**Inductance.** `inductance=None` (the default): the quasi-static current
`i = (V - K_t w) / R` (the electrical time constant `L / R`, typically 0.1 to 1 ms, is
neglected next to the mechanical one `J R / (N^2 K_t^2)`); the motor then adds no state,
and a voltage-driven joint gains the back-EMF damping `N^2 K_t^2 / R` (N m s/rad) on its
rate, a physical floor under any fitted joint damping (`back_emf_damping`). With an
inductance `L > 0` (H) the current is a state: the armature's charge is a generalised
coordinate `charge<i>` (C, after the mechanical ones) whose rate is the current, with
"kinetic" (magnetic) energy `1/2 L i^2`, Rayleigh dissipation `1/2 R i^2` and generalised
force `V - K_t w` (the Lagrange-Maxwell equations of electromechanics, as in Crandall et al., *Dynamics of
Mechanical and Electromechanical Systems*, 1968). The chain's own machinery then
integrates, linearises and differentiates it; the stored energy `1/2 L i^2` is part of
`flexdyn.kinetic_energy`. A current or torque amplifier holds the current itself (its
loop hides `L`), so an inductance is only accepted with `drive="voltage"`.

**Gear efficiency** `eta` (0 < eta <= 1). A gear passes on `eta` of the power when the
motor drives the load and takes `1/eta` of the motor's torque (times `N`) from the load
when the load drives the motor: either way it loses power, never makes it. Its losses are
friction, so they are smoothed as `flexdyn.nonlinear`'s dry friction is, over the
direction of the power flow:

    e(x) = eta^tanh(x),     x = sign(i) w / v_s,

`e -> eta` when the motor drives (`i w > 0`), `-> 1/eta` when it brakes at speed, `e = 1`
at rest (no motion, no loss, as the smoothed dry friction has none at rest). The gear's
loss `(1 - e) N K_t i s_dot` is `>= 0` everywhere (tested). So the torque-speed line of a
voltage `V` driving at `|w| >> v_s`, `eta N K_t (V - K_t w) / R`, has the catalogue's stall
torque `eta N K_t V / R` (the Maxon catalogue's output-shaft figure) as its intercept; at
exactly zero speed the smoothed gear passes `N K_t V / R`. This is the constant-efficiency
simplification: real gears lose more at light load and low speed.

**Voltage saturation** (`voltage_limit`, V, `None`: none): the amplifier applies
`clip(V, -V_max, V_max)`. A current or torque amplifier's command needs the voltage
`R i_cmd + K_t w` (quasi-static), clipped the same way; the current is then what the
clipped voltage drives, `(V - K_t w) / R`. The clip is hard, not smoothed: the model is
exact (and its derivatives are those of the linear motor) everywhere inside the limit,
where a drive spends most of its time; beyond it the derivative in the command is zero and
the derivative in `voltage_limit` is `+-1`, both the true ones (a smoothed `tanh` clip
would bias every unsaturated sample, by 8 % at half the limit).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._checks import NONNEGATIVE, POSITIVE, as_float_array, check_part

Scalar = Float[Array, ""]

#: The motor's command, per `DCMotor.drive`: its SI unit.
DRIVES = {"voltage": "V", "current": "A", "torque": "N m"}


class DCMotor(eqx.Module):
    """A brushed DC motor (or a brushless one under commutation, seen from its d-q
    terminals) with a gearbox, driving one joint; see the module docstring for the model.

    **Arguments:**
    - `resistance`: armature (terminal) resistance R, ohm.
    - `torque_constant`: K_t, N m/A (= the back-EMF constant K_b, V s/rad).
    - `efficiency`: gear efficiency eta, 0 < eta <= 1 (default 1: a lossless gear).
    - `inductance`: armature inductance L, H; `None` (default): quasi-static current (no
      state). Only with `drive="voltage"`.
    - `viscous`: the motor's viscous friction b_m, N m s/rad, on the motor shaft.
    - `coulomb`: the motor's dry friction c_m, N m, on the motor shaft, smoothed as
      `c_m tanh(w / v_s)`; `None` (default): no term (structure); `0.0`: present, off.
    - `voltage_limit`: V_max, V, the amplifier's supply; `None` (default): no saturation.
    - `drive`: what the joint's input is (static): `"voltage"` (V), `"current"` (A) or
      `"torque"` (N m at the joint, `N K_t i`).
    - `smoothing_velocity`: v_s, rad/s on the motor shaft (static, a numerical choice): the
      scale of the Coulomb `tanh` and of the efficiency's switch. The default, 1 rad/s (10
      rpm, far below a motor's working speeds), keeps the switch wide enough for a fit's
      fixed-step grid: at 0.1 rad/s a fit of a simulated log with `efficiency = 0.9` was
      biased by 20 standard errors in the resistance, at 1 rad/s it was within one.
    """

    resistance: Scalar
    torque_constant: Scalar
    efficiency: Scalar
    inductance: Scalar | None
    viscous: Scalar
    coulomb: Scalar | None
    voltage_limit: Scalar | None
    drive: str = eqx.field(static=True)
    smoothing_velocity: float = eqx.field(static=True)

    def __init__(
        self,
        resistance,
        torque_constant,
        efficiency=1.0,
        inductance=None,
        viscous=0.0,
        coulomb=None,
        voltage_limit=None,
        drive: str = "voltage",
        smoothing_velocity: float = 1.0,
    ):
        if drive not in DRIVES:
            raise ValueError(f"DCMotor.drive: expected one of {', '.join(map(repr, DRIVES))}, got {drive!r}")
        if inductance is not None and drive != "voltage":
            raise ValueError(
                f"DCMotor.inductance: a {drive} amplifier holds the current itself (its loop hides the "
                f"inductance); give an inductance only with drive='voltage', or leave it None"
            )
        try:
            smoothing_velocity = float(smoothing_velocity)
        except (TypeError, ValueError):
            raise ValueError(
                f"DCMotor.smoothing_velocity: expected a number > 0 (rad/s), got {smoothing_velocity!r}"
            ) from None
        if not 0 < smoothing_velocity < float("inf"):
            raise ValueError(
                f"DCMotor.smoothing_velocity: expected a finite number > 0 (rad/s), got {smoothing_velocity!r}"
            )
        self.drive, self.smoothing_velocity = drive, smoothing_velocity
        name = "DCMotor."
        self.resistance = as_float_array(resistance, name + "resistance")
        self.torque_constant = as_float_array(torque_constant, name + "torque_constant")
        self.efficiency = as_float_array(efficiency, name + "efficiency")
        self.inductance = None if inductance is None else as_float_array(inductance, name + "inductance")
        self.viscous = as_float_array(viscous, name + "viscous")
        self.coulomb = None if coulomb is None else as_float_array(coulomb, name + "coulomb")
        self.voltage_limit = None if voltage_limit is None else as_float_array(voltage_limit, name + "voltage_limit")

    PARAMETERS: ClassVar = (
        ("resistance", POSITIVE),
        ("torque_constant", POSITIVE),
        ("efficiency", POSITIVE),
        ("inductance", POSITIVE),
        ("viscous", NONNEGATIVE),
        ("coulomb", NONNEGATIVE),
        ("voltage_limit", POSITIVE),
    )

    def __check_init__(self):
        check_part(self)
        eta = self.efficiency
        if eta.shape == () and not _traced(eta) and not float(eta) <= 1.0:
            raise ValueError(f"DCMotor.efficiency: expected 0 < efficiency <= 1, got {float(eta):g}")

    @property
    def inductive(self) -> bool:
        """True when the current is a state (an inductance is given)."""
        return self.inductance is not None


def _traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def saturated(motor: DCMotor, voltage):
    """The voltage the amplifier applies, V: `clip(voltage, -V_max, V_max)` (`voltage` as is
    without a limit)."""
    if motor.voltage_limit is None:
        return voltage
    return jnp.clip(voltage, -motor.voltage_limit, motor.voltage_limit)


def terminal_voltage(motor: DCMotor, command, motor_speed):
    """The voltage across the armature, V, for the joint's `command` (V, A or N m, per
    `motor.drive`) at the motor shaft's speed `motor_speed` (rad/s): the command itself
    (voltage drive), or the quasi-static voltage `R i_cmd + K_t w` a current amplifier needs
    for its command (`i_cmd = command`, or `command / (N K_t)` for a torque amplifier: pass
    the command already divided by `N`, see `motor_torque`); saturated either way."""
    if motor.drive == "voltage":
        return saturated(motor, command)
    current = command if motor.drive == "current" else command / motor.torque_constant
    return saturated(motor, motor.resistance * current + motor.torque_constant * motor_speed)


def quasi_static_current(motor: DCMotor, voltage, motor_speed):
    """`i = (V - K_t w) / R`, A: the armature current when `L di/dt` is neglected."""
    return (voltage - motor.torque_constant * motor_speed) / motor.resistance


def efficiency_factor(motor: DCMotor, current, motor_speed):
    """`e(x) = eta^tanh(x)`, `x = sign(i) w / v_s` (module docstring): `-> eta` while the
    motor drives, `-> 1/eta` while the load drives it, 1 at rest."""
    x = jnp.sign(current) * motor_speed / motor.smoothing_velocity
    return motor.efficiency ** jnp.tanh(x)


def friction_torque(motor: DCMotor, motor_speed):
    """The motor's own friction on its shaft, N m (opposing `w`): `b_m w + c_m tanh(w / v_s)`."""
    torque = motor.viscous * motor_speed
    if motor.coulomb is not None:
        torque = torque + motor.coulomb * jnp.tanh(motor_speed / motor.smoothing_velocity)
    return torque


def joint_torque(motor: DCMotor, gear_ratio, current, joint_rate):
    """The motor's torque on the joint's actuated coordinate, N m:
    `N e K_t i - N (b_m w + c_m tanh(w / v_s))`, `w = N s_dot`."""
    w = gear_ratio * joint_rate
    electromagnetic = efficiency_factor(motor, current, w) * motor.torque_constant * current
    return gear_ratio * (electromagnetic - friction_torque(motor, w))


def motor_current(motor: DCMotor, gear_ratio, command, joint_rate):
    """The quasi-static armature current, A, for the joint's `command` at `joint_rate`
    (rad/s). Not for an inductive motor (its current is a state)."""
    w = gear_ratio * joint_rate
    if motor.drive == "torque":
        command = command / gear_ratio
    return quasi_static_current(motor, terminal_voltage(motor, command, w), w)


def motor_torque(motor: DCMotor, gear_ratio, command, joint_rate):
    """The joint torque, N m, of a quasi-static motor (no inductance) driven by `command`
    (V, A or N m) at the joint rate `joint_rate` (rad/s)."""
    return joint_torque(motor, gear_ratio, motor_current(motor, gear_ratio, command, joint_rate), joint_rate)


def back_emf_damping(motor: DCMotor, gear_ratio):
    """`N^2 K_t^2 / R`, N m s/rad: the damping on the joint rate, at rest, of a voltage-driven
    motor (quasi-static current) whose terminals are held at a fixed voltage (at speed, a
    gear of efficiency `eta` makes it `N^2 K_t^2 / (eta R)` while the load drives the motor).
    A joint's viscous damping fitted on a model that leaves the motor out includes it, so
    it cannot be less (issue 61: `0.0016` fitted where the back-EMF alone gives `0.0815`)."""
    return gear_ratio**2 * motor.torque_constant**2 / motor.resistance


def mechanical_time_constant(motor: DCMotor, gear_ratio, inertia):
    """`tau_m = J R / (eta N^2 K_t^2)`, s: the time constant of a voltage step's speed
    response of a load of total inertia `J` (kg m^2, at the joint, rotor's `N^2 J_m`
    included) with no friction and no inductance (the motor driving at `|w| >> v_s`)."""
    return inertia * motor.resistance / (motor.efficiency * gear_ratio**2 * motor.torque_constant**2)

"""The physical parts of a planar chain: links, joints, hubs and the payload.

Every part is an `eqx.Module` whose array fields are its physical parameters (SI
units, float64 when x64 is on) and whose integer/boolean fields are structure
(held static by `eqx.filter_jit`). Concrete values are validated when a part
is built; the message names the part and the parameter.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._checks import NONNEGATIVE, POSITIVE, SIGNED, as_float_array, check_part
from .modes import MAX_MODES

Scalar = Float[Array, ""]


def _smoothing(owner: str, name: str, value) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.{name}: expected a number > 0 (a static smoothing scale), got {value!r}") from None
    if not value > 0 or value == float("inf"):
        raise ValueError(f"{owner}.{name}: expected a finite number > 0, got {value!r}")
    return value


def _float(part, name: str, value):
    """`value` as a float array; a non-numeric one is named as `RigidLink.length` is."""
    return as_float_array(value, f"{type(part).__name__}.{name}")


class RigidLink(eqx.Module):
    """A rigid link of the chain.

    **Arguments:**
    - `length`: distance from its joint to the next joint (or the payload), m.
    - `mass`: kg.
    - `com`: position of the centre of mass along the link axis from the joint, m
      (default `length / 2`, a uniform rod; negative for a counterweighted link).
    - `inertia`: rotary inertia about the centre of mass, kg m^2 (default
      `mass * length^2 / 12`, a uniform slender rod).
    - `drag`: aerodynamic (quadratic) drag per unit length, kg/m^2: the air pushes on
      the link with `f(x) = -drag |v_n(x)| v_n(x)` N/m (`drag = rho_air C_d w / 2` for a
      strip of width `w`), `v_n` the velocity normal to the link; see
      `flexdyn.nonlinear.aerodynamic_drag`. `None` (default): no drag term at all
      (structure: the right-hand side does not compute it); `0.0`: present, switched off.
    """

    length: Scalar
    mass: Scalar
    com: Scalar
    inertia: Scalar
    drag: Scalar | None

    def __init__(self, length, mass, com=None, inertia=None, drag=None):
        self.length = _float(self, "length", length)
        self.mass = _float(self, "mass", mass)
        self.com = 0.5 * self.length if com is None else _float(self, "com", com)
        self.inertia = self.mass * self.length**2 / 12.0 if inertia is None else _float(self, "inertia", inertia)
        self.drag = None if drag is None else _float(self, "drag", drag)

    PARAMETERS: ClassVar = (
        ("length", POSITIVE),
        ("mass", POSITIVE),
        ("com", SIGNED),
        ("inertia", NONNEGATIVE),
        ("drag", NONNEGATIVE),
    )

    def __check_init__(self):
        check_part(self)

    @property
    def n_modes(self) -> int:
        return 0


class FlexibleLink(eqx.Module):
    """A uniform Euler-Bernoulli link discretised by `n_modes` clamped-mass assumed modes.

    **Arguments:**
    - `length`: l, m.
    - `rho`: mass per unit length, kg/m (papers' `rho`).
    - `EI`: flexural rigidity, N m^2.
    - `n_modes`: number of assumed modes (structure, static), 1 to 18 (`flexdyn.modes.MAX_MODES`:
      beyond it the clamped-mass frequency equation's roots lose double precision).
    - `damping_ratio`: modal damping ratio per mode (dimensionless), applied as
      `d_j = 2 zeta_j omega_j m_j` with the clamped-mass frequency and generalised
      mass of mode j (so a clamped link decays with exactly this ratio).
    - `sqrt_stiffness_damping`: coefficient `c` of paper 002's structural damping
      `D_j = c sqrt(K_j)` (paper: `c = 0.1`), in sqrt(kg), with our normalisation of
      the shapes (unit mean square, `q` in metres; see `flexdyn.modes`).
    - `drag`: aerodynamic drag per unit length, kg/m^2, as for `RigidLink` (the
      normal velocity includes the elastic rate `v_dot(x)`).
    - `geometric_stiffening`: if True (structure, static), the link's points move inwards
      as it bends, `u(x) = -1/2 int_0^x v'^2`, so that the centreline keeps its length
      (to second order in the deflection). This is what gives a spinning link its
      centrifugal stiffening and a hanging (or standing) link its gravity stiffening
      (softening); see `flexdyn.chain`. Default False: the linear assumed-modes model of
      papers 000/002/004, which has neither, and diverges when a floppy link spins faster
      than its first flexural frequency.
    """

    length: Scalar
    rho: Scalar
    EI: Scalar
    damping_ratio: Float[Array, " n_modes"]
    sqrt_stiffness_damping: Scalar
    drag: Scalar | None
    n_modes: int = eqx.field(static=True)
    geometric_stiffening: bool = eqx.field(static=True)

    def __init__(
        self,
        length,
        rho,
        EI,
        n_modes: int = 2,
        damping_ratio=0.0,
        sqrt_stiffness_damping=0.0,
        drag=None,
        geometric_stiffening: bool = False,
    ):
        if isinstance(n_modes, bool) or not isinstance(n_modes, int) or not 1 <= n_modes <= MAX_MODES:
            raise ValueError(f"FlexibleLink.n_modes: expected an integer from 1 to {MAX_MODES}, got {n_modes!r}")
        if not isinstance(geometric_stiffening, (bool, np.bool_)):
            raise ValueError(f"FlexibleLink.geometric_stiffening: expected True or False, got {geometric_stiffening!r}")
        self.n_modes = n_modes
        self.geometric_stiffening = bool(geometric_stiffening)
        self.length = _float(self, "length", length)
        self.rho = _float(self, "rho", rho)
        self.EI = _float(self, "EI", EI)
        damping_ratio = _float(self, "damping_ratio", damping_ratio)
        if damping_ratio.ndim > 1 or (damping_ratio.ndim == 1 and damping_ratio.shape[0] != n_modes):
            raise ValueError(
                f"FlexibleLink.damping_ratio: expected a scalar or one value per mode (shape ({n_modes},)), "
                f"got shape {damping_ratio.shape}"
            )
        self.damping_ratio = jnp.broadcast_to(damping_ratio, (n_modes,))
        self.sqrt_stiffness_damping = _float(self, "sqrt_stiffness_damping", sqrt_stiffness_damping)
        self.drag = None if drag is None else _float(self, "drag", drag)

    PARAMETERS: ClassVar = (
        ("length", POSITIVE),
        ("rho", POSITIVE),
        ("EI", POSITIVE),
        ("damping_ratio", NONNEGATIVE),
        ("sqrt_stiffness_damping", NONNEGATIVE),
        ("drag", NONNEGATIVE),
    )

    def __check_init__(self):
        check_part(self)

    @property
    def mass(self):
        return self.rho * self.length


class RigidJoint(eqx.Module):
    """A revolute joint whose link angle is driven directly (no elasticity).

    **Arguments:**
    - `damping`: viscous damping on the joint rate, N m s/rad.
    - `rotor_inertia`: inertia of the motor rotor, kg m^2 (motor side).
    - `gear_ratio`: motor angle / joint angle.
    - `spong_approximation`: if True the rotor's kinetic energy is `1/2 G^2 I_r
      theta_dot^2` (its carrier's rotation neglected, as paper 004 eq. 7 does);
      otherwise the exact `1/2 I_r (Omega_carrier + G theta_dot)^2`.
    - `coulomb`: dry (Coulomb) friction torque, N m, smoothed so that gradients exist:
      `-coulomb tanh(theta_dot / coulomb_velocity)` (`flexdyn.nonlinear`). `None`
      (default): no friction term (structure); `0.0`: present, switched off.
    - `coulomb_velocity`: smoothing rate of the friction law, rad/s (a numerical
      choice, static; the law is within 1 % of `sign(theta_dot)` above 2.65x this rate).
    """

    damping: Scalar
    rotor_inertia: Scalar
    gear_ratio: Scalar
    coulomb: Scalar | None
    spong_approximation: bool = eqx.field(static=True)
    coulomb_velocity: float = eqx.field(static=True)

    def __init__(
        self,
        damping=0.0,
        rotor_inertia=0.0,
        gear_ratio=1.0,
        spong_approximation: bool = False,
        coulomb=None,
        coulomb_velocity: float = 0.01,
    ):
        self.damping = _float(self, "damping", damping)
        self.rotor_inertia = _float(self, "rotor_inertia", rotor_inertia)
        self.gear_ratio = _float(self, "gear_ratio", gear_ratio)
        self.spong_approximation = bool(spong_approximation)
        self.coulomb = None if coulomb is None else _float(self, "coulomb", coulomb)
        self.coulomb_velocity = _smoothing("RigidJoint", "coulomb_velocity", coulomb_velocity)

    PARAMETERS: ClassVar = (
        ("damping", NONNEGATIVE),
        ("rotor_inertia", NONNEGATIVE),
        ("gear_ratio", POSITIVE),
        ("coulomb", NONNEGATIVE),
    )

    def __check_init__(self):
        check_part(self)

    @property
    def elastic(self) -> bool:
        return False


class ElasticJoint(eqx.Module):
    """An elastic (geared) joint, paper 004 eq. (7), (21), (43): rotor angle `alpha`
    and link angle `theta` are separate coordinates joined by a torsional spring.

    The input torque acts on the rotor coordinate. `alpha` is the rotor angle
    referred to the link side (motor angle / G), and the input torque is referred to the
    link side too: G times the motor's torque (a logged motor torque must be multiplied
    by G, a motor-side encoder's angle divided by G).

    **Arguments:**
    - `stiffness`: k_s, N m/rad.
    - `rotor_inertia`: I_r, kg m^2 (motor side; reflected inertia `G^2 I_r`).
    - `gear_ratio`: G.
    - `damping`: viscous damping on the rotor rate (bearing, motor), N m s/rad.
    - `spring_damping`: viscous damping across the spring, on `alpha_dot - theta_dot`, N m s/rad.
    - `spong_approximation`: as for `RigidJoint`.
    - `coulomb`, `coulomb_velocity`: dry friction on the rotor rate, as for `RigidJoint`.
    - `backlash`: half-width `b` of the gear's dead zone, rad: the spring acts on the
      smoothed dead zone `dz(delta) = delta - b tanh(delta / b)` of the deflection
      `delta = alpha - theta` (`flexdyn.nonlinear.backlash_deflection`). `None`
      (default): a linear spring (structure); `0.0`: present, switched off.
    """

    stiffness: Scalar
    rotor_inertia: Scalar
    gear_ratio: Scalar
    damping: Scalar
    spring_damping: Scalar
    coulomb: Scalar | None
    backlash: Scalar | None
    spong_approximation: bool = eqx.field(static=True)
    coulomb_velocity: float = eqx.field(static=True)

    def __init__(
        self,
        stiffness,
        rotor_inertia,
        gear_ratio=1.0,
        damping=0.0,
        spring_damping=0.0,
        spong_approximation: bool = False,
        coulomb=None,
        coulomb_velocity: float = 0.01,
        backlash=None,
    ):
        self.stiffness = _float(self, "stiffness", stiffness)
        self.rotor_inertia = _float(self, "rotor_inertia", rotor_inertia)
        self.gear_ratio = _float(self, "gear_ratio", gear_ratio)
        self.damping = _float(self, "damping", damping)
        self.spring_damping = _float(self, "spring_damping", spring_damping)
        self.spong_approximation = bool(spong_approximation)
        self.coulomb = None if coulomb is None else _float(self, "coulomb", coulomb)
        self.backlash = None if backlash is None else _float(self, "backlash", backlash)
        self.coulomb_velocity = _smoothing("ElasticJoint", "coulomb_velocity", coulomb_velocity)

    PARAMETERS: ClassVar = (
        ("stiffness", POSITIVE),
        ("rotor_inertia", POSITIVE),
        ("gear_ratio", POSITIVE),
        ("damping", NONNEGATIVE),
        ("spring_damping", NONNEGATIVE),
        ("coulomb", NONNEGATIVE),
        ("backlash", NONNEGATIVE),
    )

    def __check_init__(self):
        check_part(self)

    @property
    def elastic(self) -> bool:
        return True


class Hub(eqx.Module):
    """The hub at a joint: a point mass at the joint (for joint 2 and beyond it is
    carried at the tip of the previous link, e.g. paper 002's centre motor `M_h2`)
    and a rotary inertia turning with the root of the link it drives.

    **Arguments** (keywords only: `Hub(2e-3)` would read as a mass of 2 g): `mass` (kg),
    `inertia` (kg m^2).
    """

    mass: Scalar
    inertia: Scalar

    def __init__(self, *, mass=0.0, inertia=0.0):
        self.mass = _float(self, "mass", mass)
        self.inertia = _float(self, "inertia", inertia)

    PARAMETERS: ClassVar = (("mass", NONNEGATIVE), ("inertia", NONNEGATIVE))

    def __check_init__(self):
        check_part(self)


class Payload(eqx.Module):
    """A rigid payload at the tip of the last link, turning with the tip's slope.

    **Arguments:** `mass` (kg), `inertia` (kg m^2, about its centre of mass at the tip).
    """

    mass: Scalar
    inertia: Scalar

    def __init__(self, mass=0.0, inertia=0.0):
        self.mass = _float(self, "mass", mass)
        self.inertia = _float(self, "inertia", inertia)

    PARAMETERS: ClassVar = (("mass", NONNEGATIVE), ("inertia", NONNEGATIVE))

    def __check_init__(self):
        check_part(self)

"""The rigs of the three papers, as `Chain`s with their tables' values.

Angle convention for the vertical-plane pendulums: `theta` is measured from the
horizontal base x axis, counter-clockwise positive, gravity is `(0, -9.81) m/s^2`,
so the hanging equilibrium is `theta = -pi/2` and paper 000's releases "from
horizontal" and "from -97 degrees" are `theta0 = 0` and `theta0 = -97 deg`.

OCR'd table values we did not take literally (and why):

- **Paper 000, hub inertia "2x10^5 kg m^2"**: the exponent's minus sign was lost;
  a wire-pot potentiometer hub is ~1e-5 kg m^2 and only `2e-5` gives the paper's
  0.88-0.9 Hz swing of the rigid pendulum released from horizontal (2e5 would stop
  it dead). We use `2e-5 kg m^2`.
- **Paper 000, flexible link mass "0.60 kg"**: a 0.30 x 0.025 x 0.002 m spring-steel
  strip (7850 kg/m^3) has 0.118 kg; 0.60 kg would need a density of 40,000 kg/m^3.
  We use the strip's own mass, `rho = 0.3925 kg/m`, and `E = 200 GPa` (spring
  steel), `I = b h^3 / 12`, so `EI = 3.33 N m^2`. With these values the first
  flexural frequency of the pendulum hinged at its 2e-5 kg m^2 hub is 77.3 Hz (79
  Hz for a frictionless pin, `beta*l = 3.927`; no gravity, converged in the modes)
  while the paper reports 35-37 Hz; the paper's number is what the printed 0.60 kg
  gives (`rho = 2 kg/m`: 35.0 Hz), so the authors' simulation very probably used it.
  `flexible_pendulum(mass=0.60)` reproduces that case; the notebook of the paper
  reproduction shows both.
- **Paper 000, one assumed mode**: the paper uses one, but one clamped-mass mode of a
  link on so light a hub is far from converged: 97.2 Hz instead of 77.3 (+26 %), 46.0
  instead of 35.0 with 0.60 kg (+31 %); two modes give 77.35 / 35.05 Hz (0.1 %), four
  77.26 / 35.01 (`tests/flexdyn/test_chain.py` holds them against the hub-beam
  frequency equation). The paper's reported 35-37 Hz is the converged value, so
  `flexible_pendulum` defaults to two modes.
- **Paper 000, rigid link 0.180 kg**: consistent with carbon steel 0.30 x 0.018 x
  0.004 m (0.170 kg) and kept.
- **Paper 002**: Table I reads cleanly. The payload's rotary inertia is not given;
  we take a point mass (`J_P = 0`).
- **Paper 004**: Table 1 reads cleanly. It gives no centre-hub mass and no modal
  damping values; eq. (47) has no hub mass, so we use none (`hub2_mass=0`, paper
  002's value is 1 kg), and we use paper 002's structural damping `D = 0.1 sqrt(K)`
  since the paper's rigid-joint responses decay. Its rotor kinetic energy (eq. 7)
  neglects the carrier's rotation (Spong's approximation), which we follow.
"""

from __future__ import annotations

from .chain import Chain
from .parts import ElasticJoint, FlexibleLink, Hub, Payload, RigidJoint, RigidLink

STANDARD_GRAVITY = 9.81  # m/s^2, as the papers use

#: Spring steel, paper 000's flexible link.
SPRING_STEEL_DENSITY = 7850.0  # kg/m^3
SPRING_STEEL_YOUNG = 200e9  # Pa


def rigid_pendulum(joint_damping=1.9e-3, payload_mass=0.020, hub_inertia=2e-5) -> Chain:
    """Paper 000's rigid pendulum (Table 1, eq. 7): carbon-steel link 0.30 m, 0.180 kg,
    hub inertia 2e-5 kg m^2, accelerometer payload 0.020 kg at the tip, joint viscous
    damping 1.9e-3 N m s (the paper's log-decrement estimate), vertical plane."""
    return Chain(
        links=[RigidLink(length=0.30, mass=0.180)],
        joints=[RigidJoint(damping=joint_damping)],
        hubs=[Hub(inertia=hub_inertia)],
        payload=Payload(mass=payload_mass),
        gravity=(0.0, -STANDARD_GRAVITY),
    )


def flexible_pendulum(
    n_modes=2,
    mass=None,
    joint_damping=1.9e-3,
    damping_ratio=0.0,
    hub_inertia=2e-5,
    payload_mass=0.0,
    geometric_stiffening=False,
) -> Chain:
    """Paper 000's flexible pendulum (Table 1, eq. 10): spring-steel strip 0.30 x 0.025
    x 0.002 m, hinged at a hub of 2e-5 kg m^2, vertical plane, `n_modes` assumed
    modes (the paper uses one; one clamped-mass mode puts the first flexural frequency
    26 % high on this light hub, two within 0.1 %: see the module docstring).

    `mass` (kg) overrides the strip's mass from its dimensions (0.118 kg); see the
    module docstring for why the printed 0.60 kg is not the default. `damping_ratio`
    is the modal damping ratio (the paper gives no value). `geometric_stiffening`: see
    `FlexibleLink` (the paper's model has none; its weight then stiffens the hanging strip).
    """
    width, thickness, length = 0.025, 0.002, 0.30
    rho = SPRING_STEEL_DENSITY * width * thickness if mass is None else mass / length
    EI = SPRING_STEEL_YOUNG * width * thickness**3 / 12.0
    return Chain(
        links=[
            FlexibleLink(
                length=length,
                rho=rho,
                EI=EI,
                n_modes=n_modes,
                damping_ratio=damping_ratio,
                geometric_stiffening=geometric_stiffening,
            )
        ],
        joints=[RigidJoint(damping=joint_damping)],
        hubs=[Hub(inertia=hub_inertia)],
        payload=Payload(mass=payload_mass),
        gravity=(0.0, -STANDARD_GRAVITY),
    )


def _papers_002_004_link(n_modes, structural_damping, geometric_stiffening) -> FlexibleLink:
    """The flexible link of papers 002 and 004 (Table I / Table 1): l = 0.5 m, rho = 0.2
    kg/m, EI = 1.0 N m^2, structural damping D = `structural_damping` * sqrt(K)."""
    return FlexibleLink(
        length=0.5,
        rho=0.2,
        EI=1.0,
        n_modes=n_modes,
        sqrt_stiffness_damping=structural_damping,
        geometric_stiffening=geometric_stiffening,
    )


def two_link_flexible_arm(
    payload_mass=0.0, payload_inertia=0.0, n_modes=2, structural_damping=0.1, geometric_stiffening=False
) -> Chain:
    """Paper 002's two-link flexible arm in the horizontal plane (Table I): both links
    l = 0.5 m, rho = 0.2 kg/m, EI = 1.0 N m^2; motor and hub inertia J_h = 0.02 kg m^2
    at both joints (gear ratio 1, so rotor and hub turn with the link); centre motor
    mass M_h2 = 1 kg; payload `payload_mass` (0-0.1 kg in the paper) at the tip;
    structural damping D = `structural_damping` * sqrt(K) (paper: 0.1). `geometric_stiffening`:
    see `FlexibleLink` (not in the paper's model)."""
    link = _papers_002_004_link(n_modes, structural_damping, geometric_stiffening)
    return Chain(
        links=[link, link],
        joints=[RigidJoint(), RigidJoint()],
        hubs=[Hub(inertia=0.02), Hub(mass=1.0, inertia=0.02)],
        payload=Payload(mass=payload_mass, inertia=payload_inertia),
        gravity=(0.0, 0.0),
    )


def flexible_link_joint_arm(
    rigid_joints=False,
    joint_stiffness=100.0,
    n_modes=2,
    structural_damping=0.1,
    payload_mass=0.1,
    payload_inertia=0.005,
    hub2_mass=0.0,
    geometric_stiffening=False,
) -> Chain:
    """Paper 004's two-link arm with flexible links and flexible joints (Table 1):
    l = 0.5 m, rho = 0.2 kg/m, EI = 1.0 N m^2, rotor and hub inertia I_r = 0.02 kg m^2,
    gear ratio 1, joint stiffness k_s = 100 N m/rad, payload 0.1 kg and 0.005 kg m^2,
    horizontal plane. `rigid_joints=True` gives the flexible-link/rigid-joint model of
    eq. (55) that the paper compares with (k_s -> infinity). `geometric_stiffening`: see
    `FlexibleLink` (not in the paper's model)."""
    link = _papers_002_004_link(n_modes, structural_damping, geometric_stiffening)
    if rigid_joints:
        joints = [RigidJoint(rotor_inertia=0.02, spong_approximation=True) for _ in range(2)]
    else:
        joints = [
            ElasticJoint(stiffness=joint_stiffness, rotor_inertia=0.02, spong_approximation=True) for _ in range(2)
        ]
    return Chain(
        links=[link, link],
        joints=joints,
        hubs=[Hub(), Hub(mass=hub2_mass)],
        payload=Payload(mass=payload_mass, inertia=payload_inertia),
        gravity=(0.0, 0.0),
    )

"""The elastic joint's start aimed at a frequency the logs can show (`aim_joint_mode`).

`catalogue.structural_model` puts the `joint_elasticity` spring's first guess where the rotor on
its spring, against a locked link, rings at the search's `max_frequency_hz`:
`k = J_rotor (2 pi f)^2`. The link is not locked: the joint mode of a rotor `J_rotor` on a
spring `k` against a free link `J_link` is `omega^2 = k (1/J_rotor + 1/J_link)`. Behind a gear
the reflected rotor inertia is often 10-1000x the link's, and that start rings
`sqrt(J_rotor / J_link)` times higher: kHz above the logs' Nyquist frequency, a start the logs
cannot show and the solver needs hundreds of thousands of steps for (seen on a geared servo's
logs: 10-16 minutes before the fit failed on the step limit). Such a start is moved down to
`max_frequency_hz`; one the logs can show (at or below Nyquist) is kept.
"""

from __future__ import annotations

import math

import numpy as np

import flexdyn as fd

#: `aim_joint_mode` stops when the joint mode is within this relative distance of its target
AIM_TOLERANCE = 0.02

#: `aim_joint_mode`'s iterations at most (a two-inertia joint needs one: `omega^2 ~ k`)
AIM_ITERATIONS = 8


def joint_mode(chain: fd.Chain, index: int) -> tuple[float, float]:
    """The natural frequency (Hz) of the mode of elastic joint `index` (from 1) about
    `flexdyn.modal_configuration(chain)`, and the share of that mode's potential energy its
    spring holds. The joint mode is the mode whose mass-normalised shape `v` (`K v = omega^2
    M v`, `flexdyn.modal_analysis`) puts the largest share `k (v_alpha - v_theta)^2 /
    omega^2` of its energy `v^T K v = omega^2` into the spring (deflection `alpha - theta`,
    link side; the joint's `gear_ratio` is 1 in a `joint_elasticity` candidate's model).
    `(0, 0)` for a chain without a mode of positive frequency."""
    lay = chain.layout
    i = index - 1
    rotor, theta = lay.rotor[i], lay.theta[i]
    if rotor is None:
        raise ValueError(f"joint_mode: joint{index} is rigid (no rotor coordinate)")
    Q0, _ = fd.modal_configuration(chain)
    modes = fd.modal_analysis(chain, Q0)
    f = np.asarray(modes.natural_frequency, float)
    shapes = np.asarray(modes.shapes, float)
    k = float(np.asarray(chain.joints[i].stiffness))
    w2 = (2 * math.pi * f) ** 2
    positive = f > 0
    if not np.any(positive):
        return 0.0, 0.0
    share = np.where(positive, k * (shapes[rotor] - shapes[theta]) ** 2 / np.where(positive, w2, 1.0), -1.0)
    j = int(np.argmax(share))
    return float(f[j]), float(share[j])


def aim_joint_mode(chain: fd.Chain, index: int, *, target_hz: float, nyquist_hz: float) -> fd.Chain:
    """`chain` with the stiffness of elastic joint `index` (from 1) lowered so that its joint
    mode (`joint_mode`, the link free) rings at `target_hz`, when it rings above `nyquist_hz`
    (the logs cannot show it; the solver pays for it); otherwise unchanged. The stiffness is
    scaled by `(target / f)^2` until the mode is within `AIM_TOLERANCE` of the target (exact in
    one step for a two-inertia joint, whose `omega^2` is proportional to `k`), at most
    `AIM_ITERATIONS` times; never raised."""
    if not (0 < target_hz <= nyquist_hz):
        raise ValueError(
            f"aim_joint_mode: target_hz expected in (0, nyquist_hz = {nyquist_hz:g}] Hz, got {target_hz!r}"
        )
    name = f"joint{index}.stiffness"
    k0 = k = float(np.asarray(chain.joints[index - 1].stiffness))
    chain = fd.with_parameters(chain, {name: k})  # (an array: one compiled modal analysis for every k)
    f, _ = joint_mode(chain, index)
    if not f > nyquist_hz:
        return chain
    for _ in range(AIM_ITERATIONS):
        if abs(f / target_hz - 1.0) <= AIM_TOLERANCE:
            break
        k = min(k0, k * (target_hz / f) ** 2)
        chain = fd.with_parameters(chain, {name: k})
        f, _ = joint_mode(chain, index)
    return chain

r"""How much geometric stiffening a link's first mode would see: a first-order estimate.

A model built with the linear assumed-modes links of papers 000/002/004 (the default,
`FlexibleLink(geometric_stiffening=False)`) has no axial load in its bending stiffness.
`first_mode_stiffening(chain)` says, for every flexible link, how far that leaves the
first clamped-mass mode off when the link spins at `Omega` (rad/s) about its root or
carries gravity `g_axial` (m/s^2, positive pulling from the root towards the tip, as on a
hanging link):

    omega_1^2 (with stiffening) - omega_1^2 (without) = spin Omega^2 + gravity g_axial,

    spin    = [H1 + (M l + S) G(l)]_11 / m_1,
    gravity = [H0 + M G(l)]_11 / m_1,

to first order in `Omega^2` and `g` (the Rayleigh quotient of the geometric stiffness on
the unperturbed clamped-mass mode, exact to that order because the mode is an exact
eigenfunction of the clamped-mass beam). `G(x) = int_0^x phi' phi'^T`, `H0 = int rho
G(x) dx`, `H1 = int rho x G(x) dx` are the shortening integrals of `flexdyn.chain`
(`LinkMatrices.shortening*`), `M, S` the mass and first moment of everything distal to
the link (`flexdyn.tip_load`), and `m_1` the first mode's generalised mass including
them. The centrifugal tension of a link spinning about its root is
`N(x) = Omega^2 (rho (l^2 - x^2)/2 + M l + S)`; gravity along the link gives
`N(x) = g_axial (rho (l - x) + M)`; the energy `1/2 int N v'^2 dx` is `1/2 q^T (...) q`
with the matrices above.

For a uniform link without tip load `spin = 1.1933`, Southwell's coefficient of the
rotating cantilever (the in-plane mode of the linear model already softens by
`-Omega^2`; the stiffening it leaves out is this `+1.1933 Omega^2`). Checked against a
Rayleigh-Ritz solution of the axially loaded cantilever in
`tests/flexdyn/test_stiffening.py`.

What it leaves out: the other modes and second-order terms. The tension from the root's
own motion on a chain (a distal link mounted at radius `R` on a spinning link feels its
root's centripetal acceleration `Omega^2 R` like gravity along it) is the caller's to add
through `axial_gravity` (`identify.evidence.stiffening_checks` does). It is a screening number: `identify.diagnose`
uses it to say when a fitted EI is biased by the missing stiffening (a linear model
fitted to a link spinning at `Omega` absorbs it into EI, about `spin (Omega /
omega_1)^2` too high).
"""

from __future__ import annotations

import dataclasses
import typing

from .chain import Chain, assemble
from .parts import FlexibleLink


class FirstModeStiffening(typing.NamedTuple):
    """First-order geometric stiffening of one link's first clamped-mass mode (module
    docstring): `omega_1^2` gains `spin Omega^2 + gravity g_axial`."""

    frequency: float  # omega_1, the first clamped-mass natural frequency, rad/s
    spin: float  # dimensionless (Southwell coefficient)
    gravity: float  # 1/m

    def relative_shift(self, spin_rate: float = 0.0, axial_gravity: float = 0.0) -> float:
        """`(omega_1^2 with - without) / omega_1^2` at spin rate `spin_rate` (rad/s) and
        axial gravity `axial_gravity` (m/s^2, positive pulling outwards)."""
        return (self.spin * spin_rate**2 + self.gravity * axial_gravity) / self.frequency**2


def _stiffened(link):
    if not isinstance(link, FlexibleLink):
        return link
    return dataclasses.replace(link, geometric_stiffening=True)  # FlexibleLink's fields are its arguments


def first_mode_stiffening(chain: Chain) -> dict[str, FirstModeStiffening]:
    """`{"link<i>": FirstModeStiffening}` for every flexible link `i` of `chain` (1-based,
    as in parameter names), whether or not the link has `geometric_stiffening` on. See the
    module docstring for the formula and what it leaves out."""
    if not isinstance(chain, Chain):
        raise TypeError(f"first_mode_stiffening: expected a flexdyn.Chain, got {type(chain).__name__}")
    if not any(isinstance(k, FlexibleLink) for k in chain.links):
        return {}
    stiffened = Chain(
        [_stiffened(k) for k in chain.links], chain.joints, chain.hubs, chain.payload, chain.gravity, chain.motors
    )
    asm = assemble(stiffened)
    out = {}
    for i, (link, lm) in enumerate(zip(stiffened.links, asm.links)):
        if not isinstance(link, FlexibleLink):
            continue
        M, S, J = lm.tip_load[0], lm.tip_load[1], lm.tip_load[2]
        phi, slope = lm.tip_shape[0], lm.tip_slope[0]
        m1 = lm.modal_mass[0, 0] + M * phi**2 + 2.0 * S * phi * slope + J * slope**2
        g11 = lm.shortening[0, 0]
        spin = (lm.shortening_moment[0, 0] + (M * lm.length + S) * g11) / m1
        gravity = (lm.shortening_mass[0, 0] + M * g11) / m1
        out[f"link{i + 1}"] = FirstModeStiffening(float(lm.frequency[0]), float(spin), float(gravity))
    return out

"""The `phi{i}` output channel (absolute angle of link i in the base frame) against an
independent oracle: the direction of the link's chord from positions alone.

For a rigid link i, its root frame points from joint i to joint i+1, so
`phi_i = atan2(o_{i+1} - o_i)`. The joint positions come from `flexdyn.end_point`
(position kinematics only; the channel reads the frames' angle recursion, a different
code path that adds the joint angles and tip slopes).
"""

import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
from identify._data import channels as ch, units as u
from identify._data.logs import load_log


def _wrapped(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _chord_angle(chain_prefix, chain_longer, Q_prefix, Q_longer):
    """Angle of the segment from the end of `chain_prefix` to the end of `chain_longer`."""
    a = np.asarray(fd.end_point(chain_prefix, Q_prefix))
    b = np.asarray(fd.end_point(chain_longer, Q_longer))
    d = b - a
    return np.arctan2(d[1], d[0])


def _evaluate(chain, channels, Q):
    asm = fd.assemble(chain)
    y = jnp.concatenate([jnp.asarray(Q), jnp.zeros_like(jnp.asarray(Q))])
    zero = lambda t, y: jnp.zeros(chain.n_links)  # noqa: E731
    return np.asarray(ch.evaluate(asm, channels, jnp.zeros(()), y, zero))


@pytest.mark.parametrize("Q", [(0.3, -1.1), (2.9, 0.7), (-2.5, 3.0)])
def test_absolute_angles_of_a_rigid_double_pendulum(Q):
    link1 = fd.RigidLink(length=0.17, mass=0.09, com=0.11, inertia=4e-4)
    link2 = fd.RigidLink(length=0.23, mass=0.14, com=0.12, inertia=1e-3)
    two = fd.Chain([link1, link2], gravity=(-9.81, 0.0))
    one = fd.Chain([link1], gravity=(-9.81, 0.0))
    phi1, phi2 = _evaluate(two, ("phi1", "phi2"), Q)
    # link 1's chord from the base origin, link 2's from joint 2
    oracle1 = np.arctan2(*np.asarray(fd.end_point(one, jnp.asarray(Q[:1])))[::-1])
    oracle2 = _chord_angle(one, two, jnp.asarray(Q[:1]), jnp.asarray(Q))
    assert abs(_wrapped(phi1 - oracle1)) < 1e-12
    assert abs(_wrapped(phi2 - oracle2)) < 1e-12
    # and it is the sum of the relative joint angles (the conversion the data need)
    assert abs(_wrapped(phi2 - (Q[0] + Q[1]))) < 1e-12


def test_absolute_angle_after_a_flexible_link_includes_its_tip_slope():
    flex = fd.FlexibleLink(length=0.3, rho=0.4, EI=3.3, n_modes=2)
    rigid = fd.RigidLink(length=0.2, mass=0.05)
    two = fd.Chain([flex, rigid])
    Q = jnp.asarray([0.4, 0.01, -0.004, 0.9])  # theta1, q1_1, q1_2, theta2
    phi2 = _evaluate(two, ("phi2",), Q)[0]
    # The mode shapes of link 1 depend on what it carries, so joint 2 is located in this
    # chain itself: the end point turns about it on a circle as theta2 changes, and the
    # ends at theta2 and theta2 + pi are diametrically opposite.
    end = np.asarray(fd.end_point(two, Q))
    opposite = np.asarray(fd.end_point(two, Q.at[3].add(np.pi)))
    joint2 = 0.5 * (end + opposite)
    oracle = np.arctan2(*(end - joint2)[::-1])
    assert abs(_wrapped(phi2 - oracle)) < 1e-12
    # the slope matters here: without it the angle would be off by more than 0.01 rad
    assert abs(_wrapped(phi2 - (0.4 + 0.9))) > 1e-2


def test_phi_channel_vocabulary(tmp_path):
    assert u.channel_dimension("phi2") == u.ANGLE
    assert u.is_output("phi1")
    two = fd.Chain([fd.RigidLink(length=0.2, mass=0.1)] * 2)
    ch.check_channel(two, "phi2")
    with pytest.raises(ValueError, match="no link/joint 3"):
        ch.check_channel(two, "phi3")
    path = tmp_path / "swing.csv"
    path.write_text("time [s],phi1 [deg],phi2 [deg]\n" + "".join(f"{0.01 * k},180,{90 + k}\n" for k in range(12)))
    log = load_log(path)
    np.testing.assert_allclose(log.outputs["phi2"], np.radians(90.0 + np.arange(12)), rtol=1e-15)

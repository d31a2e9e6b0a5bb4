"""Measurement channels: the model outputs a log can record, by name.

| name           | quantity                                   | unit   |
| -------------- | ------------------------------------------ | ------ |
| `theta{i}`     | link angle of joint i                      | rad    |
| `phi{i}`       | absolute angle of link i in the base frame | rad    |
| `alpha{i}`     | rotor angle of (elastic) joint i           | rad    |
| `tip{i}`       | elastic tip deflection v_i(l_i) of link i  | m      |
| `curvature{i}` | root curvature v_i''(0) of link i          | 1/m    |
| `end_x`, `end_y` | end-point position in the base frame     | m      |
| `accel_x`, `accel_y` | end-point acceleration               | m/s^2  |

Inputs: `torque{i}`, N m, the torque of joint i.

`phi{i}` is the angle of link i's root frame from the base x axis (`flexdyn.kinematics.frames`):
`phi_1 = theta_1`, `phi_i = phi_{i-1} + v_{i-1}'(l_{i-1}) + theta_i` (the tip slope of a
flexible link i-1 turns the next joint's frame). Encoders that read each link against
gravity or the base rather than against the previous link (e.g. the double pendulum of
`identify/examples/real_double_pendulum`) record `phi`, not `theta`.
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp

import flexdyn as fd
from flexdyn.kinematics import frames

from . import units as u

_CHANNEL = re.compile(r"^(theta|phi|alpha|tip|curvature)(\d+)$|^(end|accel)_(x|y)$")

UNITS = {
    "theta": "rad",
    "phi": "rad",
    "alpha": "rad",
    "tip": "m",
    "curvature": "1/m",
    "end": "m",
    "accel": "m/s^2",
}


def channel_problem(chain: fd.Chain, channel: str) -> str | None:
    """None if `chain` has the channel `channel` (an output or `torque<i>`), else why not
    (naming what the rig has)."""
    if u.channel_dimension(channel) is None:
        return f"{channel!r} is not a channel; expected time or one of {u.CHANNEL_PATTERNS}"
    if u.is_reference(channel):
        return channel_problem(chain, u.referenced_channel(channel))
    kind, i = u.channel_kind_index(channel)
    if i is None:
        return None
    n = chain.n_links
    if i > n:
        return f"the rig has {n} link(s) ({describe(chain)}); there is no link/joint {i}"
    if kind == "alpha" and not chain.joints[i - 1].elastic:
        return f"joint {i} is rigid (no rotor angle alpha{i}); the rig has {describe(chain)}"
    if kind in ("tip", "curvature") and chain.links[i - 1].n_modes == 0:
        return f"link {i} is rigid (no deflection); the rig has {describe(chain)}"
    if kind in u.INPUT_KINDS:
        return input_problem(chain, kind, i)
    return None


def input_problem(chain: fd.Chain, kind: str, i: int) -> str | None:
    """None if joint `i` of `chain` is driven by an input of `kind` (`torque`: a joint
    without a motor, or a motor behind a torque amplifier; `voltage`, `current`: a motor
    with that drive), else why not."""
    motor = chain.motors[i - 1]
    drive = "torque" if motor is None else motor.drive
    if kind == drive:
        return None
    if motor is None:
        return (
            f"joint {i} has no motor, so its input is a torque (torque{i}); a {kind} drives a motor: give joint {i} "
            f'one with [rig.motors.joint{i}] (drive = "{kind}")'
        )
    return (
        f"joint {i}'s motor is driven by {drive} (its input is {drive}{i}, {fd.motor.DRIVES[drive]}), not by "
        f'{kind}; map the log\'s {drive} column to {drive}{i}, or set drive = "{kind}" in [rig.motors.joint{i}]'
    )


def input_name(chain: fd.Chain, j: int) -> str:
    """The input channel of joint `j` (0-based): `torque<j+1>`, or its motor's drive
    (`voltage<j+1>`, `current<j+1>`)."""
    motor = chain.motors[j]
    return f"{'torque' if motor is None else motor.drive}{j + 1}"


def is_output(name: str) -> bool:
    """Whether `name` is a recorded output channel (a sensor's), not an input such as a
    closed-loop log's command (`torque1`, `voltage1`)."""
    return _CHANNEL.match(name) is not None


def check_channel(chain: fd.Chain, name: str) -> None:
    """Raise `ValueError` if `name` is not an output channel this chain has."""
    why = channel_problem(chain, name)
    if why is None and u.is_input(name):
        why = f"{name!r} is an input, not an output channel"
    if why is not None:
        raise ValueError(f"output channel {name!r}: {why}")


def describe(chain: fd.Chain) -> str:
    """One line describing the chain's structure, for error messages."""
    parts = []
    for i, (link, joint) in enumerate(zip(chain.links, chain.joints), start=1):
        lk = f"flexible link {i} ({link.n_modes} modes)" if link.n_modes else f"rigid link {i}"
        parts.append(f"{'elastic' if joint.elastic else 'rigid'} joint {i} + {lk}")
    return ", ".join(parts)


def state_names(chain: fd.Chain) -> list[str]:
    """Names of the entries of the state `y = [Q, Q_dot]`: coordinates then `<coord>_rate`."""
    names = chain.coordinate_names()
    return names + [f"{n}_rate" for n in names]


def channel_unit(name: str) -> str:
    """SI unit of an output channel, or of an input channel (a closed-loop log's command)."""
    m = _CHANNEL.match(name)
    if m is None and u.is_input(name):
        return u.SI_UNIT[u.channel_dimension(name)]
    return UNITS[m[1] or m[3]]


def state_unit(entry: str) -> str:
    """SI unit of a state entry (`state_names`): joint and rotor angles (`theta1`,
    `alpha1`) in rad, modal coordinates (`q1_1`: the RMS deflection of the mode over its link,
    `flexdyn.modes`) in m, and their `_rate`s per second."""
    base, rate = (entry[: -len("_rate")], True) if entry.endswith("_rate") else (entry, False)
    unit = "m" if re.fullmatch(r"q\d+_\d+", base) else "rad"
    return f"{unit}/s" if rate else unit


def needs_acceleration(channels) -> bool:
    return any(c.startswith("accel_") for c in channels)


def evaluate(asm: fd.AssembledChain, channels: tuple[str, ...], t, y, torque):
    """Values of `channels` at one time `t` and state `y` (SI), shape (len(channels),)."""
    lay = asm.layout
    n = lay.n_dof
    Q, Qd = y[:n], y[n:]
    values = []
    tips = curv = end = acc = angles = None
    for name in channels:
        m = _CHANNEL.match(name)
        if m[1]:
            kind, i = m[1], int(m[2]) - 1
            if kind == "theta":
                values.append(Q[lay.theta[i]])
            elif kind == "phi":
                angles = frames(asm, Q).angle if angles is None else angles
                values.append(angles[i])
            elif kind == "alpha":
                values.append(Q[lay.rotor[i]])
            elif kind == "tip":
                tips = fd.tip_deflections(asm, Q) if tips is None else tips
                values.append(tips[i])
            else:
                curv = fd.root_curvatures(asm, Q) if curv is None else curv
                values.append(curv[i])
        elif m[3] == "end":
            end = fd.end_point(asm, Q) if end is None else end
            values.append(end[0 if m[4] == "x" else 1])
        else:
            if acc is None:
                Qdd = fd.accelerations(asm, Q, Qd, torque(t, y))
                pos = lambda Q_: fd.end_point(asm, Q_)  # noqa: E731
                vel = lambda Q_: jax.jvp(pos, (Q_,), (Qd,))[1]  # noqa: E731
                acc = jax.jvp(pos, (Q,), (Qdd,))[1] + jax.jvp(vel, (Q,), (Qd,))[1]
            values.append(acc[0 if m[4] == "x" else 1])
    return jnp.stack(values)

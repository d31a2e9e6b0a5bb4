"""Measurement channels: the model outputs a log can record, by name.

| name           | quantity                                   | unit   |
| -------------- | ------------------------------------------ | ------ |
| `theta{i}`     | link angle of joint i                      | rad    |
| `alpha{i}`     | rotor angle of (elastic) joint i           | rad    |
| `tip{i}`       | elastic tip deflection v_i(l_i) of link i  | m      |
| `curvature{i}` | root curvature v_i''(0) of link i          | 1/m    |
| `end_x`, `end_y` | end-point position in the base frame     | m      |
| `accel_x`, `accel_y` | end-point acceleration               | m/s^2  |

Inputs: `torque{i}`, N m, the torque of joint i.
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp

import flexdyn as fd

_CHANNEL = re.compile(r"^(theta|alpha|tip|curvature)(\d+)$|^(end|accel)_(x|y)$")

UNITS = {"theta": "rad", "alpha": "rad", "tip": "m", "curvature": "1/m", "end": "m", "accel": "m/s^2"}


def check_channel(chain: fd.Chain, name: str) -> None:
    """Raise `ValueError` if `name` is not an output this chain has."""
    m = _CHANNEL.match(name)
    if m is None:
        raise ValueError(
            f"unknown output channel {name!r}: expected theta<i>, alpha<i>, tip<i>, curvature<i>, "
            "end_x, end_y, accel_x or accel_y"
        )
    if m[1]:
        kind, i = m[1], int(m[2])
        if not 1 <= i <= chain.n_links:
            raise ValueError(f"output channel {name!r}: the rig has {chain.n_links} link(s)")
        if kind == "alpha" and not chain.joints[i - 1].elastic:
            raise ValueError(f"output channel {name!r}: joint {i} is rigid (no rotor angle)")
        if kind in ("tip", "curvature") and chain.links[i - 1].n_modes == 0:
            raise ValueError(f"output channel {name!r}: link {i} is rigid (no deflection)")


def channel_unit(name: str) -> str:
    m = _CHANNEL.match(name)
    return UNITS[m[1] or m[3]]


def needs_acceleration(channels) -> bool:
    return any(c.startswith("accel_") for c in channels)


def evaluate(asm: fd.AssembledChain, channels: tuple[str, ...], t, y, torque):
    """Values of `channels` at one time `t` and state `y` (SI), shape (len(channels),)."""
    lay = asm.layout
    n = lay.n_dof
    Q, Qd = y[:n], y[n:]
    values = []
    tips = curv = end = acc = None
    for name in channels:
        m = _CHANNEL.match(name)
        if m[1]:
            kind, i = m[1], int(m[2]) - 1
            if kind == "theta":
                values.append(Q[lay.theta[i]])
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

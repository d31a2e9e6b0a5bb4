"""Fixtures shared by the identification tests."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
import identify
import identify._model.parameters as parameters_module

# per log: free initial-state entries, free offsets (log 1: none of either)
FIT_INITIAL = [("theta1", "theta1_rate"), (), ("theta1_rate",)]
OFFSETS = [("theta1",), (), ("theta1", "end_x")]


@pytest.fixture(scope="module")
def multilog_problem():
    """Three rigid-pendulum logs of different lengths, channels and nuisance layouts (log 1
    estimates nothing), two free parameters: `(problem, x, y0_free, offset_free)`."""
    truth = fd.rigs.rigid_pendulum(joint_damping=3e-3)
    chain = fd.rigs.rigid_pendulum(joint_damping=2e-3)
    logs = []
    for l in range(3):
        t = np.arange(80 + 20 * l) * 5e-3
        logs.append(
            identify.simulate_log(
                truth,
                t,
                initial={"theta1": 0.4 + 0.1 * l},
                torque=0.01 * np.sin(3 * t)[:, None],
                channels=("theta1", "end_x") if l == 2 else ("theta1",),
                noise={"theta1": 1e-3, "end_x": 1e-4},
                rng=np.random.default_rng(l),
                fit_initial=FIT_INITIAL[l],
                offsets=OFFSETS[l],
                name=f"drop{l}",
            )
        )
    params = [
        identify.Parameter("joint1.damping", 2e-3, 1e-6, 1.0),
        identify.Parameter("payload.mass", 0.03, 1e-3, 1.0),
    ]
    p = identify.make_problem(chain, params, logs, {"theta1": 1e-3, "end_x": 1e-4})
    x = jnp.asarray(parameters_module.x_from_theta(p, [q.guess for q in params]))
    y0 = jnp.asarray([0.41, 0.05, -0.02])
    off = jnp.asarray([1e-3, -2e-3, 5e-4])
    return p, x, y0, off

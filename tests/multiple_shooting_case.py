"""A long open-loop log of a lightly damped flexible link, replayed in simulation: the
scenario of `tests/identify/test_multiple_shooting.py` and
`benchmarks/bench_multiple_shooting.py`.

The link of `tests/identify/test_fit.py` (horizontal plane) driven by a torque doublet of
random sign and size (0.02-0.06 N m, 0.1 s each way) every second, `theta1` and `tip1`
logged at 4 ms with white noise of 1 % of each channel's RMS. The hub drifts after each
doublet (no spring holds it) and the flexible mode rings lightly damped."""

from __future__ import annotations

import numpy as np

import flexdyn as fd
import identify

TRUTH = {"link1.EI": 1.0, "joint1.damping": 0.005, "hub1.inertia": 0.02, "payload.mass": 0.05}
DT = 4e-3
CHANNELS = ("theta1", "tip1")


def chain() -> fd.Chain:
    return fd.Chain(
        [fd.FlexibleLink(0.5, 0.2, TRUTH["link1.EI"], n_modes=1, damping_ratio=0.02)],
        joints=[fd.RigidJoint(damping=TRUTH["joint1.damping"])],
        hubs=[fd.Hub(inertia=TRUTH["hub1.inertia"])],
        payload=fd.Payload(mass=TRUTH["payload.mass"]),
    )


def doublet_train(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A doublet (+a for 0.1 s, -a for 0.1 s) at every whole second, `a` of random sign and
    size in [0.02, 0.06] N m; `(T, 1)`."""
    tau = np.zeros_like(t)
    for start in np.arange(0.0, t[-1] - 0.4, 1.0):
        a = rng.uniform(0.02, 0.06) * rng.choice([-1, 1])
        tau[(t >= start) & (t < start + 0.1)] = a
        tau[(t >= start + 0.1) & (t < start + 0.2)] = -a
    return tau[:, None]


def long_log(duration: float, seed: int = 5) -> tuple[identify.LogData, dict]:
    """The noisy log of `duration` s and its noise levels (SI, by channel)."""
    t = np.arange(0.0, duration, DT)
    rng = np.random.default_rng(seed)
    tau = doublet_train(t, rng)
    clean = identify.simulate_log(chain(), t, torque=tau, channels=CHANNELS)
    noise = {c: 0.01 * float(np.sqrt(np.mean(v**2))) for c, v in clean.outputs.items()}
    log = identify.simulate_log(chain(), t, torque=tau, channels=CHANNELS, noise=noise, rng=rng)
    return log, noise


def problem_of(log: identify.LogData, noise: dict, factors: dict) -> identify.Problem:
    """The four parameters free, guesses the truth times `factors` (by name; 1 elsewhere),
    bounds truth x [1e-2, 1e2]."""
    params = [identify.Parameter(n, v * factors.get(n, 1.0), v * 1e-2, v * 1e2) for n, v in TRUTH.items()]
    return identify.make_problem(chain(), params, [log], noise=noise)
